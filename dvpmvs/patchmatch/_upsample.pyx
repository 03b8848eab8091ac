# cython: language_level=3
"""Private kernel: joint bilateral upsampling of plane maps; see :func:`dvpmvs.patchmatch.upsample_planes`."""

from cython.parallel cimport prange
from libc.math cimport exp, sqrt, fabs, floor

from dvpmvs._digest cimport DVPMVS_SOURCE_DIGEST

# Checked against this file on import (dvpmvs._kernel_sources.require_current).
SOURCE_DIGEST = (<bytes>DVPMVS_SOURCE_DIGEST).decode("ascii")


def upsample_planes(const float[:, ::1] depth, const float[:, :, ::1] normal, const float[:, ::1] guide,
                    const double[:, ::1] K_coarse_inv, const double[:, ::1] K_fine_inv,
                    float[:, ::1] out_depth, float[:, :, ::1] out_normal,
                    int radius, float sigma_spatial, float sigma_color, int num_threads):
    cdef int h = depth.shape[0], w = depth.shape[1]
    cdef int H = guide.shape[0], W = guide.shape[1]
    cdef float sx = <float>w / W, sy = <float>h / H
    cdef float ci[9]
    cdef float fi[9]
    cdef int i
    for i in range(9):
        ci[i] = K_coarse_inv[i // 3, i % 3]
        fi[i] = K_fine_inv[i // 3, i % 3]
    cdef float inv_ss = 1.0 / (2.0 * sigma_spatial * sigma_spatial)
    cdef float inv_sc = 1.0 / (2.0 * sigma_color * sigma_color)
    cdef int row, col, r, c, gr, gc, r0, c0
    cdef float xc, yc, wgt, g, dx, dy, sum_w, sum_d, n0, n1, n2, rx, ry, qx, qy, denom, d, norm
    with nogil:
        for row in prange(H, schedule="static", num_threads=num_threads):
            for col in range(W):
                # This fine pixel's position on the coarse grid (pixel areas aligned).
                xc = (col + 0.5) * sx - 0.5
                yc = (row + 0.5) * sy - 0.5
                c0 = <int>floor(xc + 0.5)
                r0 = <int>floor(yc + 0.5)
                g = guide[row, col]
                rx = fi[0] * col + fi[1] * row + fi[2]
                ry = fi[3] * col + fi[4] * row + fi[5]
                sum_w = 0
                sum_d = 0
                n0 = 0
                n1 = 0
                n2 = 0
                for r in range(r0 - radius, r0 + radius + 1):
                    if r < 0 or r >= h:
                        continue
                    for c in range(c0 - radius, c0 + radius + 1):
                        if c < 0 or c >= w or not depth[r, c] > 0:
                            continue
                        # Colour term from the guide at the coarse pixel's centre.
                        gc = <int>floor((c + 0.5) / sx)
                        gr = <int>floor((r + 0.5) / sy)
                        if gc >= W:
                            gc = W - 1
                        if gr >= H:
                            gr = H - 1
                        dx = c - xc
                        dy = r - yc
                        wgt = exp(-(dx * dx + dy * dy) * inv_ss
                                  - (guide[gr, gc] - g) * (guide[gr, gc] - g) * inv_sc)
                        # The neighbour's plane, intersected with this pixel's ray.
                        qx = ci[0] * c + ci[1] * r + ci[2]
                        qy = ci[3] * c + ci[4] * r + ci[5]
                        denom = normal[r, c, 0] * rx + normal[r, c, 1] * ry + normal[r, c, 2]
                        d = depth[r, c]
                        if fabs(denom) > 1e-6:
                            d = depth[r, c] * (normal[r, c, 0] * qx + normal[r, c, 1] * qy + normal[r, c, 2]) / denom
                            if not (d > 0.5 * depth[r, c] and d < 2.0 * depth[r, c]):
                                d = depth[r, c]
                        sum_w = sum_w + wgt
                        sum_d = sum_d + wgt * d
                        n0 = n0 + wgt * normal[r, c, 0]
                        n1 = n1 + wgt * normal[r, c, 1]
                        n2 = n2 + wgt * normal[r, c, 2]
                norm = sqrt(n0 * n0 + n1 * n1 + n2 * n2)
                if sum_w > 0 and norm > 1e-8:
                    out_depth[row, col] = sum_d / sum_w
                    out_normal[row, col, 0] = n0 / norm
                    out_normal[row, col, 1] = n1 / norm
                    out_normal[row, col, 2] = n2 / norm
                else:
                    out_depth[row, col] = 0
                    out_normal[row, col, 0] = 0
                    out_normal[row, col, 1] = 0
                    out_normal[row, col, 2] = -1
