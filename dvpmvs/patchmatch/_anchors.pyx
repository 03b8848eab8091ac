# cython: language_level=3
"""Private kernels of deformable PatchMatch's anchors; use :mod:`dvpmvs.patchmatch` instead.

A weak pixel's anchors are strong pixels of its own region, one per 45-degree sector (paper
eq. 9), found by walking outward along three search lines per sector; with area maximisation
(paper eq. 12) each sector's anchor is the candidate that adds the most area to the anchors'
polygon. ``fit_anchor_planes`` and ``keep_coplanar_anchors`` fit the plane through three of a
pixel's anchors (APD-MVS's fitted plane and reliability rule).
"""

from cython.parallel cimport prange
from libc.math cimport sqrt, fabs, floor, sin, cos, M_PI
from libc.stdint cimport uint32_t, int32_t, uint8_t

from dvpmvs.patchmatch._context cimport MAX_ANCHORS, _ray_from

from dvpmvs._digest cimport DVPMVS_SOURCE_DIGEST

# Checked against this file on import (dvpmvs._kernel_sources.require_current).
SOURCE_DIGEST = (<bytes>DVPMVS_SOURCE_DIGEST).decode("ascii")


def _inverse3(const double[:, ::1] K):
    import numpy as np
    return np.linalg.inv(np.asarray(K)).astype(np.float32).ravel()


cdef struct AnchorSearch:
    # The 24 search lines (8 sectors x centre, +15, -15 degrees) as unit steps (sin and cos
    # once, not at every step of every walk).
    double dir_r[3 * MAX_ANCHORS]
    double dir_c[3 * MAX_ANCHORS]


cdef inline void _line_interval(double p, double d, int lo, int hi, double* t_min, double* t_max) noexcept nogil:
    """Narrow [t_min, t_max] to the t with lo - 1 <= p + t d <= hi + 1 (one pixel of margin, so
    that rounding a position can never move it into the box)."""
    cdef double a, b
    if fabs(d) < 1e-12:
        if p < lo - 1 or p > hi + 1:
            t_max[0] = -1
        return
    a = (lo - 1 - p) / d
    b = (hi + 1 - p) / d
    if a > b:
        a, b = b, a
    if a > t_min[0]:
        t_min[0] = a
    if b < t_max[0]:
        t_max[0] = b


