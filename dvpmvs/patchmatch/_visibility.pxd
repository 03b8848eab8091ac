# Where a pixel's point is seen from the sources: the forward-backward reprojection error of the
# geometric pass, and the paper's visibility of section 3.4 (eq. 10-11) with its restoration.
# Inline functions cimported by the kernels (no .pyx of its own).

from libc.math cimport sqrt, floor, INFINITY
from libc.stdint cimport uint32_t, uint8_t

from dvpmvs.patchmatch._context cimport Ctx, _project, _ray


cdef inline bint _source_pixel(const Ctx* c, int j, float depth, const float* ray, int* ui, int* vi) noexcept nogil:
    """The pixel of source j nearest to where the point depth * ray projects; False when the
    point is behind the source or the pixel lies outside its image."""
    cdef float u, v
    if not _project(c, j, depth, ray, &u, &v):
        return False
    ui[0] = <int>floor(u + 0.5)
    vi[0] = <int>floor(v + 0.5)
    return 0 <= ui[0] < c.src_size[2 * j] and 0 <= vi[0] < c.src_size[2 * j + 1]


cdef inline float _back_projection_error(const Ctx* c, int j, int ui, int vi, float ds, float x,
                                         float y) noexcept nogil:
    """How far (pixels, at most ``geom_max_error``) source j's pixel (ui, vi) at depth ds lands
    from the reference point (x, y)."""
    cdef const float* R = c.rel_R + 9 * j
    cdef const float* t = c.rel_t + 3 * j
    cdef const float* Ksi = c.src_K_inv + 9 * j
    if not ds > 0:
        return c.p.geom_max_error
    # Back-project the source pixel with its own depth and bring it to the reference camera.
    cdef float Z0 = ds * (Ksi[0] * ui + Ksi[1] * vi + Ksi[2])
    cdef float Z1 = ds * (Ksi[3] * ui + Ksi[4] * vi + Ksi[5])
    cdef float Z2 = ds
    Z0 = Z0 - t[0]
    Z1 = Z1 - t[1]
    Z2 = Z2 - t[2]
    # R^T Z
    cdef float W0 = R[0] * Z0 + R[3] * Z1 + R[6] * Z2
    cdef float W1 = R[1] * Z0 + R[4] * Z1 + R[7] * Z2
    cdef float W2 = R[2] * Z0 + R[5] * Z1 + R[8] * Z2
    if W2 <= 1e-8:
        return c.p.geom_max_error
    cdef float px = (c.K[0] * W0 + c.K[1] * W1 + c.K[2] * W2) / W2 - x
    cdef float py = (c.K[3] * W0 + c.K[4] * W1 + c.K[5] * W2) / W2 - y
    cdef float err = sqrt(px * px + py * py)
    return err if err < c.p.geom_max_error else c.p.geom_max_error


cdef inline float _reprojection_error(const Ctx* c, int j, float x, float y, float depth,
                                      const float* ray) noexcept nogil:
    """Forward-backward reprojection error (pixels) of the point depth * ray through source j's
    depth map; ``geom_max_error`` when the point leaves source j or meets no depth there."""
    cdef int ui, vi
    if not _source_pixel(c, j, depth, ray, &ui, &vi):
        return c.p.geom_max_error
    return _back_projection_error(c, j, ui, vi, c.src_depth[(<Py_ssize_t>j * c.SH + vi) * c.SW + ui], x, y)


cdef inline float _restored_reprojection_error(const Ctx* c, int j, float x, float y, float depth, const float* ray,
                                               const float* src_cost, int radius) noexcept nogil:
    """The forward-backward reprojection error of ``_reprojection_error`` with the paper's
    restoration (section 3.4): the projected pixel goes back with the depth of the lowest-cost
    pixel (with a depth) of the (2 radius + 1)^2 window around it in source j, not its own,
    which may be an outlier. Ties, and a window without known costs, keep the projected
    pixel's own depth (so radius 0 is ``_reprojection_error``); other ties go to the first in
    row-major order."""
    cdef float best_cost, best_depth, d, k
    cdef int ui, vi, r, q
    cdef int sw = c.src_size[2 * j], sh = c.src_size[2 * j + 1]
    cdef Py_ssize_t base
    if not _source_pixel(c, j, depth, ray, &ui, &vi):
        return c.p.geom_max_error
    base = (<Py_ssize_t>j * c.SH + vi) * c.SW + ui
    best_depth = c.src_depth[base]
    best_cost = src_cost[base] if best_depth > 0 else INFINITY
    for r in range(max(0, vi - radius), min(sh, vi + radius + 1)):
        base = (<Py_ssize_t>j * c.SH + r) * c.SW
        for q in range(max(0, ui - radius), min(sw, ui + radius + 1)):
            d = c.src_depth[base + q]
            k = src_cost[base + q]
            if d > 0 and k < best_cost:
                best_cost = k
                best_depth = d
    return _back_projection_error(c, j, ui, vi, best_depth, x, y)


cdef inline bint _in_source_highlight(const Ctx* c, int j, float depth, const float* ray,
                                      const uint8_t* src_highlight) noexcept nogil:
    """True when the point depth * ray lands in source j's highlight mask."""
    cdef int ui, vi
    return (src_highlight != NULL and _source_pixel(c, j, depth, ray, &ui, &vi)
            and src_highlight[(<Py_ssize_t>j * c.SH + vi) * c.SW + ui] != 0)


cdef inline uint32_t _visible_pixel(const Ctx* c, int row, int col, float max_error, const float* src_cost,
                                    int radius, const uint8_t* src_highlight, bint all_sources) noexcept nogil:
    """The bit mask of the sources pixel (row, col) is visible in (see ``visible_sources``)."""
    cdef Py_ssize_t pix = <Py_ssize_t>row * c.W + col
    cdef float ray[3]
    cdef uint32_t mask
    cdef int j
    cdef float err
    if not c.depth[pix] > 0:
        return 0
    mask = (<uint32_t>0xFFFFFFFF >> (32 - c.S)) if all_sources else c.selected[pix]
    _ray(c, col, row, ray)
    if c.src_depth != NULL and not all_sources:
        for j in range(c.S):
            if src_cost != NULL:
                err = _restored_reprojection_error(c, j, col, row, c.depth[pix], ray, src_cost, radius)
            else:
                err = _reprojection_error(c, j, col, row, c.depth[pix], ray)
            if err <= max_error:
                mask = mask | (<uint32_t>1 << j)
    if src_highlight != NULL:
        for j in range(c.S):
            if (mask >> j) & 1 and _in_source_highlight(c, j, c.depth[pix], ray, src_highlight):
                mask = mask & ~(<uint32_t>1 << j)
    return mask
