# cython: language_level=3
"""Private fusion kernel; see :func:`dvpmvs.fusion.fuse`.

One reference view against its neighbours: a pixel's point is kept when at least
``min_consistent`` neighbours agree (reprojection, relative depth, normal angle); the agreeing
pixels are averaged with it (the point: per-coordinate median, as COLMAP's fusion does, or
mean; normal and colour: mean) and marked used, so they are not fused again from another view.
Each kept pixel also gets the bit mask of the neighbours that agreed with it (bit j: neighbour
j), from which the caller writes which views support each point (COLMAP's ``fused.ply.vis``).
"""

from cython.parallel cimport prange
from libc.math cimport sqrt, floor, cos, M_PI
from libc.stdint cimport uint8_t, int32_t, uint64_t

from dvpmvs._digest cimport DVPMVS_SOURCE_DIGEST

# Checked against this file on import (dvpmvs._kernel_sources.require_current).
SOURCE_DIGEST = (<bytes>DVPMVS_SOURCE_DIGEST).decode("ascii")

cdef enum:
    MAX_NEIGHBOURS = 64


cdef inline void _mat3_vec(const double* M, double x, double y, double z, double* out) noexcept nogil:
    out[0] = M[0] * x + M[1] * y + M[2] * z
    out[1] = M[3] * x + M[4] * y + M[5] * z
    out[2] = M[6] * x + M[7] * y + M[8] * z


