# cython: language_level=3
"""Private fusion kernel; see :func:`dvpmvs.fusion.fuse`.

One reference view against its neighbours: a pixel's point is kept when at least
``min_consistent`` neighbours agree (reprojection, relative depth, normal angle); the agreeing
pixels are averaged with it and marked used, so they are not fused again from another view.
"""

from cython.parallel cimport prange
from libc.math cimport sqrt, floor, cos, M_PI
from libc.stdint cimport uint8_t, int32_t

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
              uint8_t[:, ::1] out_valid, int num_threads):
    cdef int H = depth.shape[0], W = depth.shape[1], N = nb_depth.shape[0]
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
    cdef int i, j, k
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
    cdef double cos_max = cos(max_normal_error_deg * M_PI / 180.0)
    cdef double max_reproj_sq = max_reproj_error * max_reproj_error
    cdef int row, col, count, u, v
    cdef double d, dj, tmp[3], X[3], Y[3], Z[3], n_w[3], n_j[3], acc_p[3], acc_n[3], acc_c[3], ex, ey, norm
    cdef int agree_u[MAX_NEIGHBOURS]
    cdef int agree_v[MAX_NEIGHBOURS]
    cdef int agree_j[MAX_NEIGHBOURS]
    with nogil:
        for row in prange(H, schedule="dynamic", num_threads=num_threads):
            for col in range(W):
                out_valid[row, col] = 0
                d = depth[row, col]
                if used[row, col] or not d > 0:
                    continue
                # World point and normal of this pixel: X = R^T (d K^-1 p - t).
                _mat3_vec(Kip, col, row, 1.0, tmp)
                _mat3_vec(RTp, d * tmp[0] - tp[0], d * tmp[1] - tp[1], d * tmp[2] - tp[2], X)
                _mat3_vec(RTp, normal[row, col, 0], normal[row, col, 1], normal[row, col, 2], n_w)
                count = 0
                for i in range(3):
                    acc_p[i] = X[i]
                    acc_n[i] = n_w[i]
                    acc_c[i] = rgb[row, col, i]
                for j in range(N):
                    # Project into neighbour j and read its depth at the nearest pixel.
                    _mat3_vec(&nbR[9 * j], X[0], X[1], X[2], Y)
                    Y[0] = Y[0] + nbt[3 * j]
                    Y[1] = Y[1] + nbt[3 * j + 1]
                    Y[2] = Y[2] + nbt[3 * j + 2]
                    if Y[2] <= 0:
                        continue
                    _mat3_vec(&nbK[9 * j], Y[0] / Y[2], Y[1] / Y[2], 1.0, tmp)
                    u = <int>floor(tmp[0] + 0.5)
                    v = <int>floor(tmp[1] + 0.5)
                    if u < 0 or v < 0 or u >= nb_size[j, 0] or v >= nb_size[j, 1]:
                        continue
                    dj = nb_depth[j, v, u]
                    if not dj > 0:
                        continue
                    if (Y[2] - dj if Y[2] > dj else dj - Y[2]) > max_depth_error * dj:
                        continue
                    # The neighbour pixel's own point, back in the reference image.
                    _mat3_vec(&nbKi[9 * j], u, v, 1.0, tmp)
                    _mat3_vec(&nbRT[9 * j], dj * tmp[0] - nbt[3 * j], dj * tmp[1] - nbt[3 * j + 1],
                              dj * tmp[2] - nbt[3 * j + 2], Z)
                    _mat3_vec(Rp, Z[0], Z[1], Z[2], Y)
                    Y[0] = Y[0] + tp[0]
                    Y[1] = Y[1] + tp[1]
                    Y[2] = Y[2] + tp[2]
                    if Y[2] <= 0:
                        continue
                    _mat3_vec(Kp, Y[0] / Y[2], Y[1] / Y[2], 1.0, tmp)
                    ex = tmp[0] - col
                    ey = tmp[1] - row
                    if ex * ex + ey * ey > max_reproj_sq:
                        continue
                    _mat3_vec(&nbRT[9 * j], nb_normal[j, v, u, 0], nb_normal[j, v, u, 1], nb_normal[j, v, u, 2], n_j)
                    if n_w[0] * n_j[0] + n_w[1] * n_j[1] + n_w[2] * n_j[2] < cos_max:
                        continue
                    agree_u[count] = u
                    agree_v[count] = v
                    agree_j[count] = j
                    count = count + 1
                    for i in range(3):
                        acc_p[i] = acc_p[i] + Z[i]
                        acc_n[i] = acc_n[i] + n_j[i]
                        acc_c[i] = acc_c[i] + nb_rgb[j, v, u, i]
                if count < min_consistent:
                    continue
                norm = sqrt(acc_n[0] * acc_n[0] + acc_n[1] * acc_n[1] + acc_n[2] * acc_n[2])
                for i in range(3):
                    out_point[row, col, i] = acc_p[i] / (count + 1)
                    out_normal[row, col, i] = acc_n[i] / norm if norm > 0 else n_w[i]
                    out_rgb[row, col, i] = acc_c[i] / (count + 1)
                out_valid[row, col] = 1
                # Marks are written, never read, in this sweep (only the reference's own ``used``
                # is read), so the result does not depend on the thread count.
                for k in range(count):
                    nb_used[agree_j[k], agree_v[k], agree_u[k]] = 1
