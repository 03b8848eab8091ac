# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True
"""Products and powers whose bits do not depend on the machine (see ``portable.py``).

Each entry of a product is a chain of fused multiply-adds in a fixed order. C's ``fma`` rounds
once, exactly, on every platform (an FMA instruction or libm's exact emulation), so the chain
gives the same double everywhere; the orders are those OpenBLAS's AVX2 kernels use for the same
calls, so that the scenes rendered before these functions existed keep their bits. Powers call
libm's ``pow`` element by element: numpy's SIMD variants of ``power`` differ in the last bits
between vector extensions.
"""

from libc.math cimport fma, pow

from dvpmvs._digest cimport DVPMVS_SOURCE_DIGEST

# Checked against this file on import (dvpmvs._kernel_sources.require_current).
SOURCE_DIGEST = (<bytes>DVPMVS_SOURCE_DIGEST).decode("ascii")


def rows_times(const double[:, ::1] rows, const double[:, ::1] matrix, double[:, ::1] out):
    """``out = rows @ matrix`` for (N, K) rows and a (K, M) matrix: each entry
    fma(r[K-1], m[K-1], ... fma(r[0], m[0], 0.0))."""
    cdef Py_ssize_t n = rows.shape[0], k = rows.shape[1], m = matrix.shape[1], i, j, l
    cdef double acc
    with nogil:
        for i in range(n):
            for j in range(m):
                acc = 0.0
                for l in range(k):
                    acc = fma(rows[i, l], matrix[l, j], acc)
                out[i, j] = acc


def matrix_times_vector(const double[:, ::1] matrix, const double[::1] vector, double[::1] out):
    """``out = matrix @ vector`` for a (M, 3) matrix: each entry
    fma(a[2], v[2], fma(a[0], v[0], fma(a[1], v[1], 0.0)))."""
    cdef Py_ssize_t i
    for i in range(matrix.shape[0]):
        out[i] = fma(matrix[i, 2], vector[2], fma(matrix[i, 0], vector[0], fma(matrix[i, 1], vector[1], 0.0)))


def power(const double[::1] base, const double[::1] exponent, double[::1] out):
    """``out = base ** exponent`` element by element, through libm's ``pow``."""
    cdef Py_ssize_t i
    with nogil:
        for i in range(base.shape[0]):
            out[i] = pow(base[i], exponent[i])
