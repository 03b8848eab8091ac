# The matching cost of a plane hypothesis (paper eq. 3): the bilateral-weighted NCC of a window
# warped into a source by the plane's homography, the deformed cost of a weak pixel (its sparser
# centre window and its anchors' windows), the geometric term of the geometric pass, the
# planar-prior term, and the view-selection-weighted aggregate over the sources, with the exact
# early stop of hypotheses that cannot win. Inline functions cimported by the kernels.

from libc.math cimport exp, sqrt, fabs
from libc.stdint cimport uint32_t

from dvpmvs._sampling cimport bilinear_clamped
from dvpmvs.patchmatch._context cimport (Ctx, Window, MAX_ANCHORS, MAX_COST, MAX_SAMPLES, MAX_SOURCES,
                                         _homography)
from dvpmvs.patchmatch._visibility cimport _reprojection_error

cdef extern from "_window_cost_simd.h":
    # Several windows' weighted sums at once, one window per lane (see the header).
    ctypedef struct dvpmvs_lanes:
        int n
        float x[256][8]
        float y[256][8]
        float w[256][8]
        float v[256][8]
    int DVPMVS_LANES
    int DVPMVS_SIMD_SCALAR
    int DVPMVS_SIMD_AVX2
    int DVPMVS_SIMD_AVX512
    int dvpmvs_simd_select(int requested) nogil
    void dvpmvs_window_sums(const float* img, int stride, const float* H, const dvpmvs_lanes* lanes, uint32_t active,
                            float* sws, float* swss, float* swrs) nogil


cdef struct RefPatch:
    int n
    float x[MAX_SAMPLES]
    float y[MAX_SAMPLES]
    float w[MAX_SAMPLES]
    float v[MAX_SAMPLES]
    float sum_w
    float mean
    float var
    float x_min
    float x_max
    float y_min
    float y_max


cdef inline void _ref_patch(const Ctx* c, int row, int col, RefPatch* p) noexcept nogil:
    """Bilateral weights and values of the reference window around (row, col); samples outside
    the image are left out. Weights: spatial Gaussian x colour Gaussian of the difference to the
    centre pixel."""
    _window_patch(c, row, col, p, &c.p.plain)


cdef inline void _window_patch(const Ctx* c, int row, int col, RefPatch* p, const Window* window) noexcept nogil:
    """The samples of ``window`` around (row, col) (see ``_ref_patch``)."""
    cdef float centre = c.ref[row * c.W + col]
    cdef int k, x, y
    cdef float v, d, sw = 0, swv = 0, swvv = 0
    p.n = 0
    for k in range(window.n):
        x = col + window.off_x[k]
        y = row + window.off_y[k]
        if x < 0 or y < 0 or x >= c.W or y >= c.H:
            continue
        v = c.ref[y * c.W + x]
        d = v - centre
        p.x[p.n] = x
        p.y[p.n] = y
        p.v[p.n] = v
        p.w[p.n] = window.spatial[k] * exp(-d * d * c.p.inv_two_sigma_color_sq)
        sw = sw + p.w[p.n]
        swv = swv + p.w[p.n] * v
        swvv = swvv + p.w[p.n] * v * v
        p.n += 1
    p.sum_w = sw
    if p.n > 0:
        p.x_min = p.x[0]
        p.y_min = p.y[0]
        p.x_max = p.x[p.n - 1]
        p.y_max = p.y[p.n - 1]
    if sw > 0:
        p.mean = swv / sw
        p.var = swvv / sw - p.mean * p.mean
    else:
        p.mean = 0
        p.var = 0


cdef inline float _ncc_cost(const Ctx* c, const RefPatch* p, int j, const float* H) noexcept nogil:
    """1 - bilateral-weighted NCC between the reference patch and its warp into source j."""
    cdef const float* img = c.src + <Py_ssize_t>j * c.SH * c.SW
    cdef int width = c.src_size[2 * j]
    cdef int height = c.src_size[2 * j + 1]
    cdef int stride = c.SW
    cdef int k
    cdef float hx, hy, hz, s, w, ax, top, bottom, sws = 0, swss = 0, swrs = 0
    cdef float one = 1.0  # a float, so that the loop stays in single precision
    cdef const float* row0
    cdef int xi[MAX_SAMPLES]
    cdef int yi[MAX_SAMPLES]
    cdef float fx[MAX_SAMPLES]
    cdef float fy[MAX_SAMPLES]
    if not _window_inside(c, p, H, width, height):
        return _ncc_cost_clamped(c, p, j, H)
    # Every sample and its 2x2 neighbourhood lie inside the source image. The warped coordinates
    # of all samples come first, in a loop free of memory lookups that the compiler vectorises;
    # the bilinear lookups follow.
    for k in range(p.n):
        hz = one / (H[6] * p.x[k] + H[7] * p.y[k] + H[8])
        hx = (H[0] * p.x[k] + H[1] * p.y[k] + H[2]) * hz
        hy = (H[3] * p.x[k] + H[4] * p.y[k] + H[5]) * hz
        xi[k] = <int>hx
        yi[k] = <int>hy
        fx[k] = hx - <float>xi[k]
        fy[k] = hy - <float>yi[k]
    for k in range(p.n):
        row0 = img + yi[k] * stride + xi[k]
        ax = fx[k]
        top = row0[0] + ax * (row0[1] - row0[0])
        bottom = row0[stride] + ax * (row0[stride + 1] - row0[stride])
        s = top + fy[k] * (bottom - top)
        w = p.w[k]
        sws = sws + w * s
        swss = swss + w * s * s
        swrs = swrs + w * s * p.v[k]
    return _ncc_from_sums(p, sws, swss, swrs)