def fuse_view(const float[:, ::1] depth, const float[:, :, ::1] normal, const uint8_t[:, :, ::1] rgb,
              const double[:, ::1] K, const double[:, ::1] R, const double[::1] t,
              uint8_t[:, ::1] used,
              const float[:, :, ::1] nb_depth, const float[:, :, :, ::1] nb_normal,
              const uint8_t[:, :, :, ::1] nb_rgb, const int32_t[:, ::1] nb_size,
              const double[:, :, ::1] nb_K, const double[:, :, ::1] nb_R, const double[:, ::1] nb_t,
              uint8_t[:, :, ::1] nb_used,
              double max_reproj_error, double max_depth_error, double max_normal_error_deg,
              int min_consistent,
              float[:, :, ::1] out_point, float[:, :, ::1] out_normal, float[:, :, ::1] out_rgb,
              uint8_t[:, ::1] out_valid, uint64_t[:, ::1] out_agreeing, int num_threads, bint median=True):
    cdef int H = depth.shape[0], W = depth.shape[1], N = nb_depth.shape[0]
    if N < 1:
        raise ValueError("fusion needs at least one neighbour view")
    if N > MAX_NEIGHBOURS:
        raise ValueError(f"at most {MAX_NEIGHBOURS} neighbours per view, got {N}")
    if H == 0 or W == 0:
        return
    cdef double Kp[9]
    cdef double Kip[9]
    cdef double Rp[9]
    cdef double RTp[9]
    cdef double tp[3]
    cdef double nbK[MAX_NEIGHBOURS * 9]
    cdef double nbKi[MAX_NEIGHBOURS * 9]
    cdef double nbR[MAX_NEIGHBOURS * 9]
    cdef double nbRT[MAX_NEIGHBOURS * 9]
    cdef double nbt[MAX_NEIGHBOURS * 3]
    import numpy as np
    Ki = np.linalg.inv(np.asarray(K))
    cdef int i, j
    for i in range(9):
        Kp[i] = K[i // 3, i % 3]
        Kip[i] = Ki[i // 3, i % 3]
        Rp[i] = R[i // 3, i % 3]
        RTp[i] = R[i % 3, i // 3]
    for i in range(3):
        tp[i] = t[i]
    for j in range(N):
        Kj_inv = np.linalg.inv(np.asarray(nb_K[j]))
        for i in range(9):
            nbK[9 * j + i] = nb_K[j, i // 3, i % 3]
            nbKi[9 * j + i] = Kj_inv[i // 3, i % 3]
            nbR[9 * j + i] = nb_R[j, i // 3, i % 3]
            nbRT[9 * j + i] = nb_R[j, i % 3, i // 3]
        for i in range(3):
            nbt[3 * j + i] = nb_t[j, i]
    cdef FuseCtx c
    c.depth = &depth[0, 0]
    c.normal = &normal[0, 0, 0]
    c.rgb = &rgb[0, 0, 0]
    c.used = &used[0, 0]
    c.W = W
    c.N = N
    c.HN = nb_depth.shape[1]
    c.WN = nb_depth.shape[2]
    c.nb_depth = &nb_depth[0, 0, 0]
    c.nb_normal = &nb_normal[0, 0, 0, 0]
    c.nb_rgb = &nb_rgb[0, 0, 0, 0]
    c.nb_size = &nb_size[0, 0]
    c.nb_used = &nb_used[0, 0, 0]
    c.Kp = Kp
    c.Kip = Kip
    c.Rp = Rp
    c.RTp = RTp
    c.tp = tp
    c.nbK = nbK
    c.nbKi = nbKi
    c.nbR = nbR
    c.nbRT = nbRT
    c.nbt = nbt
    c.cos_max = cos(max_normal_error_deg * M_PI / 180.0)
    c.max_reproj_sq = max_reproj_error * max_reproj_error
    c.max_depth_error = max_depth_error
    c.min_consistent = min_consistent
    c.median = median
    c.out_point = &out_point[0, 0, 0]
    c.out_normal = &out_normal[0, 0, 0]
    c.out_rgb = &out_rgb[0, 0, 0]
    c.out_valid = &out_valid[0, 0]
    c.out_agreeing = &out_agreeing[0, 0]
    cdef int row, col
    with nogil:
        for row in prange(H, schedule="dynamic", num_threads=num_threads):
            for col in range(W):
                _fuse_pixel(&c, row, col)


cdef struct FuseCtx:
    const float* depth
    const float* normal
    const uint8_t* rgb
    const uint8_t* used
    int W
    int N
    int HN
    int WN
    const float* nb_depth
    const float* nb_normal
    const uint8_t* nb_rgb
    const int32_t* nb_size
    uint8_t* nb_used
    const double* Kp
    const double* Kip
    const double* Rp
    const double* RTp
    const double* tp
    const double* nbK
    const double* nbKi
    const double* nbR
    const double* nbRT
    const double* nbt
    double cos_max
    double max_reproj_sq
    double max_depth_error
    int min_consistent
    bint median  # the fused point: per-coordinate median of the agreeing points (else their mean)
    float* out_point
    float* out_normal
    float* out_rgb
    uint8_t* out_valid
    uint64_t* out_agreeing  # bit j set: neighbour j agreed with the kept pixel


cdef double _median(const double* points, int axis, int n) noexcept nogil:
    """Median of coordinate ``axis`` of ``n`` (<= MAX_NEIGHBOURS + 1) xyz points; the mean of the
    two middle values for even ``n``."""
    cdef double v[MAX_NEIGHBOURS + 1]
    cdef double x
    cdef int i, k
    for i in range(n):  # insertion sort: n is small
        x = points[3 * i + axis]
        k = i
        while k > 0 and v[k - 1] > x:
            v[k] = v[k - 1]
            k -= 1
        v[k] = x
    if n % 2:
        return v[n // 2]
    return 0.5 * (v[n // 2 - 1] + v[n // 2])


cdef double _mean(const double* points, int axis, int n) noexcept nogil:
    """Mean of coordinate ``axis`` of ``n`` xyz points (summed in order)."""
    cdef double total = 0
    cdef int i
    for i in range(n):
        total = total + points[3 * i + axis]
    return total / n


cdef void _fuse_pixel(const FuseCtx* c, int row, int col) noexcept nogil:
    # Every array here is local to the call, hence private to the thread running it.
    cdef Py_ssize_t pix = <Py_ssize_t>row * c.W + col, q
    cdef int count = 0, u, v, i, j, k
    cdef double d, dj, ex, ey, norm
    cdef double tmp[3]
    cdef double X[3]
    cdef double Y[3]
    cdef double Z[3]
    cdef double n_w[3]
    cdef double n_j[3]
    cdef double acc_n[3]
    cdef double acc_c[3]
    cdef Py_ssize_t agree[MAX_NEIGHBOURS]
    cdef uint64_t agreeing = 0
    cdef double points[3 * (MAX_NEIGHBOURS + 1)]  # the pixel's own point, then the agreeing ones
    c.out_valid[pix] = 0
    c.out_agreeing[pix] = 0
    d = c.depth[pix]
    if c.used[pix] or not d > 0:
        return
    # World point and normal of this pixel: X = R^T (d K^-1 p - t).
    _mat3_vec(c.Kip, col, row, 1.0, tmp)
    _mat3_vec(c.RTp, d * tmp[0] - c.tp[0], d * tmp[1] - c.tp[1], d * tmp[2] - c.tp[2], X)
    _mat3_vec(c.RTp, c.normal[3 * pix], c.normal[3 * pix + 1], c.normal[3 * pix + 2], n_w)
    for i in range(3):
        acc_n[i] = n_w[i]
        acc_c[i] = c.rgb[3 * pix + i]
        points[i] = X[i]
    for j in range(c.N):
        # Project into neighbour j and read its depth at the nearest pixel.
        _mat3_vec(&c.nbR[9 * j], X[0], X[1], X[2], Y)
        for i in range(3):
            Y[i] = Y[i] + c.nbt[3 * j + i]
        if Y[2] <= 0:
            continue
        _mat3_vec(&c.nbK[9 * j], Y[0] / Y[2], Y[1] / Y[2], 1.0, tmp)
        u = <int>floor(tmp[0] + 0.5)
        v = <int>floor(tmp[1] + 0.5)
        if u < 0 or v < 0 or u >= c.nb_size[2 * j] or v >= c.nb_size[2 * j + 1]:
            continue
        q = (<Py_ssize_t>j * c.HN + v) * c.WN + u
        dj = c.nb_depth[q]
        if not dj > 0:
            continue
        if (Y[2] - dj if Y[2] > dj else dj - Y[2]) > c.max_depth_error * dj:
            continue
        # The neighbour pixel's own point, back in the reference image.
        _mat3_vec(&c.nbKi[9 * j], u, v, 1.0, tmp)
        _mat3_vec(&c.nbRT[9 * j], dj * tmp[0] - c.nbt[3 * j], dj * tmp[1] - c.nbt[3 * j + 1],
                  dj * tmp[2] - c.nbt[3 * j + 2], Z)
        _mat3_vec(c.Rp, Z[0], Z[1], Z[2], Y)
        for i in range(3):
            Y[i] = Y[i] + c.tp[i]
        if Y[2] <= 0:
            continue
        _mat3_vec(c.Kp, Y[0] / Y[2], Y[1] / Y[2], 1.0, tmp)
        ex = tmp[0] - col
        ey = tmp[1] - row
        if ex * ex + ey * ey > c.max_reproj_sq:
            continue
        _mat3_vec(&c.nbRT[9 * j], c.nb_normal[3 * q], c.nb_normal[3 * q + 1], c.nb_normal[3 * q + 2], n_j)
        if n_w[0] * n_j[0] + n_w[1] * n_j[1] + n_w[2] * n_j[2] < c.cos_max:
            continue
        agree[count] = q
        agreeing = agreeing | (<uint64_t>1 << j)
        count = count + 1
        for i in range(3):
            points[3 * count + i] = Z[i]
            acc_n[i] = acc_n[i] + n_j[i]
            acc_c[i] = acc_c[i] + c.nb_rgb[3 * q + i]
    if count < c.min_consistent:
        return
    norm = sqrt(acc_n[0] * acc_n[0] + acc_n[1] * acc_n[1] + acc_n[2] * acc_n[2])
    for i in range(3):
        c.out_point[3 * pix + i] = _median(points, i, count + 1) if c.median else _mean(points, i, count + 1)
        c.out_normal[3 * pix + i] = acc_n[i] / norm if norm > 0 else n_w[i]
        c.out_rgb[3 * pix + i] = acc_c[i] / (count + 1)
    c.out_valid[pix] = 1
    c.out_agreeing[pix] = agreeing
    # Marks are written, never read, in this sweep (only the reference's own ``used`` is read),
    # so the result does not depend on the thread count.
    for k in range(count):
        c.nb_used[agree[k]] = 1