cdef void _anchor_pixel(const uint8_t[:, ::1] strong, const int32_t* labels, const int32_t* box,
                        const AnchorSearch* s, int32_t* out, int row, int col, int min_distance,
                        int max_distance, int step, bint area_max, double nearest) noexcept nogil:
    """The anchors of pixel (row, col) into ``out`` (see ``find_anchors``). Each sector's
    candidates are the first strong pixel on each of its three search lines; without
    ``area_max`` the nearest of them is the anchor (ties: the centre line first), and the walk
    stops at it. ``nearest``: the distance to the nearest strong pixel; the walk starts where a
    line's pixel can be that far (a line's pixel at distance r, rounded to the grid, lies within
    sqrt(1/2) of the point at r)."""
    cdef int H = strong.shape[0], W = strong.shape[1]
    cdef int a, k, line, qr, qc, r, r_first, r_last, first, open_lines
    cdef int32_t own = labels[row * W + col] if labels != NULL else 1
    cdef const int32_t* b = box + 4 * (own if labels != NULL else 0)
    cdef double t_min[3]
    cdef double t_max[3]
    cdef double lo, hi
    cdef int32_t candidates[3 * MAX_ANCHORS]
    for a in range(MAX_ANCHORS):
        out[a] = -1
    for k in range(3 * MAX_ANCHORS):
        candidates[k] = -1
    if strong[row, col] or own <= 0 or b[0] > b[1]:
        return
    for a in range(MAX_ANCHORS):
        # Only the stretch of each line inside the bounding box of the region's strong pixels
        # can hold an anchor (a line leaves a box once): the walk visits that stretch alone,
        # and finds what the walk over the whole distance finds.
        lo = max_distance + 1.0
        hi = -1.0
        for k in range(3):
            line = 3 * a + k
            t_min[k] = min_distance
            t_max[k] = max_distance
            _line_interval(row, s.dir_r[line], b[0], b[1], &t_min[k], &t_max[k])
            _line_interval(col, s.dir_c[line], b[2], b[3], &t_min[k], &t_max[k])
            if t_min[k] <= t_max[k]:
                lo = min(lo, t_min[k])
                hi = max(hi, t_max[k])
        lo = max(lo, nearest - 0.75)
        if lo > hi:
            continue
        # The walk's distances are min_distance + m * step; start at the first one >= lo.
        r_first = min_distance + step * <int>max(0.0, floor((lo - min_distance) / step))
        r_last = <int>floor(hi)
        r = r_first
        first = -1
        while r <= r_last:
            # Within the 45-degree sector: its centre line first, then 15 degrees either side.
            open_lines = 0
            for k in range(3):
                line = 3 * a + k
                if candidates[line] >= 0 or r > t_max[k]:
                    continue
                open_lines += 1
                if r < t_min[k]:
                    continue
                qr = row + <int>floor(r * s.dir_r[line] + 0.5)
                qc = col + <int>floor(r * s.dir_c[line] + 0.5)
                if qr < 0 or qc < 0 or qr >= H or qc >= W or not strong[qr, qc]:
                    continue
                if labels != NULL and labels[qr * W + qc] != own:
                    continue
                candidates[line] = qr * W + qc
                open_lines -= 1
                if first < 0:
                    first = line
                if not area_max:
                    break
            if first >= 0 and (not area_max or open_lines == 0):
                break
            # Fixed steps: steps growing to an eighth of the distance were faster but jumped over
            # thin strong strips (lower F1 at both tolerances on the 400x300 suite).
            r = r + step
        if first >= 0:
            out[a] = candidates[first]
    if area_max:
        _maximise_area(candidates, out, row, col, W)