cdef inline float _ncc_cost_clamped(const Ctx* c, const RefPatch* p, int j, const float* H) noexcept nogil:
    """``_ncc_cost`` of a window whose warp leaves the source image: samples clamped to its
    border; MAX_COST when a sample falls behind the source camera."""
    cdef const float* img = c.src + <Py_ssize_t>j * c.SH * c.SW
    cdef int width = c.src_size[2 * j]
    cdef int height = c.src_size[2 * j + 1]
    cdef int k
    cdef float hx, hy, hz, s, w, sws = 0, swss = 0, swrs = 0
    for k in range(p.n):
        hz = H[6] * p.x[k] + H[7] * p.y[k] + H[8]
        if hz <= 1e-8:
            return MAX_COST
        hx = (H[0] * p.x[k] + H[1] * p.y[k] + H[2]) / hz
        hy = (H[3] * p.x[k] + H[4] * p.y[k] + H[5]) / hz
        s = bilinear_clamped(img, c.SW, width, height, hx, hy)
        w = p.w[k]
        sws = sws + w * s
        swss = swss + w * s * s
        swrs = swrs + w * s * p.v[k]
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


cdef inline void _ncc_costs_in_lanes(const Ctx* c, const RefPatch* patches, const dvpmvs_lanes* lanes, int num,
                                     uint32_t wanted, int j, const float* H, float* out) noexcept nogil:
    """``out[a] = _ncc_cost(c, &patches[a], j, H)`` for the windows a < ``num`` whose bit is set
    in ``wanted``, ``lanes`` holding their samples (``_fill_lanes``): the windows inside the
    source image at once, one per vector lane, the others one by one."""
    cdef const float* img = c.src + <Py_ssize_t>j * c.SH * c.SW
    cdef int width = c.src_size[2 * j]
    cdef int height = c.src_size[2 * j + 1]
    cdef uint32_t inside = 0
    cdef float sws[8]
    cdef float swss[8]
    cdef float swrs[8]
    cdef int a
    for a in range(num):
        if (wanted >> a) & 1:
            if _window_inside(c, &patches[a], H, width, height):
                inside = inside | (<uint32_t>1 << a)
            else:
                out[a] = _ncc_cost_clamped(c, &patches[a], j, H)
    if inside == 0:
        return
    dvpmvs_window_sums(img, c.SW, H, lanes, inside, sws, swss, swrs)
    for a in range(num):
        if (inside >> a) & 1:
            out[a] = _ncc_from_sums(&patches[a], sws[a], swss[a], swrs[a])


cdef inline void _fill_lanes(const RefPatch* patches, int num, dvpmvs_lanes* lanes) noexcept nogil:
    """The samples of windows 0..``num`` - 1 transposed into lanes (see the header); a shorter
    window repeats its last sample's position with weight and value 0."""
    cdef int a, k, last
    lanes.n = 0
    for a in range(num):
        if patches[a].n > lanes.n:
            lanes.n = patches[a].n
    for a in range(num):
        for k in range(lanes.n):
            last = k if k < patches[a].n else patches[a].n - 1
            lanes.x[k][a] = patches[a].x[last]
            lanes.y[k][a] = patches[a].y[last]
            lanes.w[k][a] = patches[a].w[k] if k < patches[a].n else 0
            lanes.v[k][a] = patches[a].v[k] if k < patches[a].n else 0
    for a in range(num, 8):
        for k in range(lanes.n):
            lanes.x[k][a] = 0
            lanes.y[k][a] = 0
            lanes.w[k][a] = 0
            lanes.v[k][a] = 0


