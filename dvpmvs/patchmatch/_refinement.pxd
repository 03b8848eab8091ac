# Refinement of a pixel's plane: perturbed and random hypotheses, the planar prior's and the
# fitted planes, judged by the selected sources; and the geometry-driven constraints of the
# paper's section 3.5 (normal aggregation: a plane must face every selected source; depth
# aggregation: perturbed depths from epipolar intervals). Inline functions cimported by the
# kernels (no .pyx of its own).

from libc.math cimport sqrt, fabs
from libc.stdint cimport uint64_t, uint32_t

from dvpmvs.patchmatch._context cimport (Ctx, Work, MAX_GROUP, MAX_SOURCES, NUM_REFINE, _normalise, _random_normal,
                                         _same_plane, _random_depth, _uniform)
from dvpmvs.patchmatch._window_cost cimport Patches, _aggregate, _group_scored, _prior_term


cdef inline bint _faces_sources(const Ctx* c, uint32_t mask, float depth, const float* n,
                                const float* ray) noexcept nogil:
    """Paper section 3.5, normal aggregation: True when the plane (depth, n) faces every source
    of ``mask``, n . (P - C_j) <= 0 for its point P = depth * ray and each source centre C_j.
    A source cannot see the back of a surface, so such a hypothesis cannot be what it sees."""
    cdef int j
    cdef float px = depth * ray[0], py = depth * ray[1], pz = depth
    for j in range(c.S):
        if ((mask >> j) & 1 and n[0] * (px - c.centre[3 * j]) + n[1] * (py - c.centre[3 * j + 1])
                + n[2] * (pz - c.centre[3 * j + 2]) > 0):
            return False
    return True


cdef inline int _kth_smallest(const float* v, int n, int k) noexcept nogil:
    """The index of the k-th smallest (0-based) of v[0:n], ties in index order."""
    cdef int i, m, rank
    for i in range(n):
        rank = 0
        for m in range(n):
            if v[m] < v[i] or (v[m] == v[i] and m < i):
                rank += 1
        if rank == k:
            return i
    return 0


cdef inline bint _epipolar_intervals(const Ctx* c, uint32_t mask, float depth, int row, int col,
                                     float* out) noexcept nogil:
    """Paper section 3.5, depth aggregation: the depths at which the point of pixel (row, col)
    at ``depth`` moves by ``aggregation_inner`` and ``aggregation_outer`` pixels along its
    epipolar line in each source of ``mask``, nearer and farther, aggregated over the sources into a near interval
    ``out[0:2]`` and a far one ``out[2:4]``. On each side, with mu = min(``aggregation_views``,
    sources): the interval of the source whose inner depth is the mu-th nearest to ``depth``
    (the mu-th most sensitive source there), so that at its inner end at least mu sources move
    by ``aggregation_inner`` pixels or more, and at its outer end that source moves by
    ``aggregation_outer`` and the less sensitive ones by less. (Taking the two ends' order
    statistics apart, as the paper's formula reads, crosses them over where the sources'
    sensitivities differ by more than outer / inner.) A source whose line ends (epipole or
    vanishing point) within reach is left out. False without any source."""
    cdef float near_out[MAX_SOURCES]
    cdef float near_in[MAX_SOURCES]
    cdef float far_in[MAX_SOURCES]
    cdef float far_out[MAX_SOURCES]
    cdef float steps[4]
    cdef float found[4]
    cdef const float* A
    cdef const float* k
    cdef float m0, m1, m2, den, x0, y0, gx, gy, g, ex, ey, xs, num, dn, d
    cdef int j, s, mu, count = 0
    cdef bint ok
    steps[0] = -c.p.aggregation_outer
    steps[1] = -c.p.aggregation_inner
    steps[2] = c.p.aggregation_inner
    steps[3] = c.p.aggregation_outer
    for j in range(c.S):
        if not (mask >> j) & 1:
            continue
        # Source j sees the point at depth d as (d m + k) projected, with the homography's terms:
        # m = K_j R_j K^-1 (col, row, 1) = A_j (col, row, 1), k = K_j t_j = b_j.
        A = c.A + 9 * j
        k = c.b + 3 * j
        m0 = A[0] * col + A[1] * row + A[2]
        m1 = A[3] * col + A[4] * row + A[5]
        m2 = A[6] * col + A[7] * row + A[8]
        den = depth * m2 + k[2]
        if not den > 1e-8:
            continue
        x0 = (depth * m0 + k[0]) / den
        y0 = (depth * m1 + k[1]) / den
        # The line's direction: where the image point goes as the depth grows.
        gx = (m0 * k[2] - m2 * k[0]) / (den * den)
        gy = (m1 * k[2] - m2 * k[1]) / (den * den)
        g = sqrt(gx * gx + gy * gy)
        if not g > 1e-12:
            continue
        ex = gx / g
        ey = gy / g
        ok = True
        for s in range(4):
            # Back along the line to the ray: solve the coordinate that moves the most for d.
            if fabs(ex) >= fabs(ey):
                xs = x0 + steps[s] * ex
                num = k[0] - xs * k[2]
                dn = xs * m2 - m0
            else:
                xs = y0 + steps[s] * ey
                num = k[1] - xs * k[2]
                dn = xs * m2 - m1
            d = num / dn if dn != 0 else -1
            if not (d > 0 and (d < depth if s < 2 else d > depth)):
                ok = False
                break
            found[s] = d
        if not ok:
            continue
        near_out[count] = found[0]
        near_in[count] = found[1]
        far_in[count] = found[2]
        far_out[count] = found[3]
        count += 1
    if count == 0:
        return False
    mu = (c.p.aggregation_views if c.p.aggregation_views < count else count) - 1
    j = _kth_smallest(near_in, count, count - 1 - mu)  # the mu-th largest inner depth below ``depth``
    out[0] = near_out[j]
    out[1] = near_in[j]
    j = _kth_smallest(far_in, count, mu)  # the mu-th smallest inner depth above it
    out[2] = far_in[j]
    out[3] = far_out[j]
    return True