cdef inline long long _area_gain(int32_t q, int W, int row, int col, long long ur, long long uc) noexcept nogil:
    """(q - p) x u for pixel q, p = (row, col): twice the area q adds, up to a constant."""
    return (q % W - col) * ur - (q // W - row) * uc


cdef void _maximise_area(const int32_t* candidates, int32_t* out, int row, int col, int W) noexcept nogil:
    """Paper eq. 12: each sector's anchor becomes the candidate that adds the most area to the
    polygon of the anchors around the pixel, its neighbouring sectors' anchors held fixed. With
    u = (next anchor) - (previous anchor), the growth of triangle areas is half the cross
    product (c - p) x u plus a constant, so the candidate maximising (c - p) x u wins (exact
    integer arithmetic; ties keep the current anchor). The sectors are visited in order, each
    with its neighbours' current anchors, until a visit changes nothing (at most 4 rounds:
    each change grows the polygon, so the rounds converge)."""
    cdef int a, k, prev, nxt, m, _round
    cdef int32_t q, best
    cdef long long ur, uc, gain, best_gain
    cdef bint changed
    for _round in range(4):
        changed = False
        for a in range(MAX_ANCHORS):
            if out[a] < 0:
                continue
            prev = -1
            nxt = -1
            for m in range(1, MAX_ANCHORS):
                if nxt < 0 and out[(a + m) % MAX_ANCHORS] >= 0:
                    nxt = (a + m) % MAX_ANCHORS
                if prev < 0 and out[(a - m + MAX_ANCHORS) % MAX_ANCHORS] >= 0:
                    prev = (a - m + MAX_ANCHORS) % MAX_ANCHORS
            if prev < 0 or prev == nxt:
                continue  # fewer than three anchors: no polygon to grow
            ur = out[nxt] // W - out[prev] // W
            uc = out[nxt] % W - out[prev] % W
            best = out[a]
            best_gain = _area_gain(best, W, row, col, ur, uc)
            for k in range(3):
                q = candidates[3 * a + k]
                if q < 0 or q == best:
                    continue
                gain = _area_gain(q, W, row, col, ur, uc)
                if gain > best_gain:
                    best = q
                    best_gain = gain
            if best != out[a]:
                out[a] = best
                changed = True
        if not changed:
            break


def find_anchors(const uint8_t[:, ::1] strong, labels, int32_t[:, :, ::1] anchors, int min_distance,
                 int max_distance, int step, int num_threads, bint area_max=False):
    """For every weak pixel, one strong anchor per 45-degree sector, searched outward from
    ``min_distance`` to ``max_distance`` pixels in steps of ``step``; with ``labels`` (H, W) int32 only anchors of the
    pixel's own region (eq. 9), and none for boundary pixels (label 0). The nearest strong pixel
    of the sector's three search lines, or with ``area_max`` the one of the lines' first strong
    pixels that maximises the anchors' area (paper eq. 12, ``_maximise_area``)."""
    import cv2
    import numpy as np
    cdef const int32_t[:, ::1] lab
    cdef const float[:, ::1] nearest
    cdef const int32_t* lab_ptr = NULL
    cdef int H = strong.shape[0], W = strong.shape[1]
    if anchors.shape[0] != H or anchors.shape[1] != W or anchors.shape[2] != MAX_ANCHORS:
        raise ValueError(f"anchors must be ({H}, {W}, {MAX_ANCHORS})")
    cdef int num_regions = 1
    if labels is not None:
        lab = labels
        if lab.shape[0] != H or lab.shape[1] != W:
            raise ValueError("labels do not match the strong-pixel map")
        if H * W > 0 and np.asarray(lab).min() < 0:
            raise ValueError("labels must be >= 0 (0: boundary pixels)")
        lab_ptr = &lab[0, 0]
        num_regions = (int(np.asarray(lab).max()) + 1) if H * W > 0 else 1
    # Bounding box of each region's strong pixels (of all strong pixels without labels).
    box_array = np.empty((num_regions, 4), np.int32)
    box_array[:, 0] = H
    box_array[:, 1] = -1
    box_array[:, 2] = W
    box_array[:, 3] = -1
    cdef int32_t[:, ::1] box = box_array
    # box[region] = rows r0..r1, cols c0..c1 of the region's strong pixels (r0 > r1: none).
    cdef AnchorSearch search
    cdef int row, col, a, k, region
    cdef double angle
    # Each weak pixel's distance to the nearest strong pixel (of any region): no walk finds one
    # nearer (exact Euclidean distances, Felzenszwalb and Huttenlocher's transform).
    if H * W == 0:
        return
    nearest = cv2.distanceTransform((np.asarray(strong) == 0).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    for a in range(MAX_ANCHORS):
        for k in range(3):
            angle = (a + (0.0 if k == 0 else (1.0 / 3.0 if k == 1 else -1.0 / 3.0))) * M_PI / 4.0
            search.dir_r[3 * a + k] = sin(angle)
            search.dir_c[3 * a + k] = cos(angle)
    with nogil:
        for row in range(H):
            for col in range(W):
                if not strong[row, col]:
                    continue
                region = lab_ptr[row * W + col] if lab_ptr != NULL else 0
                box[region, 0] = min(box[region, 0], row)
                box[region, 1] = max(box[region, 1], row)
                box[region, 2] = min(box[region, 2], col)
                box[region, 3] = max(box[region, 3], col)
        for row in prange(H, schedule="dynamic", num_threads=num_threads):
            for col in range(W):
                _anchor_pixel(strong, lab_ptr, &box[0, 0], &search, &anchors[row, col, 0], row, col,
                              min_distance, max_distance, step, area_max, nearest[row, col])


cdef inline float _cross2(float ax, float ay, float bx, float by) noexcept nogil:
    return ax * by - ay * bx


cdef void _fit_pixel(const float* depth, const int32_t* anchors, const float* K_inv, int W, int row, int col,
                     float max_rel_error, int min_inliers, float* out_depth, float* out_normal,
                     uint32_t* out_inliers) noexcept nogil:
    """The plane through three of the pixel's anchors whose triangle contains it, agreed with by
    the most anchors (depth within ``max_rel_error``, relative); ties go to the smaller summed
    error. Every triple is tried (at most 56), so the choice is deterministic. ``out_inliers``
    (or NULL): bit a set for anchor slot a on the plane; 0 without one."""
    cdef float X[MAX_ANCHORS * 3]
    cdef float ray_k[MAX_ANCHORS * 3]
    cdef float px[MAX_ANCHORS]
    cdef float py[MAX_ANCHORS]
    cdef int slot[MAX_ANCHORS]
    cdef uint32_t on_plane, best_on_plane = 0
    cdef float ray[3]
    cdef float n[3]
    cdef float e1[3]
    cdef float e2[3]
    cdef float norm, off, denom, dk, err, total, best_total = 1e30, t1, t2, t3
    cdef int num = 0, a, b, k, m, q, count, best_count = 0
    for a in range(MAX_ANCHORS):
        q = anchors[a]
        if q < 0 or not depth[q] > 0:
            continue
        slot[num] = a
        px[num] = q % W
        py[num] = q // W
        _ray_from(K_inv, px[num], py[num], &ray_k[3 * num])
        for k in range(3):
            X[3 * num + k] = depth[q] * ray_k[3 * num + k]
        num += 1
    out_depth[0] = 0
    if out_inliers != NULL:
        out_inliers[0] = 0
    if num < 3 or num < min_inliers:
        return
    _ray_from(K_inv, col, row, ray)
    for a in range(num):
        for b in range(a + 1, num):
            for m in range(b + 1, num):
                # The pixel inside (or on) the triangle: an interpolation, not an extrapolation.
                t1 = _cross2(px[a] - col, py[a] - row, px[b] - col, py[b] - row)
                t2 = _cross2(px[b] - col, py[b] - row, px[m] - col, py[m] - row)
                t3 = _cross2(px[m] - col, py[m] - row, px[a] - col, py[a] - row)
                if not (t1 * t2 >= 0 and t1 * t3 >= 0 and t2 * t3 >= 0):
                    continue
                for k in range(3):
                    e1[k] = X[3 * b + k] - X[3 * a + k]
                    e2[k] = X[3 * m + k] - X[3 * a + k]
                n[0] = e1[1] * e2[2] - e1[2] * e2[1]
                n[1] = e1[2] * e2[0] - e1[0] * e2[2]
                n[2] = e1[0] * e2[1] - e1[1] * e2[0]
                norm = sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
                if not norm > 0:
                    continue
                for k in range(3):
                    n[k] = n[k] / norm
                off = n[0] * X[3 * a] + n[1] * X[3 * a + 1] + n[2] * X[3 * a + 2]  # n . X = off
                count = 0
                total = 0
                on_plane = 0
                for k in range(num):
                    denom = n[0] * ray_k[3 * k] + n[1] * ray_k[3 * k + 1] + n[2] * ray_k[3 * k + 2]
                    if fabs(denom) < 1e-9:
                        continue
                    dk = off / denom
                    err = fabs(dk - X[3 * k + 2]) / X[3 * k + 2]
                    if err <= max_rel_error:
                        count += 1
                        total = total + err
                        on_plane = on_plane | (<uint32_t>1 << slot[k])
                if count > best_count or (count == best_count and total < best_total):
                    denom = n[0] * ray[0] + n[1] * ray[1] + n[2] * ray[2]
                    if fabs(denom) < 1e-9 or not off / denom > 0:
                        continue
                    best_count = count
                    best_total = total
                    best_on_plane = on_plane
                    out_depth[0] = off / denom
                    # Facing the camera: n . ray < 0.
                    for k in range(3):
                        out_normal[k] = -n[k] if denom > 0 else n[k]
    if best_count < min_inliers:
        out_depth[0] = 0
    elif out_inliers != NULL:
        out_inliers[0] = best_on_plane


cdef void _keep_coplanar_pixel(const float* depth, int32_t* anchors, const float* K_inv, int W, int row, int col,
                               float max_rel_error, int min_inliers) noexcept nogil:
    cdef float plane_depth
    cdef float plane_normal[3]
    cdef uint32_t on_plane
    cdef int a
    _fit_pixel(depth, anchors, K_inv, W, row, col, max_rel_error, min_inliers, &plane_depth, plane_normal, &on_plane)
    for a in range(MAX_ANCHORS):
        if not (on_plane >> a) & 1:
            anchors[a] = -1


cdef void _anchor_planes(const float[:, ::1] depth, int32_t[:, :, ::1] anchors, const double[:, ::1] K,
                         float max_rel_error, int min_inliers, float* fit_depth, float* fit_normal,
                         int num_threads) except *:
    """Every pixel's anchor plane into ``fit_depth`` / ``fit_normal``; with NULL there, the
    anchors off the plane are dropped instead (all of them without a plane)."""
    cdef int H = depth.shape[0], W = depth.shape[1], row, col, i
    if anchors.shape[0] != H or anchors.shape[1] != W or anchors.shape[2] != MAX_ANCHORS:
        raise ValueError(f"anchors must be ({H}, {W}, {MAX_ANCHORS})")
    cdef float K_inv[9]
    Ki = _inverse3(K)
    for i in range(9):
        K_inv[i] = Ki[i]
    with nogil:
        for row in prange(H, schedule="dynamic", num_threads=num_threads):
            for col in range(W):
                if fit_depth == NULL:
                    _keep_coplanar_pixel(&depth[0, 0], &anchors[row, col, 0], K_inv, W, row, col, max_rel_error,
                                         min_inliers)
                else:
                    _fit_pixel(&depth[0, 0], &anchors[row, col, 0], K_inv, W, row, col, max_rel_error, min_inliers,
                               fit_depth + row * W + col, fit_normal + 3 * (row * W + col), NULL)


def fit_anchor_planes(const float[:, ::1] depth, int32_t[:, :, ::1] anchors, const double[:, ::1] K,
                      float[:, ::1] fit_depth, float[:, :, ::1] fit_normal, float max_rel_error, int min_inliers,
                      int num_threads):
    """For every pixel with anchors, the plane through three of them (triangle around the pixel)
    that the most anchors agree with, as ``fit_depth`` (0: none) and ``fit_normal`` (APD-MVS's
    fitted plane of a weak pixel's anchors)."""
    cdef int H = depth.shape[0], W = depth.shape[1]
    if fit_depth.shape[0] != H or fit_depth.shape[1] != W or fit_normal.shape[0] != H or fit_normal.shape[1] != W:
        raise ValueError("fit_depth / fit_normal do not match the depth map")
    if H * W == 0:
        return
    _anchor_planes(depth, anchors, K, max_rel_error, min_inliers, &fit_depth[0, 0], &fit_normal[0, 0, 0],
                   num_threads)


def keep_coplanar_anchors(const float[:, ::1] depth, int32_t[:, :, ::1] anchors, const double[:, ::1] K,
                          float max_rel_error, int min_inliers, int num_threads):
    """APD-MVS's reliability rule for a weak pixel's anchors, in place: keep the anchors on the
    plane of :func:`fit_anchor_planes` (through three anchors around the pixel, the most anchors
    within ``max_rel_error``); a pixel without such a plane (fewer than ``min_inliers`` agree)
    loses all its anchors, and so its deformation."""
    _anchor_planes(depth, anchors, K, max_rel_error, min_inliers, NULL, NULL, num_threads)