cdef inline bint _window_inside(const Ctx* c, const RefPatch* p, const float* H, int width, int height) noexcept nogil:
    """True when the warp of the window's bounding box stays in front of the source camera and
    strictly inside its image: the warp of a convex region lies in the hull of its corners."""
    cdef float xs[2]
    cdef float ys[2]
    cdef float hx, hy, hz
    cdef int a, b
    xs[0] = p.x_min
    xs[1] = p.x_max
    ys[0] = p.y_min
    ys[1] = p.y_max
    for a in range(2):
        for b in range(2):
            hz = H[6] * xs[a] + H[7] * ys[b] + H[8]
            if hz <= 1e-8:
                return False
            hx = (H[0] * xs[a] + H[1] * ys[b] + H[2]) / hz
            hy = (H[3] * xs[a] + H[4] * ys[b] + H[5]) / hz
            if not (hx >= 0 and hy >= 0 and hx < width - 1 and hy < height - 1):
                return False
    return True


cdef inline float _view_cost(const Ctx* c, const RefPatch* p, int j, int row, int col, float depth,
                             const float* n, const float* ray) noexcept nogil:
    """Cost of hypothesis (depth, n) at (row, col) against source j: 1 - NCC, plus in the
    geometric pass geom_weight * min(reprojection error, geom_max_error)."""
    cdef float H[9]
    cdef float cost = _warp(c, j, row, col, depth, n, ray, H)
    if cost == 0:
        cost = _ncc_cost(c, p, j, H)
    if c.src_depth != NULL:
        cost = cost + c.p.geom_weight * _reprojection_error(c, j, col, row, depth, ray)
    return cost


cdef struct Patches:
    # A pixel's matching support: its own window, and for a weak pixel with anchors (deformable
    # PatchMatch) a sparser centre window plus one window around each anchor.
    RefPatch centre
    int num_anchors
    RefPatch anchor[MAX_ANCHORS]
    RefPatch select_anchor[MAX_ANCHORS]  # the same anchors' view-selection windows (c.p.select)
    dvpmvs_lanes anchor_lanes  # ``anchor``'s samples, one anchor per lane
    dvpmvs_lanes select_lanes  # ``select_anchor``'s
    uint32_t anchor_sources[MAX_ANCHORS]  # the sources each anchor is visible in (bit j: source j)
    int anchors_seen[MAX_SOURCES]  # per source, how many of the anchors it sees (once per pixel)


