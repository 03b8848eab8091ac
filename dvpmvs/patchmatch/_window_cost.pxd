# The matching cost of a plane hypothesis (paper eq. 3): the bilateral-weighted NCC of a window
# warped into a source by the plane's homography, the deformed cost of a weak pixel (its sparser
# centre window and its anchors' windows), the geometric term of the geometric pass, the
# planar-prior term, and the view-selection-weighted aggregate over the sources, with the exact
# early stop of hypotheses that cannot win. Inline functions cimported by the kernels.

from libc.math cimport exp, expf, sqrt, fabs
from libc.stdint cimport int32_t, uint8_t, uint32_t

from dvpmvs.patchmatch._context cimport (Ctx, Window, Work, MAX_ANCHORS, MAX_GROUP, MAX_COST, MAX_SAMPLES,
                                         MAX_SOURCES, _homography, _plane_vector)
from dvpmvs.patchmatch._visibility cimport _reprojection_error

cdef extern from "_window_cost_simd.h":
    # Batches of (window, source) pairs matched at once, one per vector lane (see the header).
    ctypedef struct dvpmvs_windows:
        int n
        float x[256][8]
        float y[256][8]
        float w[256][8]
        float v[256][8]
    int DVPMVS_BATCH  # lanes of a batch: 8
    ctypedef struct dvpmvs_batch:
        int count
        int32_t slot[8]
        int32_t offset[8]
        int32_t width[8]
        int32_t height[8]
        float H[9][8]
    ctypedef struct dvpmvs_sums:
        int count
        float sum_w[8]
        float mean[8]
        float var[8]
        float sws[8]
        float swss[8]
        float swrs[8]
    int DVPMVS_SIMD_SCALAR
    int DVPMVS_SIMD_AVX2
    int dvpmvs_simd_level
    int dvpmvs_simd_select(int requested) nogil
    int dvpmvs_window_sums(const float* img, int stride, int width, int height, const float* H, const float* x,
                           const float* y, const float* w, const float* v, int n, int step, float* sws, float* swss,
                           float* swrs) nogil
    uint32_t dvpmvs_batch_sums(const float* stack, int stride, const dvpmvs_windows* table, dvpmvs_batch* batch,
                               float* sws, float* swss, float* swrs) nogil
    void dvpmvs_ncc(const dvpmvs_sums* sums, float* out) nogil


cdef struct RefPatch:
    int n
    float x[MAX_SAMPLES]
    float y[MAX_SAMPLES]
    float w[MAX_SAMPLES]
    float v[MAX_SAMPLES]
    float sum_w
    float mean
    float var


cdef inline void _ref_patch(const Ctx* c, int row, int col, RefPatch* p) noexcept nogil:
    """Bilateral weights and values of the reference window around (row, col); samples outside
    the image are left out. Weights: spatial Gaussian x colour Gaussian of the difference to the
    centre pixel (``_colour_weight``)."""
    _window_patch(c, row, col, p, &c.p.plain, _cached_weights(c, row, col) if c.plain_cached else NULL)


cdef inline const float* _cached_weights(const Ctx* c, int row, int col) noexcept nogil:
    """The anchor window's colour weights around (row, col) computed once per level, or NULL."""
    if c.anchor_slot == NULL:
        return NULL
    cdef int slot = c.anchor_slot[<Py_ssize_t>row * c.W + col]
    return NULL if slot < 0 else c.anchor_weight + <Py_ssize_t>slot * c.p.anchor.n


cdef inline float _colour_weight(const Ctx* c, const Window* window, int k, float v, float centre) noexcept nogil:
    """Sample k's bilateral weight in ``window``: its spatial weight times the colour Gaussian of
    its value ``v``'s difference to the centre pixel's."""
    cdef float d = v - centre
    return window.spatial[k] * expf(-d * d * c.p.inv_two_sigma_color_sq)


