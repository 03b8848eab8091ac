# Inline bilinear sampling shared by every kernel that warps images (cimport this file).
# ``bilinear``: typed memoryview, ``fill`` outside; ``bilinear_clamped``: raw pointer with a row
# stride (images padded into a stack), clamped to the border.

cdef inline float bilinear_clamped(const float* img, int stride, int width, int height, float x,
                                   float y) noexcept nogil:
    """Bilinear sample of an image of ``width`` columns stored with row stride ``stride``,
    clamped to the border (NaN positions read the corner, never outside the image)."""
    if not (x >= 0.0):
        x = 0.0
    elif x > width - 1:
        x = width - 1
    if not (y >= 0.0):
        y = 0.0
    elif y > height - 1:
        y = height - 1
    cdef int x0 = <int>x
    cdef int y0 = <int>y
    cdef int x1 = x0 + 1 if x0 + 1 < width else x0
    cdef int y1 = y0 + 1 if y0 + 1 < height else y0
    cdef float ax = x - x0
    cdef float ay = y - y0
    return ((1.0 - ay) * ((1.0 - ax) * img[y0 * stride + x0] + ax * img[y0 * stride + x1])
            + ay * ((1.0 - ax) * img[y1 * stride + x0] + ax * img[y1 * stride + x1]))


cdef inline float bilinear(const float[:, ::1] image, float x, float y, float fill) noexcept nogil:
    """Sample ``image`` at the continuous pixel position (x, y); pixel centres are integers.

    Positions whose 2x2 neighbourhood leaves the image return ``fill``.
    """
    cdef int height = <int>image.shape[0]
    cdef int width = <int>image.shape[1]
    if not (x >= 0.0 and y >= 0.0 and x <= width - 1 and y <= height - 1):  # also rejects NaN
        return fill
    return bilinear_clamped(&image[0, 0], width, width, height, x, y)
