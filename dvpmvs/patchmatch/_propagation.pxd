# Propagation and view selection (ACMM's adaptive checkerboard and multi-hypothesis joint view
# selection): the planes of the other colour's best neighbours carried to the pixel, their costs
# against every source, the sources' selection probabilities and Monte-Carlo weights, and the
# best candidate under them. Inline functions cimported by the kernels (no .pyx of its own).

from libc.math cimport exp
from libc.stdint cimport uint64_t, uint32_t

from dvpmvs.patchmatch._context cimport (Ctx, Work, MAX_ANCHORS, MAX_CANDIDATES, MAX_GROUP, MAX_SOURCES,
                                         NUM_CANDIDATES, NEAR_DEPTH, FAR_SAMPLES, _plane_depth, _ray, _same_plane,
                                         _uniform)
from dvpmvs.patchmatch._window_cost cimport Patches, _aggregate, _all_sources, _group_costs, _group_scored, _prior_term
from dvpmvs.patchmatch._refinement cimport _faces_sources


cdef struct Candidates:
    # A pixel's propagated hypotheses: the NUM_CANDIDATES checkerboard candidates, then for a
    # deformed pixel its anchors' planes. ``pixel``: where each comes from, -1 for none.
    int num
    int pixel[MAX_CANDIDATES]
    float depth[MAX_CANDIDATES]
    float normal[MAX_CANDIDATES * 3]
    float costs[MAX_CANDIDATES * MAX_SOURCES]  # per candidate, its cost against every source


cdef inline void _consider(const Ctx* c, int row, int col, float* best_cost, int* best_pix) noexcept nogil:
    cdef Py_ssize_t q
    if row < 0 or col < 0 or row >= c.H or col >= c.W:
        return
    q = <Py_ssize_t>row * c.W + col
    if c.depth[q] > 0 and c.cost[q] < best_cost[0]:
        best_cost[0] = c.cost[q]
        best_pix[0] = <int>q


cdef inline void _candidates(const Ctx* c, int row, int col, int* cand) noexcept nogil:
    """Adaptive checkerboard sampling: in each of 4 V-shaped near regions and 4 far strips
    (up, down, left, right) the pixel of the other colour with the lowest cost; -1 if none."""
    cdef int d, s, k, e
    cdef float best
    cdef int dirs_r[4]
    cdef int dirs_c[4]
    dirs_r[0] = -1
    dirs_c[0] = 0
    dirs_r[1] = 1
    dirs_c[1] = 0
    dirs_r[2] = 0
    dirs_c[2] = -1
    dirs_r[3] = 0
    dirs_c[3] = 1
    for d in range(4):
        # Near: a V opening away from the pixel, rows s = 1..3 of width 2s - 1 (other colour only).
        best = 1e30
        cand[d] = -1
        for s in range(1, NEAR_DEPTH + 1):
            for e in range(-(s - 1), s, 2):
                _consider(c, row + dirs_r[d] * s + dirs_c[d] * e, col + dirs_c[d] * s + dirs_r[d] * e,
                          &best, &cand[d])
        # Far: a straight strip from distance 5 on, every second pixel.
        best = 1e30
        cand[4 + d] = -1
        for k in range(FAR_SAMPLES):
            s = NEAR_DEPTH + 2 + 2 * k
            _consider(c, row + dirs_r[d] * s, col + dirs_c[d] * s, &best, &cand[4 + d])


cdef inline int _same_plane_as(const float* cand_depth, const float* cand_normal, const int* cand, int i,
                               float d, const float* n) noexcept nogil:
    """The first candidate before ``i`` with the same plane as (d, n), or -1."""
    cdef int k
    for k in range(i):
        if cand[k] >= 0 and _same_plane(d, n, cand_depth[k], &cand_normal[3 * k]):
            return k
    return -1