cdef inline void _window_patch(const Ctx* c, int row, int col, RefPatch* p, const Window* window,
                               const float* weights) noexcept nogil:
    """The samples of ``window`` around (row, col) (see ``_ref_patch``); ``weights`` (else NULL):
    the samples' colour weights computed before (``anchor_windows``), one per sample of the
    window."""
    cdef float centre = c.ref[row * c.W + col]
    cdef int k, x, y
    cdef float v, sw = 0, swv = 0, swvv = 0
    p.n = 0
    for k in range(window.n):
        x = col + window.off_x[k]
        y = row + window.off_y[k]
        if x < 0 or y < 0 or x >= c.W or y >= c.H:
            continue
        v = c.ref[y * c.W + x]
        p.x[p.n] = x
        p.y[p.n] = y
        p.v[p.n] = v
        p.w[p.n] = weights[k] if weights != NULL else _colour_weight(c, window, k, v, centre)
        sw = sw + p.w[p.n]
        swv = swv + p.w[p.n] * v
        swvv = swvv + p.w[p.n] * v * v
        p.n += 1
    p.sum_w = sw
    if sw > 0:
        p.mean = swv / sw
        p.var = swvv / sw - p.mean * p.mean
    else:
        p.mean = 0
        p.var = 0


cdef inline float _ncc_cost(const Ctx* c, const RefPatch* p, int j, const float* H) noexcept nogil:
    """1 - bilateral-weighted NCC between the reference patch and its warp into source j, the
    samples clamped to the source's border; MAX_COST when a sample falls behind the source camera
    (the scalar path of the header's kernel, ``dvpmvs_window_sums``)."""
    cdef float sws, swss, swrs
    if dvpmvs_window_sums(c.src + <Py_ssize_t>j * c.SH * c.SW, c.SW, c.src_size[2 * j], c.src_size[2 * j + 1], H,
                          p.x, p.y, p.w, p.v, p.n, 1, &sws, &swss, &swrs):
        return MAX_COST
    return _ncc_from_sums(p, sws, swss, swrs)


cdef inline float _ncc_from_sums(const RefPatch* p, float sws, float swss, float swrs) noexcept nogil:
    """1 - NCC from the window's weighted sums of the warped samples s: sum w s, sum w s^2 and
    sum w s v (v the reference's values)."""
    cdef float mean_s, var_s, cov, denom, s
    mean_s = sws / p.sum_w
    var_s = swss / p.sum_w - mean_s * mean_s
    # Textureless patches carry no information: maximal cost, as in COLMAP and ACMM.
    if p.var < 1e-7 or var_s < 1e-7:
        return MAX_COST
    cov = swrs / p.sum_w - p.mean * mean_s
    denom = sqrt(p.var * var_s)
    s = 1.0 - cov / denom
    if s < 0:
        return 0
    if s > MAX_COST:
        return MAX_COST
    return s


cdef inline void _fill_table(const RefPatch* patches, int num, dvpmvs_windows* table) noexcept nogil:
    """The samples of windows 0..``num`` - 1 transposed into a table's slots (see the header); a
    shorter window repeats its last sample's position with weight and value 0."""
    cdef int a, k, last
    table.n = 0
    for a in range(num):
        if patches[a].n > table.n:
            table.n = patches[a].n
    for a in range(num):
        for k in range(table.n):
            last = k if k < patches[a].n else patches[a].n - 1
            table.x[k][a] = patches[a].x[last]
            table.y[k][a] = patches[a].y[last]
            table.w[k][a] = patches[a].w[k] if k < patches[a].n else 0
            table.v[k][a] = patches[a].v[k] if k < patches[a].n else 0


cdef struct Patches:
    # A pixel's matching support: its own window, and for a weak pixel with anchors (deformable
    # PatchMatch) a sparser centre window plus one window around each anchor.
    RefPatch centre
    float centre_weight  # lambda of eq. 3 for this pixel: 0 where its centre window is dropped
    int num_anchors
    RefPatch anchor[MAX_ANCHORS]
    # With the vector path, the windows' samples transposed for batches (``_score_group``).
    dvpmvs_windows centre_table
    dvpmvs_windows anchor_table
    uint32_t anchor_sources[MAX_ANCHORS]  # the sources each anchor is visible in (bit j: source j)
    int anchors_seen[MAX_SOURCES]  # per source, how many of the anchors it sees (once per pixel)