cdef inline void _patches(const Ctx* c, int row, int col, Patches* pp) noexcept nogil:
    cdef Py_ssize_t pix = <Py_ssize_t>row * c.W + col
    cdef int a, j, q, count = 0
    pp.num_anchors = 0
    if c.anchors != NULL:
        for a in range(MAX_ANCHORS):
            if c.anchors[pix * MAX_ANCHORS + a] >= 0:
                count += 1
    if count < c.p.min_anchors or count == 0:
        _ref_patch(c, row, col, &pp.centre)
        return
    _window_patch(c, row, col, &pp.centre, &c.p.coarse)
    for a in range(MAX_ANCHORS):
        q = c.anchors[pix * MAX_ANCHORS + a]
        if q < 0:
            continue
        _window_patch(c, q // c.W, q % c.W, &pp.anchor[pp.num_anchors], &c.p.anchor)
        pp.anchor_sources[pp.num_anchors] = c.anchor_visible[q] if c.anchor_visible != NULL else <uint32_t>0xFFFFFFFF
        if pp.anchor[pp.num_anchors].sum_w > 0:
            if c.p.select.n > 0:
                _window_patch(c, q // c.W, q % c.W, &pp.select_anchor[pp.num_anchors], &c.p.select)
                if not pp.select_anchor[pp.num_anchors].sum_w > 0:
                    # No sample of the sparser window in the image (a step that skips the
                    # anchor itself, at the border): the full window stands in.
                    pp.select_anchor[pp.num_anchors] = pp.anchor[pp.num_anchors]
            pp.num_anchors += 1
    for j in range(c.S):
        pp.anchors_seen[j] = 0
        for a in range(pp.num_anchors):
            if (pp.anchor_sources[a] >> j) & 1:
                pp.anchors_seen[j] += 1
    _fill_lanes(pp.anchor, pp.num_anchors, &pp.anchor_lanes)
    if c.p.select.n > 0:
        _fill_lanes(pp.select_anchor, pp.num_anchors, &pp.select_lanes)


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


cdef inline bint _scored_view(const Ctx* c, const Patches* pp, const RefPatch* anchor_patch,
                              const dvpmvs_lanes* anchor_lanes, int j, int row, int col, float depth, const float* n,
                              const float* ray, const Bound* bound, float* cost, int* windows) noexcept nogil:
    """The pixel's cost against source j into ``cost``: plain (``_view_cost``), or for a deformed
    pixel lambda * m(p, B_p) + (1 - lambda) * mean over anchors m(s, B_s) (paper eq. 3), the
    anchors' windows B_s from ``anchor_patch`` (``pp.anchor``, or ``pp.select_anchor``, with
    their samples in ``anchor_lanes``); every window is warped by the homography of the pixel's
    own plane. With anchor visibility
    (``c.anchor_visible``), the mean runs over the anchors visible in source j (paper eq. 10-11),
    and the centre window alone judges a source that sees none of them. ``windows`` counts the
    evaluations (hypothesis x source x window: 1 + the anchors used per source, whether or not the
    window lands in the image; for a stopped source, the windows matched). With a ``bound``
    (else NULL), stops as soon as the hypothesis cannot win (``_beaten``) and returns False;
    the geometric term is computed first, then the centre window, then the anchors' windows
    together (``_ncc_costs_in_lanes``), so that an early stop skips most of the work."""
    cdef float H[9]
    cdef float costs[MAX_ANCHORS]
    cdef float photo, anchors = 0, centre, geom = 0  # geom + 0 leaves a cost >= 0 unchanged
    cdef int a
    cdef uint32_t seen = 0
    cdef int visible = pp.anchors_seen[j] if pp.num_anchors > 0 else 0  # the anchors source j sees
    cdef uint32_t bit = <uint32_t>1 << j
    if c.src_depth != NULL:
        geom = c.p.geom_weight * _reprojection_error(c, j, col, row, depth, ray)
    if bound != NULL and _beaten(bound, geom):
        return False
    photo = _warp(c, j, row, col, depth, n, ray, H)
    if photo == 0:
        if visible == 0:
            photo = _ncc_cost(c, &pp.centre, j, H)
        else:
            centre = _ncc_cost(c, &pp.centre, j, H)
            if bound != NULL and _beaten(bound, _deformed(c, centre, anchors, visible) + geom):
                windows[0] += 1
                return False
            for a in range(pp.num_anchors):
                if pp.anchor_sources[a] & bit:
                    seen = seen | (<uint32_t>1 << a)
            _ncc_costs_in_lanes(c, anchor_patch, anchor_lanes, pp.num_anchors, seen, j, H, costs)
            for a in range(pp.num_anchors):
                if (seen >> a) & 1:
                    anchors = anchors + costs[a]
            photo = _deformed(c, centre, anchors, visible)
    cost[0] = photo + geom
    windows[0] += 1 + visible
    return True


cdef inline float _deformed(const Ctx* c, float centre, float anchors, int num_anchors) noexcept nogil:
    """Paper eq. 3 from the centre window's cost and the sum of the anchor windows' costs."""
    return c.p.deform_lambda * centre + (1.0 - c.p.deform_lambda) * anchors / num_anchors


cdef inline float _patches_cost(const Ctx* c, const Patches* pp, int j, int row, int col, float depth,
                                const float* n, const float* ray, int* windows) noexcept nogil:
    """``_scored_view`` without a bound: the cost itself."""
    cdef float cost
    _scored_view(c, pp, pp.anchor, &pp.anchor_lanes, j, row, col, depth, n, ray, NULL, &cost, windows)
    return cost


cdef inline float _selection_cost(const Ctx* c, const Patches* pp, int j, int row, int col, float depth,
                                  const float* n, const float* ray, int* windows) noexcept nogil:
    """``_patches_cost`` with view selection's sparser anchor windows (``pp.select_anchor``)."""
    cdef float cost
    _scored_view(c, pp, pp.select_anchor, &pp.select_lanes, j, row, col, depth, n, ray, NULL, &cost, windows)
    return cost


cdef inline bint _scored(const Ctx* c, const Patches* pp, const float* w, float den, float prior, float best,
                         int row, int col, float depth, const float* n, const float* ray, float* costs,
                         int* windows) noexcept nogil:
    """Hypothesis (depth, n) against the selected sources (w > 0) into ``costs`` (MAX_COST for
    the others), or False as soon as its aggregated cost plus ``prior`` is known to reach
    ``best`` (it cannot win: only a lower cost replaces the best). ``den``: ``_weight_sum(w)``."""
    cdef Bound bound
    cdef int j
    bound.num = 0
    bound.den = den
    bound.prior = prior
    bound.best = best
    for j in range(c.S):
        if w[j] > 0:
            bound.weight = w[j]
            if not _scored_view(c, pp, pp.anchor, &pp.anchor_lanes, j, row, col, depth, n, ray,
                                &bound if c.p.early_stop else NULL, &costs[j], windows):
                return False
            bound.num = bound.num + w[j] * costs[j]
        else:
            costs[j] = MAX_COST
    return True


cdef inline float _warp(const Ctx* c, int j, int row, int col, float depth, const float* n, const float* ray,
                       float* H) noexcept nogil:
    """0 when the plane (depth, n) at (row, col) has a homography into source j (into ``H``)
    that carries the pixel inside the source image; MAX_COST otherwise: the view cannot judge."""
    if not (depth > 0) or not _homography(c, j, depth, n, ray, H):
        return MAX_COST
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