cdef inline int _propagated(const Ctx* c, int row, int col, const Patches* pp, const float* ray,
                            Candidates* cd, Work* evals) noexcept nogil:
    """Step 1 of a pixel's update: the candidates from the other colour, their plane carried to
    this pixel, scored against every source (the checkerboard ones; view selection reads them),
    their windows matched together (``_group_costs``). A deformed pixel also tries its anchors'
    planes (they lie on its surface, by construction of the regions), those of the other colour
    only: the same colour is being updated concurrently. Returns the number of candidates."""
    cdef Py_ssize_t pix = <Py_ssize_t>row * c.W + col
    cdef const float* n = c.normal + 3 * pix
    cdef const float* vc = c.view_cost + pix * c.S
    cdef float ray_q[3]
    cdef int same_as[NUM_CANDIDATES]
    cdef int member[MAX_GROUP]
    cdef float depths[MAX_GROUP]
    cdef float normals[3 * MAX_GROUP]
    cdef float costs[MAX_GROUP * MAX_SOURCES]
    cdef int i, j, k, q, qrow, qcol, num_valid = 0, count = 0
    cdef float d
    _candidates(c, row, col, cd.pixel)
    cd.num = NUM_CANDIDATES
    if pp.num_anchors > 0:
        for k in range(MAX_ANCHORS):
            q = c.anchors[pix * MAX_ANCHORS + k]
            if q >= 0 and ((q // c.W) + (q % c.W)) % 2 != (row + col) % 2 and c.depth[q] > 0:
                cd.pixel[cd.num] = q
            else:
                cd.pixel[cd.num] = -1
            cd.num += 1
    for i in range(cd.num):
        if cd.pixel[i] < 0:
            continue
        q = cd.pixel[i]
        qrow = q // c.W
        qcol = q - qrow * c.W
        _ray(c, qcol, qrow, ray_q)
        d = _plane_depth(c.normal + 3 * q, c.depth[q], ray_q, ray)
        if not d > 0:
            d = c.depth[q]
        cd.depth[i] = d
        for k in range(3):
            cd.normal[3 * i + k] = c.normal[3 * q + k]
        # Anchors' planes do not vote in the view selection: they are scored after it, on the
        # selected sources only (the aggregate reads no other), which is the same result for a
        # fraction of the deformed windows.
        if i < NUM_CANDIDATES:
            # Where propagation has converged, neighbours carry the pixel's own plane or each
            # other's: their costs are known (the pixel's ``vc`` is its plane's, kept current).
            same_as[i] = _same_plane_as(cd.depth, cd.normal, cd.pixel, i, d, &cd.normal[3 * i])
            if same_as[i] < 0 and _same_plane(d, &cd.normal[3 * i], c.depth[pix], n):
                for j in range(c.S):
                    cd.costs[i * MAX_SOURCES + j] = vc[j]
            elif same_as[i] < 0:
                # View selection needs the cost in every source it may draw.
                member[count] = i
                depths[count] = d
                for k in range(3):
                    normals[3 * count + k] = cd.normal[3 * i + k]
                count += 1
        num_valid += 1
    if count > 0:
        _group_costs(c, pp, _all_sources(c), count, depths, normals, row, col, ray, costs, evals)
        for k in range(count):
            for j in range(c.S):
                cd.costs[member[k] * MAX_SOURCES + j] = costs[k * MAX_SOURCES + j]
    for i in range(NUM_CANDIDATES):
        if cd.pixel[i] >= 0 and same_as[i] >= 0:
            for j in range(c.S):
                cd.costs[i * MAX_SOURCES + j] = cd.costs[same_as[i] * MAX_SOURCES + j]
    return num_valid


cdef inline uint32_t _select_views(const Ctx* c, int row, int col, const Candidates* cd, uint64_t key,
                                   uint64_t* counter, float* w) noexcept nogil:
    """Step 2: multi-hypothesis joint view selection. Each source's probability from how many
    checkerboard candidates it finds good (cost under ``good_cost``) and bad (over ``bad_cost``),
    times a prior from the 4 direct neighbours' selections; the weights ``w`` are the counts of
    ``num_view_draws`` Monte-Carlo draws. Returns the mask of the sources drawn (0: none, and
    ``w`` is not to be used)."""
    cdef float prior[MAX_SOURCES]
    cdef float prob[MAX_SOURCES]
    cdef int nb_r[4]
    cdef int nb_c[4]
    cdef int i, j, k, good, bad, _draw
    cdef float value, sum_good, total, r
    cdef uint32_t mask
    nb_r[0] = row - 1
    nb_c[0] = col
    nb_r[1] = row + 1
    nb_c[1] = col
    nb_r[2] = row
    nb_c[2] = col - 1
    nb_r[3] = row
    nb_c[3] = col + 1
    for j in range(c.S):
        prior[j] = 0
    for k in range(4):
        if nb_r[k] < 0 or nb_c[k] < 0 or nb_r[k] >= c.H or nb_c[k] >= c.W:
            continue
        mask = c.selected[nb_r[k] * c.W + nb_c[k]]
        for j in range(c.S):
            prior[j] = prior[j] + (0.9 if (mask >> j) & 1 else 0.1)
    total = 0
    for j in range(c.S):
        good = 0
        bad = 0
        sum_good = 0
        for i in range(NUM_CANDIDATES):
            if cd.pixel[i] < 0:
                continue
            value = cd.costs[i * MAX_SOURCES + j]
            if value < c.p.good_cost:
                sum_good = sum_good + exp(-value * value / 0.18)
                good += 1
            if value > c.p.bad_cost:
                bad += 1
        if good > 2 and bad < 3:
            prob[j] = sum_good / good
        elif bad < 3:
            prob[j] = exp(-c.p.good_cost * c.p.good_cost / 0.32)
        else:
            prob[j] = 0
        prob[j] = prob[j] * (prior[j] if prior[j] > 0 else 1.0)
        total = total + prob[j]
        w[j] = 0
    if total <= 0:
        return 0
    # Monte-Carlo draws from the selection probabilities; weights are the draw counts.
    mask = 0
    for _draw in range(c.p.num_view_draws):
        r = _uniform(key, counter[0]) * total
        counter[0] += 1
        value = 0
        for j in range(c.S):
            value = value + prob[j]
            if r < value or j == c.S - 1:
                if prob[j] > 0:
                    w[j] = w[j] + 1
                    mask = mask | (<uint32_t>1 << j)
                break
    return mask


cdef inline int _adopt_best_candidate(const Ctx* c, int row, int col, const Patches* pp, const float* ray,
                                      Candidates* cd, const float* w, uint32_t mask, float den, float* best_agg,
                                      float* best_photo, Work* evals) noexcept nogil:
    """Step 3: the best of the pixel's current hypothesis (``best_agg``, ``best_photo``) and the
    candidates under the new weights ``w``; the winner's plane and view costs are taken.
    Hypotheses compete on photometric (+ geometric) cost plus the planar-prior term; the stored
    cost stays without the prior, so that filtering judges the images alone. Anchors' planes,
    like the refinement's hypotheses, are scored together on the selected sources only (the
    aggregate reads no other) and given up once they cannot win against the best checkerboard
    candidate (``_group_scored``); they come after the checkerboard candidates and are compared
    in their order, so the same hypothesis wins as in one pass in order. Returns the index of the
    candidate taken, -1 for none."""
    cdef Py_ssize_t pix = <Py_ssize_t>row * c.W + col
    cdef float* n = c.normal + 3 * pix
    cdef float* vc = c.view_cost + pix * c.S
    cdef int member[MAX_GROUP]
    cdef float depths[MAX_GROUP]
    cdef float normals[3 * MAX_GROUP]
    cdef float priors[MAX_GROUP]
    cdef float costs[MAX_GROUP * MAX_SOURCES]
    cdef int i, j, k, g, count = 0, best_i = -1
    cdef uint32_t scored = 0
    cdef float photo, agg, prior_i
    for i in range(cd.num):
        if cd.pixel[i] < 0:
            continue
        if c.p.normal_aggregation and not _faces_sources(c, mask, cd.depth[i], &cd.normal[3 * i], ray):
            continue  # a surface that a selected source would see from behind
        prior_i = _prior_term(c, pix, cd.depth[i], &cd.normal[3 * i])
        if i >= NUM_CANDIDATES:
            if _same_plane(cd.depth[i], &cd.normal[3 * i], c.depth[pix], n):
                cd.pixel[i] = -1  # the pixel's own plane: it cannot beat itself
                continue
            if _same_plane_as(cd.depth, cd.normal, cd.pixel, i, cd.depth[i], &cd.normal[3 * i]) >= 0:
                cd.pixel[i] = -1  # a plane already scored: equal costs cannot win over it
                continue
            member[count] = i
            depths[count] = cd.depth[i]
            priors[count] = prior_i
            for k in range(3):
                normals[3 * count + k] = cd.normal[3 * i + k]
            count += 1
            continue
        photo = _aggregate(c, &cd.costs[i * MAX_SOURCES], w)
        agg = photo + prior_i
        if agg < best_agg[0]:
            best_agg[0] = agg
            best_photo[0] = photo
            best_i = i
    if count > 0:
        scored = _group_scored(c, pp, w, den, priors, best_agg[0], count, depths, normals, row, col, ray, costs,
                               evals)
    for g in range(count):
        if not (scored >> g) & 1:
            continue  # it cannot win (nor can a later anchor with its plane, which it still skipped)
        i = member[g]
        for j in range(c.S):
            cd.costs[i * MAX_SOURCES + j] = costs[g * MAX_SOURCES + j]
        photo = _aggregate(c, &cd.costs[i * MAX_SOURCES], w)
        agg = photo + priors[g]
        if agg < best_agg[0]:
            best_agg[0] = agg
            best_photo[0] = photo
            best_i = i
    if best_i >= 0:
        c.depth[pix] = cd.depth[best_i]
        for k in range(3):
            n[k] = cd.normal[3 * best_i + k]
        for j in range(c.S):
            vc[j] = cd.costs[best_i * MAX_SOURCES + j]
    return best_i