cdef inline void _plain_patches(const Ctx* c, int row, int col, Patches* pp) noexcept nogil:
    """The matching support of a pixel without anchors: its own window."""
    pp.num_anchors = 0
    pp.centre_weight = c.p.deform_lambda
    _ref_patch(c, row, col, &pp.centre)
    if dvpmvs_simd_level != DVPMVS_SIMD_SCALAR:
        _fill_table(&pp.centre, 1, &pp.centre_table)


cdef inline void _patches(const Ctx* c, int row, int col, Patches* pp) noexcept nogil:
    cdef Py_ssize_t pix = <Py_ssize_t>row * c.W + col
    cdef int a, j, q, count = 0
    pp.num_anchors = 0
    if c.anchors != NULL:
        for a in range(MAX_ANCHORS):
            if c.anchors[pix * MAX_ANCHORS + a] >= 0:
                count += 1
    if count < c.p.min_anchors or count == 0:
        _plain_patches(c, row, col, pp)
        return
    _window_patch(c, row, col, &pp.centre, &c.p.coarse, NULL)
    pp.centre_weight = 0 if c.centre_dropped != NULL and c.centre_dropped[pix] else c.p.deform_lambda
    for a in range(MAX_ANCHORS):
        q = c.anchors[pix * MAX_ANCHORS + a]
        if q < 0:
            continue
        _window_patch(c, q // c.W, q % c.W, &pp.anchor[pp.num_anchors], &c.p.anchor,
                      _cached_weights(c, q // c.W, q % c.W))
        pp.anchor_sources[pp.num_anchors] = c.anchor_visible[q] if c.anchor_visible != NULL else <uint32_t>0xFFFFFFFF
        if pp.anchor[pp.num_anchors].sum_w > 0:
            pp.num_anchors += 1
    for j in range(c.S):
        pp.anchors_seen[j] = 0
        for a in range(pp.num_anchors):
            if (pp.anchor_sources[a] >> j) & 1:
                pp.anchors_seen[j] += 1
    if dvpmvs_simd_level != DVPMVS_SIMD_SCALAR:
        _fill_table(&pp.centre, 1, &pp.centre_table)
        _fill_table(pp.anchor, pp.num_anchors, &pp.anchor_table)


cdef struct Bound:
    # A hypothesis competing against the best aggregated cost so far (``_aggregate`` plus the
    # planar-prior term): its views are summed as ``_aggregate`` sums them, in source order.
    float num  # sum of weight * cost over the selected sources scored so far
    float weight  # the weight of the source being scored
    float den  # sum of the selected sources' weights
    float prior  # the hypothesis's planar-prior term
    float best  # the aggregated cost to beat


cdef inline bint _beaten(const Bound* b, float view_cost) noexcept nogil:
    """True when ``view_cost``, a lower bound of the current source's cost, already puts the
    hypothesis's aggregated cost at or above ``b.best``. Exact: every cost is >= 0, so the
    running sum can only grow, and float rounding is monotone, so the final sum, quotient and
    prior term computed as ``_aggregate`` and its caller do are at least these."""
    cdef float num = b.num + b.weight * view_cost
    cdef float photo = num / b.den
    return photo + b.prior >= b.best


cdef inline bint _scored_view(const Ctx* c, const Patches* pp, int j, int row, int col, float depth, const float* n,
                              const float* ray, const Bound* bound, float* cost, Work* windows) noexcept nogil:
    """The pixel's cost against source j into ``cost``, one window after the other (the scalar
    path; ``_score_group`` matches them in batches): plain, 1 - NCC of the pixel's window, or
    for a deformed pixel lambda * m(p, B_p) + (1 - lambda) * mean over anchors m(s, B_s) (paper
    eq. 3), plus in the geometric pass geom_weight * min(reprojection error, geom_max_error); the
    window is warped by the homography of the pixel's own plane. With anchor visibility
    (``c.anchor_visible``), the mean runs over the anchors visible in source j (paper eq. 10-11),
    and the centre window alone judges a source that sees none of them. ``windows`` counts the
    windows matched. With a ``bound`` (else NULL), stops as soon as the hypothesis cannot win
    (``_beaten``) and returns False; the geometric term is computed first, then the centre
    window, then the anchors, so that an early stop skips most of the work."""
    cdef float H[9]
    cdef float photo, anchors = 0, centre, geom = 0  # geom + 0 leaves a cost >= 0 unchanged
    cdef int a
    cdef int visible = pp.anchors_seen[j] if pp.num_anchors > 0 else 0  # the anchors source j sees
    cdef uint32_t bit = <uint32_t>1 << j
    if c.src_depth != NULL:
        geom = c.p.geom_weight * _reprojection_error(c, j, col, row, depth, ray)
    if bound != NULL and _beaten(bound, geom):
        return False
    cdef float m[3]
    photo = _warp(c, j, row, col, m, H) if _plane_vector(c, depth, n, ray, m) else MAX_COST
    if photo == 0:
        windows.windows += 1
        windows.samples += pp.centre.n
        if visible == 0:
            photo = _ncc_cost(c, &pp.centre, j, H)
        else:
            centre = _ncc_cost(c, &pp.centre, j, H)
            for a in range(pp.num_anchors):
                if not (pp.anchor_sources[a] & bit):
                    continue
                if bound != NULL and _beaten(bound, _deformed(pp, centre, anchors, visible) + geom):
                    return False
                anchors = anchors + _ncc_cost(c, &pp.anchor[a], j, H)
                windows.windows += 1
                windows.samples += pp.anchor[a].n
            photo = _deformed(pp, centre, anchors, visible)
    cost[0] = photo + geom
    return True


cdef inline float _deformed(const Patches* pp, float centre, float anchors, int num_anchors) noexcept nogil:
    """Paper eq. 3 from the centre window's cost and the sum of the anchor windows' costs; with
    the centre window dropped (``pp.centre_weight`` 0), the paper's highlight form of eq. 3: the
    anchors' mean alone."""
    return pp.centre_weight * centre + (1.0 - pp.centre_weight) * anchors / num_anchors


cdef inline uint32_t _all_sources(const Ctx* c) noexcept nogil:
    return <uint32_t>0xFFFFFFFF >> (32 - c.S)


cdef inline void _sources_cost(const Ctx* c, const Patches* pp, uint32_t sources, int row, int col, float depth,
                               const float* n, const float* ray, float* costs, Work* windows) noexcept nogil:
    """The hypothesis (depth, n)'s cost against every source of ``sources`` into ``costs[j]``
    (the others' left as they are)."""
    _group_costs(c, pp, sources, 1, &depth, n, row, col, ray, costs, windows)


cdef inline void _group_costs(const Ctx* c, const Patches* pp, uint32_t sources, int count, const float* depth,
                              const float* normal, int row, int col, const float* ray, float* costs,
                              Work* windows) noexcept nogil:
    """``_sources_cost`` of hypotheses 0..``count`` - 1 (``depth[h]``, ``normal[3 h:3 h + 3]``)
    into ``costs[h * MAX_SOURCES + j]``: their windows matched together, lanes filled across
    hypotheses and sources (``_score_group``)."""
    cdef int h, j
    windows.hypotheses += count
    if dvpmvs_simd_level != DVPMVS_SIMD_SCALAR and c.batch_indices:
        _score_group(c, pp, sources, count, depth, normal, NULL, row, col, ray, NULL, 0, 0, costs, windows)
        return
    for h in range(count):
        for j in range(c.S):
            if (sources >> j) & 1:
                _scored_view(c, pp, j, row, col, depth[h], &normal[3 * h], ray, NULL, &costs[h * MAX_SOURCES + j],
                             windows)


cdef inline uint32_t _group_scored(const Ctx* c, const Patches* pp, const float* w, float den, const float* prior,
                                   float best, int count, const float* depth, const float* normal, int row, int col,
                                   const float* ray, float* costs, Work* windows) noexcept nogil:
    """Hypotheses 0..``count`` - 1 (``depth[h]``, ``normal[3 h:3 h + 3]``, planar-prior term
    ``prior[h]``) against the selected sources (w > 0) into ``costs[h * MAX_SOURCES + j]``
    (MAX_COST for the others). Returns the mask of those scored in full (bit h); hypothesis h is
    given up as soon as its aggregated cost plus ``prior[h]`` is known to reach ``best`` (it cannot
    win: only a lower cost replaces the best), which the caller's comparisons of the others in
    their order do not change. ``den``: ``_weight_sum(w)``."""
    cdef Bound bound
    cdef int h, j
    cdef uint32_t selected = 0, scored = 0
    cdef float* hc
    windows.hypotheses += count
    for j in range(c.S):
        if w[j] > 0:
            selected = selected | (<uint32_t>1 << j)
    for h in range(count):
        for j in range(c.S):
            if not w[j] > 0:
                costs[h * MAX_SOURCES + j] = MAX_COST
    if dvpmvs_simd_level != DVPMVS_SIMD_SCALAR and c.batch_indices:
        return _score_group(c, pp, selected, count, depth, normal, prior, row, col, ray,
                            w if c.p.early_stop else NULL, den, best, costs, windows)
    for h in range(count):
        hc = &costs[h * MAX_SOURCES]
        bound.num = 0
        bound.den = den
        bound.prior = prior[h]
        bound.best = best
        for j in range(c.S):
            if w[j] > 0:
                bound.weight = w[j]
                if not _scored_view(c, pp, j, row, col, depth[h], &normal[3 * h], ray,
                                    &bound if c.p.early_stop else NULL, &hc[j], windows):
                    break
                bound.num = bound.num + w[j] * hc[j]
        else:
            scored = scored | (<uint32_t>1 << h)
    return scored


cdef struct Scoring:
    # One hypothesis against a set of sources while its windows are matched in batches.
    float H[MAX_SOURCES * 9]  # per source, the hypothesis's homography
    float geom[MAX_SOURCES]  # the geometric term (0 in the photometric pass)
    float centre[MAX_SOURCES]  # the centre window's cost
    float anchor[MAX_SOURCES * MAX_ANCHORS]  # the anchor windows' costs ...
    uint8_t matched[MAX_SOURCES * MAX_ANCHORS]  # ... where matched
    int next_anchor[MAX_SOURCES]  # the anchors before it that source j sees are summed in ...
    float anchor_sum[MAX_SOURCES]  # ... in order
    float cost[MAX_SOURCES]  # the source's cost, or a lower bound of it (``_bound_source``)
    uint32_t warped  # the sources the pixel lands in
    uint32_t deformed  # the sources whose cost takes anchor windows


cdef inline void _bound_source(const Ctx* c, const Patches* pp, Scoring* sc, int j) noexcept nogil:
    """Source j's cost from its centre window and the anchors matched so far: exact once they
    all are (as ``_scored_view`` computes it: their costs summed in order), a lower bound
    before: the anchors' costs are summed up to the first one not matched yet (every cost is
    >= 0, and float sums and products of such terms grow with each of them)."""
    cdef int a = sc.next_anchor[j]
    cdef uint32_t bit = <uint32_t>1 << j
    while a < pp.num_anchors and (not (pp.anchor_sources[a] & bit) or sc.matched[j * MAX_ANCHORS + a]):
        if pp.anchor_sources[a] & bit:
            sc.anchor_sum[j] = sc.anchor_sum[j] + sc.anchor[j * MAX_ANCHORS + a]
        a += 1
    sc.next_anchor[j] = a
    sc.cost[j] = _deformed(pp, sc.centre[j], sc.anchor_sum[j], pp.anchors_seen[j]) + sc.geom[j]


cdef inline bint _cannot_win(const Ctx* c, const Scoring* sc, uint32_t sources, const float* w, float den,
                             float prior, float best) noexcept nogil:
    """True when the hypothesis's aggregated cost, summed as ``_aggregate`` sums it (sources in
    order) from each source's cost or lower bound (``sc.cost``), already reaches ``best``:
    exact, as ``_beaten`` is."""
    cdef float num = 0
    cdef int j
    for j in range(c.S):
        if (sources >> j) & 1:
            num = num + w[j] * sc.cost[j]
    return num / den + prior >= best


cdef inline void _match_batch(const Ctx* c, const Patches* pp, dvpmvs_batch* batch, const int* lane_hypothesis,
                              const int* lane_source, Scoring* sc, bint anchors) noexcept nogil:
    """The costs of a batch's (hypothesis, window, source) lanes into ``sc[hypothesis]`` (the
    centre windows', or the anchors' with ``anchors``, whose sources' bounds are brought up to
    date); the batch is emptied."""
    cdef const dvpmvs_windows* table = &pp.anchor_table if anchors else &pp.centre_table
    cdef const RefPatch* patches = &pp.anchor[0] if anchors else &pp.centre
    cdef dvpmvs_sums sums
    cdef float ncc[8]
    cdef float cost
    cdef int l, j, a
    cdef Scoring* s
    cdef uint32_t behind
    if batch.count == 0:
        return
    behind = dvpmvs_batch_sums(c.src, c.SW, table, batch, sums.sws, sums.swss, sums.swrs)
    sums.count = batch.count
    for l in range(batch.count):
        a = batch.slot[l]
        sums.sum_w[l] = patches[a].sum_w
        sums.mean[l] = patches[a].mean
        sums.var[l] = patches[a].var
    # The vector NCC computes all 8 lanes: the spare ones repeat lane 0, which the stack's
    # leftovers would otherwise fill with whatever they held (subnormal floats among them, whose
    # divisions take a microcode assist of about a hundred cycles each).
    for l in range(batch.count, DVPMVS_BATCH):
        sums.sum_w[l] = sums.sum_w[0]
        sums.mean[l] = sums.mean[0]
        sums.var[l] = sums.var[0]
        sums.sws[l] = sums.sws[0]
        sums.swss[l] = sums.swss[0]
        sums.swrs[l] = sums.swrs[0]
    dvpmvs_ncc(&sums, ncc)  # _ncc_from_sums of every lane
    for l in range(batch.count):
        s = &sc[lane_hypothesis[l]]
        j = lane_source[l]
        a = batch.slot[l]
        cost = MAX_COST if (behind >> l) & 1 else ncc[l]
        if anchors:
            s.anchor[j * MAX_ANCHORS + a] = cost
            s.matched[j * MAX_ANCHORS + a] = 1
        else:
            s.centre[j] = cost
    if anchors:
        for l in range(batch.count):
            if l == 0 or lane_source[l] != lane_source[l - 1] or lane_hypothesis[l] != lane_hypothesis[l - 1]:
                _bound_source(c, pp, &sc[lane_hypothesis[l]], lane_source[l])
    batch.count = 0


cdef inline void _add_lane(const Ctx* c, dvpmvs_batch* batch, int* lane_hypothesis, int* lane_source, int h, int j,
                           int slot, const float* H) noexcept nogil:
    cdef int l = batch.count, k
    batch.slot[l] = slot
    batch.offset[l] = <int32_t>(j * c.SH * c.SW)
    batch.width[l] = c.src_size[2 * j]
    batch.height[l] = c.src_size[2 * j + 1]
    for k in range(9):
        batch.H[k][l] = H[k]
    lane_hypothesis[l] = h
    lane_source[l] = j
    batch.count = l + 1


cdef inline uint32_t _given_up(const Ctx* c, const Scoring* sc, const int* lane_hypothesis, int lanes, uint32_t alive,
                               uint32_t sources, const float* w, float den, const float* prior,
                               float best) noexcept nogil:
    """The hypotheses among the first ``lanes`` lanes of a batch just matched that can no longer
    win (``_cannot_win``), as a mask."""
    cdef uint32_t given_up = 0, bit
    cdef int l, h
    for l in range(lanes):
        h = lane_hypothesis[l]
        bit = <uint32_t>1 << h
        if (alive & bit) and not (given_up & bit) and _cannot_win(c, &sc[h], sources, w, den, prior[h], best):
            given_up = given_up | bit
    return given_up


cdef inline uint32_t _score_group(const Ctx* c, const Patches* pp, uint32_t sources, int count, const float* depth,
                                  const float* normal, const float* prior, int row, int col, const float* ray,
                                  const float* w, float den, float best, float* costs,
                                  Work* windows) noexcept nogil:
    """``_scored_view``'s costs of hypotheses 0..``count`` - 1 (at most MAX_GROUP; ``depth[h]``,
    ``normal[3 h:3 h + 3]``) against every source of ``sources`` into ``costs[h * MAX_SOURCES +
    j]``, their windows matched in batches of (hypothesis, window, source) lanes filled across
    hypotheses and sources: the geometric terms and homographies first, then every hypothesis's
    centre windows, then the anchors' windows, hypothesis by hypothesis and source by source.
    With ``w`` (else NULL), hypothesis h is given up as soon as its aggregated cost plus
    ``prior[h]`` is known to reach ``best`` (``_cannot_win``, checked after each stage and after
    each batch it had lanes in); ``den``: ``_weight_sum(w)``. Returns the mask of the hypotheses
    scored in full; a lane of a hypothesis given up while it waited in a batch is matched and
    not used, so each hypothesis's costs are those it would have alone."""
    cdef Scoring sc[MAX_GROUP]
    cdef Scoring* s
    cdef dvpmvs_batch batch
    cdef int lane_hypothesis[8]
    cdef int lane_source[8]
    cdef uint32_t alive = 0, bit
    cdef int order[MAX_SOURCES]
    cdef int i, j, k, a, h, num_order = 0
    cdef float m[3]
    cdef bint plane
    batch.count = 0
    # 1. The geometric terms, and where the pixel lands in each source.
    for h in range(count):
        s = &sc[h]
        s.warped = 0
        s.deformed = 0
        plane = _plane_vector(c, depth[h], &normal[3 * h], ray, m)
        for j in range(c.S):
            if not (sources >> j) & 1:
                continue
            s.geom[j] = 0  # geom + 0 leaves a cost >= 0 unchanged
            if c.src_depth != NULL:
                s.geom[j] = c.p.geom_weight * _reprojection_error(c, j, col, row, depth[h], ray)
            if plane and _warp(c, j, row, col, m, &s.H[9 * j]) == 0:
                s.warped = s.warped | (<uint32_t>1 << j)
                s.cost[j] = s.geom[j]
            else:
                s.cost[j] = MAX_COST + s.geom[j]
        if w == NULL or not _cannot_win(c, s, sources, w, den, prior[h], best):
            alive = alive | (<uint32_t>1 << h)
    # 2. The centre windows.
    for h in range(count):
        if not (alive >> h) & 1:
            continue
        for j in range(c.S):
            if (sc[h].warped >> j) & 1:
                windows.windows += 1
                windows.samples += pp.centre.n
                _add_lane(c, &batch, lane_hypothesis, lane_source, h, j, 0, &sc[h].H[9 * j])
                if batch.count == DVPMVS_BATCH:
                    _match_batch(c, pp, &batch, lane_hypothesis, lane_source, sc, False)
    _match_batch(c, pp, &batch, lane_hypothesis, lane_source, sc, False)
    for h in range(count):
        if not (alive >> h) & 1:
            continue
        s = &sc[h]
        for j in range(c.S):
            if (s.warped >> j) & 1:
                if pp.num_anchors > 0 and pp.anchors_seen[j] > 0:
                    s.deformed = s.deformed | (<uint32_t>1 << j)
                    s.next_anchor[j] = 0
                    s.anchor_sum[j] = 0
                    for a in range(pp.num_anchors):
                        s.matched[j * MAX_ANCHORS + a] = 0
                    _bound_source(c, pp, s, j)
                else:
                    s.cost[j] = s.centre[j] + s.geom[j]
        if w != NULL and s.deformed != 0 and _cannot_win(c, s, sources, w, den, prior[h], best):
            alive = alive & ~(<uint32_t>1 << h)
    # 3. The anchors' windows, source by source: with a bound, the most weighted sources first,
    # whose costs raise the lower bound the most (it is summed in source order whatever the
    # order of the work), so that a hypothesis that cannot win is given up after fewer windows.
    if pp.num_anchors > 0:
        for j in range(c.S):
            if (sources >> j) & 1:
                order[num_order] = j
                num_order += 1
        if w != NULL:
            for i in range(1, num_order):  # insertion sort by weight, descending; ties in source order
                j = order[i]
                k = i - 1
                while k >= 0 and w[order[k]] < w[j]:
                    order[k + 1] = order[k]
                    k -= 1
                order[k + 1] = j
    for h in range(count):
        for i in range(num_order):
            j = order[i]
            bit = <uint32_t>1 << j
            if not (sc[h].deformed & bit):
                continue
            for a in range(pp.num_anchors):
                if not (alive >> h) & 1:
                    break
                if not (pp.anchor_sources[a] & bit):
                    continue
                windows.windows += 1
                windows.samples += pp.anchor[a].n
                _add_lane(c, &batch, lane_hypothesis, lane_source, h, j, a, &sc[h].H[9 * j])
                if batch.count == DVPMVS_BATCH:
                    _match_batch(c, pp, &batch, lane_hypothesis, lane_source, sc, True)
                    if w != NULL:
                        alive = alive & ~_given_up(c, sc, lane_hypothesis, DVPMVS_BATCH, alive, sources, w, den,
                                                   prior, best)
    _match_batch(c, pp, &batch, lane_hypothesis, lane_source, sc, True)
    for h in range(count):
        if not (alive >> h) & 1:
            continue
        s = &sc[h]
        for j in range(c.S):
            if (sources >> j) & 1:
                if (s.deformed >> j) & 1:
                    _bound_source(c, pp, s, j)  # the anchors matched one by one, after the last batch
                costs[h * MAX_SOURCES + j] = s.cost[j]
    return alive


cdef inline float _warp(const Ctx* c, int j, int row, int col, const float* m, float* H) noexcept nogil:
    """0 when the plane of ``m`` (``_plane_vector``) carries the pixel (row, col) inside source j's
    image through its homography (into ``H``); MAX_COST otherwise: the view cannot judge."""
    _homography(c, j, m, H)
    cdef float hz = H[6] * col + H[7] * row + H[8]
    if hz <= 1e-8:
        return MAX_COST
    cdef float hx = (H[0] * col + H[1] * row + H[2]) / hz
    cdef float hy = (H[3] * col + H[4] * row + H[5]) / hz
    if hx < 0 or hy < 0 or hx > c.src_size[2 * j] - 1 or hy > c.src_size[2 * j + 1] - 1:
        return MAX_COST
    return 0


cdef inline float _weight_sum(const Ctx* c, const float* w) noexcept nogil:
    cdef float den = 0
    cdef int j
    for j in range(c.S):
        if w[j] > 0:
            den = den + w[j]
    return den


cdef inline float _aggregate(const Ctx* c, const float* costs, const float* w) noexcept nogil:
    cdef float num = 0, den = _weight_sum(c, w)
    cdef int j
    for j in range(c.S):
        if w[j] > 0:
            num = num + w[j] * costs[j]
    return num / den if den > 0 else MAX_COST


cdef inline float _prior_term(const Ctx* c, Py_ssize_t pix, float d, const float* n) noexcept nogil:
    """Planar-prior penalty (ACMMP's idea, our form): prior_weight * (1 - exp(-relative depth
    difference^2 / (2 sd^2) - (1 - cos angle) / sa^2)); 0 where the pixel has no prior. A wrong
    prior loses where the photometric cost is decisive (texture), and decides where it is not."""
    if c.prior_depth == NULL:
        return 0
    cdef float dp = c.prior_depth[pix]
    if not dp > 0:
        return 0
    cdef const float* np_ = c.prior_normal + 3 * pix
    cdef float rel = (d - dp) / dp
    cdef float one_minus_cos = 1.0 - (n[0] * np_[0] + n[1] * np_[1] + n[2] * np_[2])
    return c.p.prior_weight * (1.0 - exp(-rel * rel * c.p.prior_inv_two_sigma_depth_sq
                                         - one_minus_cos * c.p.prior_inv_sigma_angle_sq))
