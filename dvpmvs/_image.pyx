# cython: language_level=3
"""Private image kernels; use the documented wrappers in :mod:`dvpmvs.image`."""

from cython.parallel cimport prange

from dvpmvs._sampling cimport bilinear

from dvpmvs._digest cimport DVPMVS_SOURCE_DIGEST

# Checked against this file on import (dvpmvs._kernel_sources.require_current).
SOURCE_DIGEST = (<bytes>DVPMVS_SOURCE_DIGEST).decode("ascii")


def sample_bilinear(const float[:, ::1] image, const float[:, ::1] xs, const float[:, ::1] ys,
                    float[:, ::1] out, float fill):
    cdef Py_ssize_t rows = xs.shape[0]
    cdef Py_ssize_t cols = xs.shape[1]
    cdef Py_ssize_t i, j
    with nogil:
        for i in prange(rows, schedule="static"):
            for j in range(cols):
                out[i, j] = bilinear(image, xs[i, j], ys[i, j], fill)


def central_gradient(const float[:, ::1] image, float[:, ::1] gx, float[:, ::1] gy):
    cdef Py_ssize_t height = image.shape[0]
    cdef Py_ssize_t width = image.shape[1]
    cdef Py_ssize_t i, j, left, right, up, down
    with nogil:
        for i in prange(height, schedule="static"):
            up = i - 1 if i > 0 else i
            down = i + 1 if i < height - 1 else i
            for j in range(width):
                left = j - 1 if j > 0 else j
                right = j + 1 if j < width - 1 else j
                gx[i, j] = (image[i, right] - image[i, left]) / (right - left) if right > left else 0.0
                gy[i, j] = (image[down, j] - image[up, j]) / (down - up) if down > up else 0.0