cdef inline bint _refine(const Ctx* c, int row, int col, const Patches* pp, const float* ray, const float* w,
                         uint32_t mask, float den, uint64_t key, uint64_t* counter, float* best_agg,
                         float* best_photo, Work* evals) noexcept nogil:
    """Step 4 of a pixel's update: perturbed and random depths and normals, and the planar
    prior's and the fitted plane, judged by the selected sources (``w``, ``mask``, ``den``), their
    windows matched together (``_group_scored``); the best of them replaces the pixel's plane and
    view costs when it beats ``best_agg`` (updated, with ``best_photo``). True when the plane
    changed."""
    cdef Py_ssize_t pix = <Py_ssize_t>row * c.W + col
    cdef float* n = c.normal + 3 * pix
    cdef float* vc = c.view_cost + pix * c.S
    cdef float depths[MAX_GROUP]
    cdef float normals[3 * MAX_GROUP]
    cdef float priors[MAX_GROUP]
    cdef float costs[MAX_GROUP * MAX_SOURCES]
    cdef float* hyp_n
    cdef float intervals[4]
    cdef bint epipolar = False
    cdef int i, j, k, g, count = 0, best_g = -1
    cdef uint32_t scored
    cdef float pert = c.p.perturbation, d, r, photo, agg
    if c.p.depth_aggregation:
        epipolar = _epipolar_intervals(c, mask, c.depth[pix], row, col, intervals)
    for i in range(NUM_REFINE + 2):
        # 0: random depth, 1: random normal, 2: perturbed depth, 3: perturbed normal, 4: both,
        # 5: the planar prior's own plane, 6: the fitted plane (through the anchors, or the
        # region's), when there is one. Each from the pixel's plane as the update found it.
        hyp_n = &normals[3 * count]
        if i == NUM_REFINE:
            if c.prior_depth == NULL or not c.prior_depth[pix] > 0:
                continue
            d = c.prior_depth[pix]
            for k in range(3):
                hyp_n[k] = c.prior_normal[3 * pix + k]
        elif i == NUM_REFINE + 1:
            if c.fit_depth == NULL or not c.fit_depth[pix] > 0:
                continue
            d = c.fit_depth[pix]
            for k in range(3):
                hyp_n[k] = c.fit_normal[3 * pix + k]
        elif i == 0:
            d = _random_depth(c.p, _uniform(key, counter[0]))
        elif (i == 2 or i == 4) and epipolar:
            # Nearer or farther (one draw for both): a depth within the side's interval.
            r = 2.0 * _uniform(key, counter[0])
            if r < 1:
                d = intervals[0] + (intervals[1] - intervals[0]) * r
            else:
                d = intervals[2] + (intervals[3] - intervals[2]) * (r - 1)
        elif i == 2 or i == 4:
            d = c.depth[pix] * (1.0 + pert * (2.0 * _uniform(key, counter[0]) - 1.0))
        else:
            d = c.depth[pix]
        counter[0] += 1
        if i >= NUM_REFINE:
            pass
        elif i == 1:
            _random_normal(key, counter[0], ray, hyp_n)
        elif i == 3 or i == 4:
            for k in range(3):
                hyp_n[k] = n[k] + pert * (2.0 * _uniform(key, counter[0] + k) - 1.0)
            _normalise(hyp_n)
            if hyp_n[0] * ray[0] + hyp_n[1] * ray[1] + hyp_n[2] * ray[2] >= 0:
                continue
        else:
            for k in range(3):
                hyp_n[k] = n[k]
        counter[0] += 3
        if not d > 0:
            continue
        if i >= NUM_REFINE and _same_plane(d, hyp_n, c.depth[pix], n):
            continue  # the prior's or the fitted plane already taken: it cannot beat itself
        if c.p.normal_aggregation and not _faces_sources(c, mask, d, hyp_n, ray):
            continue
        depths[count] = d
        priors[count] = _prior_term(c, pix, d, hyp_n)
        count += 1
    if count == 0:
        return False
    # Given up against the best before them, compared in their order: the same winner as one by one.
    scored = _group_scored(c, pp, w, den, priors, best_agg[0], count, depths, normals, row, col, ray, costs, evals)
    for g in range(count):
        if not (scored >> g) & 1:
            continue
        photo = _aggregate(c, &costs[g * MAX_SOURCES], w)
        agg = photo + priors[g]
        if agg < best_agg[0]:
            best_agg[0] = agg
            best_photo[0] = photo
            best_g = g
    if best_g >= 0:
        c.depth[pix] = depths[best_g]
        for k in range(3):
            n[k] = normals[3 * best_g + k]
        for j in range(c.S):
            vc[j] = costs[best_g * MAX_SOURCES + j]
        return True
    return False
