# cython: language_level=3
"""Private PatchMatch kernels (ACMH/ACMM family); use :mod:`dvpmvs.patchmatch` instead.

State of one reference view at one scale, all C-contiguous float32 unless noted:
``depth`` (H, W), ``normal`` (H, W, 3) unit camera-frame normals facing the camera,
``cost`` (H, W) the view-selection-weighted matching cost, ``view_cost`` (H, W, S) the cost of
the pixel's hypothesis against every source, ``weights`` (H, W, S) the last view-selection
weights, ``selected`` (H, W) uint32 bit j set when source j was selected.

Sources are padded into one (S, HS, WS) stack with their true sizes in ``src_size`` (S, 2)
int32 ``(width, height)``. ``A`` (S, 9) = K_j R_j K^-1 and ``b`` (S, 3) = K_j t_j give the
plane-induced homography H = A + b m^T with m = K^-T n / (n . X) for the plane through the
camera-frame point X with normal n (R_j, t_j: reference camera -> source camera).

Pixel convention: array index [row, col] is the image point (col, row) (COLMAP's dense stage).

Determinism: one call updates the pixels of one checkerboard colour; a pixel reads only its own
state and that of the other colour, and random numbers come from a counter-based hash of
(seed, pixel, iteration, draw), so the result does not depend on the number of threads.
"""

from cython.parallel cimport prange
from libc.math cimport exp, sqrt, fabs, floor, cos, sin, acos, M_PI, INFINITY
from libc.stdint cimport uint64_t, uint32_t, int32_t, uint8_t

from dvpmvs._sampling cimport bilinear_clamped

from dvpmvs._digest cimport DVPMVS_SOURCE_DIGEST

# Checked against this file on import (dvpmvs._kernel_sources.require_current).
SOURCE_DIGEST = (<bytes>DVPMVS_SOURCE_DIGEST).decode("ascii")

cdef enum:
    MAX_SOURCES = 32
    MAX_SAMPLES = 256
    NUM_CANDIDATES = 8  # adaptive checkerboard candidates (view selection looks at these)
    MAX_ANCHORS = 8  # deformable PatchMatch: one anchor per 45-degree sector
    MAX_CANDIDATES = 16  # checkerboard candidates + anchors
    NUM_REFINE = 5
    NEAR_DEPTH = 3  # rows of the V-shaped near regions
    FAR_SAMPLES = 11  # samples of the far strips (stride 2)

cdef float MAX_COST = 2.0  # 1 - NCC lies in [0, 2]


# -- random numbers -------------------------------------------------------------------------

cdef inline uint64_t _mix(uint64_t z) noexcept nogil:
    # splitmix64 finaliser: a bijective 64-bit hash.
    z = z + <uint64_t>0x9E3779B97F4A7C15
    z = (z ^ (z >> 30)) * <uint64_t>0xBF58476D1CE4E5B9
    z = (z ^ (z >> 27)) * <uint64_t>0x94D049BB133111EB
    return z ^ (z >> 31)


cdef inline float _uniform(uint64_t key, uint64_t counter) noexcept nogil:
    """Uniform in [0, 1) from (key, counter)."""
    return <float>(_mix(key ^ _mix(counter)) >> 40) * <float>(1.0 / 16777216.0)


cdef inline uint64_t _pixel_key(uint64_t seed, uint64_t pixel, uint64_t stage) noexcept nogil:
    return _mix(_mix(seed) ^ _mix(pixel * <uint64_t>0x100000001B3 + stage))


# -- small geometry -------------------------------------------------------------------------

cdef struct Ctx:
    const float* ref
    int W
    int H
    const float* src
    int S
    int SW
    int SH
    const int32_t* src_size
    const float* A
    const float* b
    const float* rel_R  # (S, 9) reference -> source rotation
    const float* rel_t  # (S, 3)
    const float* src_K  # (S, 9)
    const float* src_K_inv  # (S, 9)
    const float* src_depth  # (S, SH, SW) or NULL: the sources' depth maps (geometric pass)
    const float* prior_depth  # (H, W) or NULL: planar prior depth, 0 where there is none
    const float* prior_normal  # (H, W, 3)
    float prior_weight
    float prior_inv_two_sigma_depth_sq  # relative depth
    float prior_inv_sigma_angle_sq  # on 1 - cos(angle), ~ angle^2 / 2
    const int32_t* anchors  # (H, W, MAX_ANCHORS) pixel indices, -1 for none; NULL: no deformation
    const uint32_t* anchor_visible  # (H, W) source bit masks of where an anchor is visible; NULL: all
    const float* fit_depth  # (H, W) or NULL: a weak pixel's fitted plane (anchors' or region's), 0 where none
    const float* fit_normal  # (H, W, 3)
    int min_anchors  # a weak pixel with fewer anchors keeps the plain patch
    float deform_lambda  # weight of the centre patch in the deformed cost (eq. 3)
    int coarse_num_samples  # the centre patch of a deformed pixel: 11x11 sampled every 5 pixels
    int coarse_off_x[MAX_SAMPLES]
    int coarse_off_y[MAX_SAMPLES]
    float coarse_spatial[MAX_SAMPLES]
    int anchor_num_samples  # an anchor's window: 11x11 sampled every deform_anchor_step pixels
    int anchor_off_x[MAX_SAMPLES]
    int anchor_off_y[MAX_SAMPLES]
    float anchor_spatial[MAX_SAMPLES]
    # View selection's anchor windows (11x11 every deform_select_step pixels) for a deformed
    # pixel's checkerboard candidates; 0: the full ones. Then only the ``select_rescore`` best
    # candidates by that cost are scored with the full windows, on the selected sources.
    int select_num_samples
    int select_off_x[MAX_SAMPLES]
    int select_off_y[MAX_SAMPLES]
    float select_spatial[MAX_SAMPLES]
    int select_rescore
    float K[9]
    float K_inv[9]
    float* depth
    float* normal
    float* cost
    float* view_cost
    float* weights
    uint32_t* selected
    int num_samples
    int off_x[MAX_SAMPLES]
    int off_y[MAX_SAMPLES]
    float spatial[MAX_SAMPLES]
    float inv_two_sigma_color_sq
    float depth_min
    float depth_max
    float search_min
    float search_max
    float geom_weight
    float geom_max_error
    float good_cost
    float bad_cost
    float perturbation
    int num_view_draws
    bint early_stop  # give up hypotheses that cannot win (``_scored``); the maps are the same
    bint keep_view_costs  # rescore the unselected sources of a changed plane (another sweep reads them)
    float centre[3 * MAX_SOURCES]  # the sources' camera centres in the reference camera frame
    bint normal_aggregation  # paper section 3.5: normals must face every selected source
    bint depth_aggregation  # paper section 3.5: perturbed depths from epipolar intervals
    float aggregation_inner  # ... moving the point this many pixels along the epipolar lines (alpha) ...
    float aggregation_outer  # ... to this many (alpha + beta) ...
    int aggregation_views  # ... in this many of the selected sources (mu)
    uint64_t seed
    int iteration


cdef inline void _ray_from(const float* K_inv, float x, float y, float* ray) noexcept nogil:
    # K^-1 (x, y, 1): its z is 1, so depth * ray is the camera-frame point.
    ray[0] = K_inv[0] * x + K_inv[1] * y + K_inv[2]
    ray[1] = K_inv[3] * x + K_inv[4] * y + K_inv[5]
    ray[2] = 1.0


cdef inline void _ray(const Ctx* c, float x, float y, float* ray) noexcept nogil:
    _ray_from(c.K_inv, x, y, ray)


cdef inline void _random_normal(uint64_t key, uint64_t counter, const float* ray, float* n) noexcept nogil:
    """A uniformly random unit normal in the hemisphere facing the camera along ``ray``."""
    cdef float z = 2.0 * _uniform(key, counter) - 1.0
    cdef float phi = 2.0 * <float>M_PI * _uniform(key, counter + 1)
    cdef float s = sqrt(max(0.0, 1.0 - z * z))
    n[0] = s * cos(phi)
    n[1] = s * sin(phi)
    n[2] = z
    if n[0] * ray[0] + n[1] * ray[1] + n[2] * ray[2] > 0:
        n[0] = -n[0]
        n[1] = -n[1]
        n[2] = -n[2]


cdef inline void _normalise(float* n) noexcept nogil:
    cdef float norm = sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    if norm > 1e-12:
        n[0] /= norm
        n[1] /= norm
        n[2] /= norm


cdef inline float _plane_depth(const float* n, float depth_q, const float* ray_q, const float* ray_p) noexcept nogil:
    """Depth along ``ray_p`` of the plane through depth_q * ray_q with normal n (<= 0: none)."""
    cdef float denom = n[0] * ray_p[0] + n[1] * ray_p[1] + n[2] * ray_p[2]
    if fabs(denom) < 1e-6:
        return -1.0
    return depth_q * (n[0] * ray_q[0] + n[1] * ray_q[1] + n[2] * ray_q[2]) / denom


# -- reference patch ------------------------------------------------------------------------

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
    _window_patch(c, row, col, p, c.off_x, c.off_y, c.spatial, c.num_samples)


cdef void _window_patch(const Ctx* c, int row, int col, RefPatch* p, const int* off_x, const int* off_y,
                        const float* spatial, int num_samples) noexcept nogil:
    cdef float centre = c.ref[row * c.W + col]
    cdef int k, x, y
    cdef float v, d, sw = 0, swv = 0, swvv = 0
    p.n = 0
    for k in range(num_samples):
        x = col + off_x[k]
        y = row + off_y[k]
        if x < 0 or y < 0 or x >= c.W or y >= c.H:
            continue
        v = c.ref[y * c.W + x]
        d = v - centre
        p.x[p.n] = x
        p.y[p.n] = y
        p.v[p.n] = v
        p.w[p.n] = spatial[k] * exp(-d * d * c.inv_two_sigma_color_sq)
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


# -- matching cost --------------------------------------------------------------------------

cdef inline float _ncc_cost(const Ctx* c, const RefPatch* p, int j, const float* H) noexcept nogil:
    """1 - bilateral-weighted NCC between the reference patch and its warp into source j."""
    cdef const float* img = c.src + <Py_ssize_t>j * c.SH * c.SW
    cdef int width = c.src_size[2 * j]
    cdef int height = c.src_size[2 * j + 1]
    cdef int stride = c.SW
    cdef int k
    cdef float hx, hy, hz, s, w, ax, top, bottom, sws = 0, swss = 0, swrs = 0
    cdef float mean_s, var_s, cov, denom
    cdef float one = 1.0  # a float, so that the loop stays in single precision
    cdef const float* row0
    cdef int xi[MAX_SAMPLES]
    cdef int yi[MAX_SAMPLES]
    cdef float fx[MAX_SAMPLES]
    cdef float fy[MAX_SAMPLES]
    if _window_inside(c, p, H, width, height):
        # Fast path: every sample and its 2x2 neighbourhood lie inside the source image. The
        # warped coordinates of all samples come first, in a loop free of memory lookups that
        # the compiler vectorises; the bilinear lookups follow.
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
    else:
        for k in range(p.n):
            hz = H[6] * p.x[k] + H[7] * p.y[k] + H[8]
            if hz <= 1e-8:
                return MAX_COST
            hx = (H[0] * p.x[k] + H[1] * p.y[k] + H[2]) / hz
            hy = (H[3] * p.x[k] + H[4] * p.y[k] + H[5]) / hz
            s = bilinear_clamped(img, stride, width, height, hx, hy)
            w = p.w[k]
            sws = sws + w * s
            swss = swss + w * s * s
            swrs = swrs + w * s * p.v[k]
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


cdef inline bint _homography(const Ctx* c, int j, float depth, const float* n, const float* ray, float* H) noexcept nogil:
    """H = A_j + b_j m^T, m = K^-T n / (n . X), X = depth * ray. False for a plane seen edge-on."""
    cdef float nx = depth * (n[0] * ray[0] + n[1] * ray[1] + n[2] * ray[2])
    if fabs(nx) < 1e-8:
        return False
    # m^T = n^T K^-1 / (n . X)
    cdef float m0 = (n[0] * c.K_inv[0] + n[1] * c.K_inv[3] + n[2] * c.K_inv[6]) / nx
    cdef float m1 = (n[0] * c.K_inv[1] + n[1] * c.K_inv[4] + n[2] * c.K_inv[7]) / nx
    cdef float m2 = (n[0] * c.K_inv[2] + n[1] * c.K_inv[5] + n[2] * c.K_inv[8]) / nx
    cdef const float* A = c.A + 9 * j
    cdef const float* b = c.b + 3 * j
    cdef int r
    for r in range(3):
        H[3 * r] = A[3 * r] + b[r] * m0
        H[3 * r + 1] = A[3 * r + 1] + b[r] * m1
        H[3 * r + 2] = A[3 * r + 2] + b[r] * m2
    return True


cdef inline bint _project(const Ctx* c, int j, float depth, const float* ray, float* u, float* v) noexcept nogil:
    """Source j's image point (u, v) of the reference point depth * ray; False behind source j."""
    cdef const float* R = c.rel_R + 9 * j
    cdef const float* t = c.rel_t + 3 * j
    cdef const float* Ks = c.src_K + 9 * j
    cdef float X0 = depth * ray[0], X1 = depth * ray[1], X2 = depth
    cdef float Y0 = R[0] * X0 + R[1] * X1 + R[2] * X2 + t[0]
    cdef float Y1 = R[3] * X0 + R[4] * X1 + R[5] * X2 + t[1]
    cdef float Y2 = R[6] * X0 + R[7] * X1 + R[8] * X2 + t[2]
    if Y2 <= 1e-8:
        return False
    u[0] = (Ks[0] * Y0 + Ks[1] * Y1 + Ks[2] * Y2) / Y2
    v[0] = (Ks[3] * Y0 + Ks[4] * Y1 + Ks[5] * Y2) / Y2
    return True


cdef inline bint _source_pixel(const Ctx* c, int j, float depth, const float* ray, int* ui, int* vi) noexcept nogil:
    """The pixel of source j nearest to where the point depth * ray projects; False when the
    point is behind the source or the pixel lies outside its image."""
    cdef float u, v
    if not _project(c, j, depth, ray, &u, &v):
        return False
    ui[0] = <int>floor(u + 0.5)
    vi[0] = <int>floor(v + 0.5)
    return 0 <= ui[0] < c.src_size[2 * j] and 0 <= vi[0] < c.src_size[2 * j + 1]


cdef inline float _reprojection_error(const Ctx* c, int j, float x, float y, float depth, const float* ray) noexcept nogil:
    """Forward-backward reprojection error (pixels) of the point depth * ray through source j's
    depth map; ``geom_max_error`` when the point leaves source j or meets no depth there."""
    cdef int ui, vi
    if not _source_pixel(c, j, depth, ray, &ui, &vi):
        return c.geom_max_error
    return _back_projection_error(c, j, ui, vi, c.src_depth[(<Py_ssize_t>j * c.SH + vi) * c.SW + ui], x, y)


cdef inline float _back_projection_error(const Ctx* c, int j, int ui, int vi, float ds, float x,
                                         float y) noexcept nogil:
    """How far (pixels, at most ``geom_max_error``) source j's pixel (ui, vi) at depth ds lands
    from the reference point (x, y)."""
    cdef const float* R = c.rel_R + 9 * j
    cdef const float* t = c.rel_t + 3 * j
    cdef const float* Ksi = c.src_K_inv + 9 * j
    if not ds > 0:
        return c.geom_max_error
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
        return c.geom_max_error
    cdef float px = (c.K[0] * W0 + c.K[1] * W1 + c.K[2] * W2) / W2 - x
    cdef float py = (c.K[3] * W0 + c.K[4] * W1 + c.K[5] * W2) / W2 - y
    cdef float err = sqrt(px * px + py * py)
    return err if err < c.geom_max_error else c.geom_max_error


cdef inline float _view_cost(const Ctx* c, const RefPatch* p, int j, int row, int col, float depth,
                             const float* n, const float* ray) noexcept nogil:
    """Cost of hypothesis (depth, n) at (row, col) against source j: 1 - NCC, plus in the
    geometric pass geom_weight * min(reprojection error, geom_max_error)."""
    cdef float H[9]
    cdef float cost = _warp(c, j, row, col, depth, n, ray, H)
    if cost == 0:
        cost = _ncc_cost(c, p, j, H)
    if c.src_depth != NULL:
        cost = cost + c.geom_weight * _reprojection_error(c, j, col, row, depth, ray)
    return cost


cdef struct Patches:
    # A pixel's matching support: its own window, and for a weak pixel with anchors (deformable
    # PatchMatch) a sparser centre window plus one window around each anchor.
    RefPatch centre
    int num_anchors
    RefPatch anchor[MAX_ANCHORS]
    RefPatch select_anchor[MAX_ANCHORS]  # the same anchors' view-selection windows (c.select_num_samples)
    uint32_t anchor_sources[MAX_ANCHORS]  # the sources each anchor is visible in (bit j: source j)
    int anchors_seen[MAX_SOURCES]  # per source, how many of the anchors it sees (once per pixel)


cdef void _patches(const Ctx* c, int row, int col, Patches* pp) noexcept nogil:
    cdef Py_ssize_t pix = <Py_ssize_t>row * c.W + col
    cdef int a, j, q, count = 0
    pp.num_anchors = 0
    if c.anchors != NULL:
        for a in range(MAX_ANCHORS):
            if c.anchors[pix * MAX_ANCHORS + a] >= 0:
                count += 1
    if count < c.min_anchors or count == 0:
        _ref_patch(c, row, col, &pp.centre)
        return
    _window_patch(c, row, col, &pp.centre, c.coarse_off_x, c.coarse_off_y, c.coarse_spatial,
                  c.coarse_num_samples)
    for a in range(MAX_ANCHORS):
        q = c.anchors[pix * MAX_ANCHORS + a]
        if q < 0:
            continue
        _window_patch(c, q // c.W, q % c.W, &pp.anchor[pp.num_anchors], c.anchor_off_x, c.anchor_off_y,
                      c.anchor_spatial, c.anchor_num_samples)
        pp.anchor_sources[pp.num_anchors] = c.anchor_visible[q] if c.anchor_visible != NULL else <uint32_t>0xFFFFFFFF
        if pp.anchor[pp.num_anchors].sum_w > 0:
            if c.select_num_samples > 0:
                _window_patch(c, q // c.W, q % c.W, &pp.select_anchor[pp.num_anchors], c.select_off_x,
                              c.select_off_y, c.select_spatial, c.select_num_samples)
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


cdef inline bint _scored_view(const Ctx* c, const Patches* pp, const RefPatch* anchor_patch, int j, int row,
                              int col, float depth, const float* n, const float* ray, const Bound* bound,
                              float* cost, int* windows) noexcept nogil:
    """The pixel's cost against source j into ``cost``: plain (``_view_cost``), or for a deformed
    pixel lambda * m(p, B_p) + (1 - lambda) * mean over anchors m(s, B_s) (paper eq. 3), the
    anchors' windows B_s from ``anchor_patch`` (``pp.anchor``, or ``pp.select_anchor``); every
    window is warped by the homography of the pixel's own plane. With anchor visibility
    (``c.anchor_visible``), the mean runs over the anchors visible in source j (paper eq. 10-11),
    and the centre window alone judges a source that sees none of them. ``windows`` counts the
    evaluations (hypothesis x source x window: 1 + the anchors used per source, whether or not the
    window lands in the image; for a stopped source, the windows matched). With a ``bound``
    (else NULL), stops as soon as the hypothesis cannot win (``_beaten``) and returns False;
    the geometric term is computed first, then the centre window, then the anchors, so that an
    early stop skips most of the work."""
    cdef float H[9]
    cdef float photo, anchors = 0, centre, geom = 0  # geom + 0 leaves a cost >= 0 unchanged
    cdef int a, used = 0
    cdef int visible = pp.anchors_seen[j] if pp.num_anchors > 0 else 0  # the anchors source j sees
    cdef uint32_t bit = <uint32_t>1 << j
    if c.src_depth != NULL:
        geom = c.geom_weight * _reprojection_error(c, j, col, row, depth, ray)
    if bound != NULL and _beaten(bound, geom):
        return False
    photo = _warp(c, j, row, col, depth, n, ray, H)
    if photo == 0:
        if visible == 0:
            photo = _ncc_cost(c, &pp.centre, j, H)
        else:
            centre = _ncc_cost(c, &pp.centre, j, H)
            for a in range(pp.num_anchors):
                if not (pp.anchor_sources[a] & bit):
                    continue
                if bound != NULL and _beaten(bound, _deformed(c, centre, anchors, visible) + geom):
                    windows[0] += 1 + used
                    return False
                anchors = anchors + _ncc_cost(c, &anchor_patch[a], j, H)
                used += 1
            photo = _deformed(c, centre, anchors, visible)
    cost[0] = photo + geom
    windows[0] += 1 + visible
    return True


cdef inline float _deformed(const Ctx* c, float centre, float anchors, int num_anchors) noexcept nogil:
    """Paper eq. 3 from the centre window's cost and the sum of the anchor windows' costs."""
    return c.deform_lambda * centre + (1.0 - c.deform_lambda) * anchors / num_anchors


cdef inline float _patches_cost(const Ctx* c, const Patches* pp, int j, int row, int col, float depth,
                                const float* n, const float* ray, int* windows) noexcept nogil:
    """``_scored_view`` without a bound: the cost itself."""
    cdef float cost
    _scored_view(c, pp, pp.anchor, j, row, col, depth, n, ray, NULL, &cost, windows)
    return cost


cdef inline float _selection_cost(const Ctx* c, const Patches* pp, int j, int row, int col, float depth,
                                  const float* n, const float* ray, int* windows) noexcept nogil:
    """``_patches_cost`` with view selection's sparser anchor windows (``pp.select_anchor``)."""
    cdef float cost
    _scored_view(c, pp, pp.select_anchor, j, row, col, depth, n, ray, NULL, &cost, windows)
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
            if not _scored_view(c, pp, pp.anchor, j, row, col, depth, n, ray, &bound if c.early_stop else NULL,
                                &costs[j], windows):
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


# -- initial costs --------------------------------------------------------------------------

cdef void _initial_pixel(const Ctx* c, int row, int col, int top_k, int randomise) noexcept nogil:
    cdef Py_ssize_t pix = <Py_ssize_t>row * c.W + col
    cdef Patches patch
    cdef float ray[3]
    cdef float* n = c.normal + 3 * pix
    cdef float* vc = c.view_cost + pix * c.S
    cdef float* w = c.weights + pix * c.S
    cdef uint64_t key
    cdef int j, k, chosen, count = 0
    cdef float lo
    cdef uint32_t mask = 0
    cdef int windows = 0
    _ray(c, col, row, ray)
    if randomise:
        key = _pixel_key(c.seed, pix, 0xFFFF)
        c.depth[pix] = c.depth_min + (c.depth_max - c.depth_min) * _uniform(key, 0)
        _random_normal(key, 1, ray, n)
    elif n[0] * ray[0] + n[1] * ray[1] + n[2] * ray[2] > 0:
        n[0] = -n[0]
        n[1] = -n[1]
        n[2] = -n[2]
    _patches(c, row, col, &patch)
    for j in range(c.S):
        vc[j] = _patches_cost(c, &patch, j, row, col, c.depth[pix], n, ray, &windows)
        w[j] = 0
    # Before any view selection: the mean over the top_k best sources.
    for k in range(min(top_k, c.S)):
        chosen = -1
        lo = 1e30
        for j in range(c.S):
            if w[j] == 0 and vc[j] < lo:
                lo = vc[j]
                chosen = j
        if chosen >= 0:
            w[chosen] = 1
            mask = mask | (<uint32_t>1 << chosen)
            count += 1
    c.cost[pix] = _aggregate(c, vc, w)
    for j in range(c.S):
        w[j] = w[j] / count if count > 0 else 0  # weights are shares, like the sampled ones
    c.selected[pix] = mask


# -- propagation, view selection, refinement ------------------------------------------------

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
    return c.prior_weight * (1.0 - exp(-rel * rel * c.prior_inv_two_sigma_depth_sq
                                       - one_minus_cos * c.prior_inv_sigma_angle_sq))


cdef inline void _consider(const Ctx* c, int row, int col, float* best_cost, int* best_pix) noexcept nogil:
    cdef Py_ssize_t q
    if row < 0 or col < 0 or row >= c.H or col >= c.W:
        return
    q = <Py_ssize_t>row * c.W + col
    if c.depth[q] > 0 and c.cost[q] < best_cost[0]:
        best_cost[0] = c.cost[q]
        best_pix[0] = <int>q


cdef void _candidates(const Ctx* c, int row, int col, int* cand) noexcept nogil:
    """Adaptive checkerboard sampling: in each of 4 V-shaped near regions and 4 far strips
    (up, down, left, right) the pixel of the other colour with the lowest cost; -1 if none."""
    cdef int d, s, k, e
    cdef float best
    cdef int dirs_r[4]
    cdef int dirs_c[4]
    dirs_r[0] = -1; dirs_c[0] = 0
    dirs_r[1] = 1; dirs_c[1] = 0
    dirs_r[2] = 0; dirs_c[2] = -1
    dirs_r[3] = 0; dirs_c[3] = 1
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


cdef inline bint _same_plane(float d, const float* n, float d2, const float* n2) noexcept nogil:
    """The same plane hypothesis: a normal copied unchanged, and a depth equal up to the rounding
    of carrying the plane from one pixel to another (1e-5 relative: 0.05 mm at 5 m)."""
    return (n[0] == n2[0] and n[1] == n2[1] and n[2] == n2[2]
            and fabs(d - d2) <= 1e-5 * d2)


cdef inline int _same_plane_as(const float* cand_depth, const float* cand_normal, const int* cand, int i,
                               float d, const float* n) noexcept nogil:
    """The first candidate before ``i`` with the same plane as (d, n), or -1."""
    cdef int k
    for k in range(i):
        if cand[k] >= 0 and _same_plane(d, n, cand_depth[k], &cand_normal[3 * k]):
            return k
    return -1


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


cdef bint _epipolar_intervals(const Ctx* c, uint32_t mask, float depth, int row, int col,
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
    steps[0] = -c.aggregation_outer
    steps[1] = -c.aggregation_inner
    steps[2] = c.aggregation_inner
    steps[3] = c.aggregation_outer
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
    mu = (c.aggregation_views if c.aggregation_views < count else count) - 1
    j = _kth_smallest(near_in, count, count - 1 - mu)  # the mu-th largest inner depth below ``depth``
    out[0] = near_out[j]
    out[1] = near_in[j]
    j = _kth_smallest(far_in, count, mu)  # the mu-th smallest inner depth above it
    out[2] = far_in[j]
    out[3] = far_out[j]
    return True


cdef void _pick_rescored(const Ctx* c, Py_ssize_t pix, const int* cand, const float* cand_depth,
                         const float* cand_normal, const float* costs, const uint8_t* sparse, const float* w,
                         uint32_t mask, const float* ray, uint8_t* rescore) noexcept nogil:
    """``rescore[i]`` = 1 for the ``c.select_rescore`` checkerboard candidates with the lowest
    aggregated cost (plus planar-prior term) by view selection's sparser windows (``sparse[i]``),
    the lower index first on ties; a plane that an earlier candidate also carries counts once,
    and one that normal aggregation rules out not at all."""
    cdef float rank[NUM_CANDIDATES]
    cdef int i, k, chosen
    cdef float lo
    for i in range(NUM_CANDIDATES):
        rescore[i] = 0
        rank[i] = INFINITY
        if cand[i] < 0 or not sparse[i]:
            continue
        if _same_plane_as(cand_depth, cand_normal, cand, i, cand_depth[i], &cand_normal[3 * i]) >= 0:
            continue
        if c.normal_aggregation and not _faces_sources(c, mask, cand_depth[i], &cand_normal[3 * i], ray):
            continue
        rank[i] = _aggregate(c, &costs[i * MAX_SOURCES], w) + _prior_term(c, pix, cand_depth[i], &cand_normal[3 * i])
    for k in range(c.select_rescore):
        chosen = -1
        lo = INFINITY
        for i in range(NUM_CANDIDATES):
            if not rescore[i] and rank[i] < lo:
                lo = rank[i]
                chosen = i
        if chosen < 0:
            return
        rescore[chosen] = 1


cdef int _update_pixel(const Ctx* c, int row, int col) noexcept nogil:
    """Returns the number of evaluations made (hypothesis x source x window)."""
    cdef Py_ssize_t pix = <Py_ssize_t>row * c.W + col
    cdef Patches patch
    cdef float ray[3]
    cdef float ray_q[3]
    cdef int cand[MAX_CANDIDATES]
    cdef float cand_depth[MAX_CANDIDATES]
    cdef float cand_normal[MAX_CANDIDATES * 3]
    cdef float costs[MAX_CANDIDATES * MAX_SOURCES]
    cdef float prior[MAX_SOURCES]
    cdef float prob[MAX_SOURCES]
    cdef float w[MAX_SOURCES]
    cdef float trial_costs[MAX_SOURCES]
    cdef float best_costs[MAX_SOURCES]
    cdef float hyp_n[3]
    cdef float best_n[3]
    cdef float intervals[4]
    cdef bint epipolar = False
    cdef bint sparse_selection
    cdef uint8_t sparse[NUM_CANDIDATES]  # the candidate's costs are view selection's sparser ones
    cdef uint8_t rescore[NUM_CANDIDATES]  # ... and it is among the best of them: scored in full
    cdef float* n = c.normal + 3 * pix
    cdef float* vc = c.view_cost + pix * c.S
    cdef int i, j, k, q, good, bad, num_valid = 0, best_i, qrow, qcol, num_cand = NUM_CANDIDATES
    cdef int nb_r[4]
    cdef int nb_c[4]
    cdef float value, sum_good, total, r, agg, best_agg, best_d, d, pert, photo, best_photo, den, prior_i
    cdef int same
    cdef uint32_t mask
    cdef uint64_t key = _pixel_key(c.seed, pix, <uint64_t>c.iteration + 1)
    cdef uint64_t counter = 0
    cdef int evals = 0  # hypothesis x source x window

    _ray(c, col, row, ray)
    _patches(c, row, col, &patch)
    if patch.centre.sum_w <= 0:
        return 0
    sparse_selection = c.select_num_samples > 0 and patch.num_anchors > 0

    # 1. Candidates from the other colour, their plane carried to this pixel; a deformed pixel
    # also tries its anchors' planes (they lie on its surface, by construction of the regions),
    # those of the other colour only: the same colour is being updated concurrently.
    _candidates(c, row, col, cand)
    if patch.num_anchors > 0:
        for k in range(MAX_ANCHORS):
            q = c.anchors[pix * MAX_ANCHORS + k]
            if q >= 0 and ((q // c.W) + (q % c.W)) % 2 != (row + col) % 2 and c.depth[q] > 0:
                cand[num_cand] = q
            else:
                cand[num_cand] = -1
            num_cand += 1
    for i in range(num_cand):
        if cand[i] < 0:
            continue
        q = cand[i]
        qrow = q // c.W
        qcol = q - qrow * c.W
        _ray(c, qcol, qrow, ray_q)
        d = _plane_depth(c.normal + 3 * q, c.depth[q], ray_q, ray)
        if not (d > 0 and d >= c.search_min and d <= c.search_max):
            d = c.depth[q]
        cand_depth[i] = d
        for k in range(3):
            cand_normal[3 * i + k] = c.normal[3 * q + k]
        # Anchors' planes do not vote in the view selection: they are scored after it, on the
        # selected sources only (the aggregate reads no other), which is the same result for a
        # fraction of the deformed windows.
        if i < NUM_CANDIDATES:
            # Where propagation has converged, neighbours carry the pixel's own plane or each
            # other's: their costs are known (the pixel's ``vc`` is its plane's, kept current).
            same = _same_plane_as(cand_depth, cand_normal, cand, i, d, &cand_normal[3 * i])
            sparse[i] = 0
            if same >= 0:
                for j in range(c.S):
                    costs[i * MAX_SOURCES + j] = costs[same * MAX_SOURCES + j]
                sparse[i] = sparse[same]
            elif _same_plane(d, &cand_normal[3 * i], c.depth[pix], n):
                for j in range(c.S):
                    costs[i * MAX_SOURCES + j] = vc[j]
            elif sparse_selection:
                # View selection needs every source's cost; the sparser anchor windows give it
                # for a fraction of the samples (``deform_select_step``).
                for j in range(c.S):
                    costs[i * MAX_SOURCES + j] = _selection_cost(c, &patch, j, row, col, d, &cand_normal[3 * i],
                                                                 ray, &evals)
                sparse[i] = 1
            else:
                for j in range(c.S):
                    costs[i * MAX_SOURCES + j] = _patches_cost(c, &patch, j, row, col, d, &cand_normal[3 * i], ray,
                                                               &evals)
        num_valid += 1
    if num_valid == 0:
        return 0

    # 2. Multi-hypothesis joint view selection. Prior: the 4 direct neighbours' selections.
    nb_r[0] = row - 1; nb_c[0] = col
    nb_r[1] = row + 1; nb_c[1] = col
    nb_r[2] = row; nb_c[2] = col - 1
    nb_r[3] = row; nb_c[3] = col + 1
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
            if cand[i] < 0:
                continue
            value = costs[i * MAX_SOURCES + j]
            if value < c.good_cost:
                sum_good = sum_good + exp(-value * value / 0.18)
                good += 1
            if value > c.bad_cost:
                bad += 1
        if good > 2 and bad < 3:
            prob[j] = sum_good / good
        elif bad < 3:
            prob[j] = exp(-c.good_cost * c.good_cost / 0.32)
        else:
            prob[j] = 0
        prob[j] = prob[j] * (prior[j] if prior[j] > 0 else 1.0)
        total = total + prob[j]
        w[j] = 0
    if total <= 0:
        return evals
    # Monte-Carlo draws from the selection probabilities; weights are the draw counts.
    mask = 0
    for k in range(c.num_view_draws):
        r = _uniform(key, counter) * total
        counter += 1
        value = 0
        for j in range(c.S):
            value = value + prob[j]
            if r < value or j == c.S - 1:
                if prob[j] > 0:
                    w[j] = w[j] + 1
                    mask = mask | (<uint32_t>1 << j)
                break
    if mask == 0:
        return evals
    c.selected[pix] = mask
    for j in range(c.S):
        c.weights[pix * c.S + j] = w[j] / c.num_view_draws
    # 3. The best of the current hypothesis and the candidates under the new weights.
    # Hypotheses compete on photometric (+ geometric) cost plus the planar-prior term; the
    # stored cost stays without the prior, so that filtering judges the images alone. Anchors'
    # planes, like the refinement's hypotheses below, are scored on the selected sources only
    # (the aggregate reads no other) and given up once they cannot win (``_scored``); they come
    # after the checkerboard candidates, so the same hypothesis wins as in one pass in order.
    den = _weight_sum(c, w)
    best_i = -1
    best_photo = _aggregate(c, vc, w)
    best_agg = best_photo + _prior_term(c, pix, c.depth[pix], n)
    if sparse_selection:
        _pick_rescored(c, pix, cand, cand_depth, cand_normal, costs, sparse, w, mask, ray, rescore)
    for i in range(num_cand):
        if cand[i] < 0:
            continue
        if i < NUM_CANDIDATES and sparse[i] and not rescore[i]:
            continue  # a duplicate plane, or not among the best by the sparser cost
        if c.normal_aggregation and not _faces_sources(c, mask, cand_depth[i], &cand_normal[3 * i], ray):
            continue  # a surface that a selected source would see from behind
        prior_i = _prior_term(c, pix, cand_depth[i], &cand_normal[3 * i])
        if i < NUM_CANDIDATES and sparse[i]:
            # Its costs so far are the sparser windows': scored again in full, as an anchor's
            # plane is (selected sources, given up once it cannot win).
            if not _scored(c, &patch, w, den, prior_i, best_agg, row, col, cand_depth[i], &cand_normal[3 * i], ray,
                           &costs[i * MAX_SOURCES], &evals):
                continue
        elif i >= NUM_CANDIDATES:
            if _same_plane(cand_depth[i], &cand_normal[3 * i], c.depth[pix], n):
                cand[i] = -1  # the pixel's own plane: it cannot beat itself
                continue
            if _same_plane_as(cand_depth, cand_normal, cand, i, cand_depth[i], &cand_normal[3 * i]) >= 0:
                cand[i] = -1  # a plane already scored: equal costs cannot win over it
                continue
            if not _scored(c, &patch, w, den, prior_i, best_agg, row, col, cand_depth[i], &cand_normal[3 * i], ray,
                           &costs[i * MAX_SOURCES], &evals):
                continue  # it cannot win (nor can a later anchor with its plane, which it still skips)
        photo = _aggregate(c, &costs[i * MAX_SOURCES], w)
        agg = photo + prior_i
        if agg < best_agg:
            best_agg = agg
            best_photo = photo
            best_i = i
    if best_i >= 0:
        c.depth[pix] = cand_depth[best_i]
        for k in range(3):
            n[k] = cand_normal[3 * best_i + k]
        for j in range(c.S):
            vc[j] = costs[best_i * MAX_SOURCES + j]

    # 4. Refinement: perturbed and random depths and normals, judged by the selected views.
    pert = c.perturbation
    best_d = -1
    if c.depth_aggregation:
        epipolar = _epipolar_intervals(c, mask, c.depth[pix], row, col, intervals)
    for i in range(NUM_REFINE + 2):
        # 0: random depth, 1: random normal, 2: perturbed depth, 3: perturbed normal, 4: both,
        # 5: the planar prior's own plane, 6: the fitted plane (through the anchors, or the
        # region's), when there is one.
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
            d = c.depth_min + (c.depth_max - c.depth_min) * _uniform(key, counter)
        elif (i == 2 or i == 4) and epipolar:
            # Nearer or farther (one draw for both): a depth within the side's interval.
            r = 2.0 * _uniform(key, counter)
            if r < 1:
                d = intervals[0] + (intervals[1] - intervals[0]) * r
            else:
                d = intervals[2] + (intervals[3] - intervals[2]) * (r - 1)
        elif i == 2 or i == 4:
            d = c.depth[pix] * (1.0 + pert * (2.0 * _uniform(key, counter) - 1.0))
        else:
            d = c.depth[pix]
        counter += 1
        if i >= NUM_REFINE:
            pass
        elif i == 1:
            _random_normal(key, counter, ray, hyp_n)
        elif i == 3 or i == 4:
            for k in range(3):
                hyp_n[k] = n[k] + pert * (2.0 * _uniform(key, counter + k) - 1.0)
            _normalise(hyp_n)
            if hyp_n[0] * ray[0] + hyp_n[1] * ray[1] + hyp_n[2] * ray[2] >= 0:
                continue
        else:
            for k in range(3):
                hyp_n[k] = n[k]
        counter += 3
        if not (d > 0 and d >= c.search_min and d <= c.search_max):
            continue
        if i >= NUM_REFINE and _same_plane(d, hyp_n, c.depth[pix], n):
            continue  # the prior's or the fitted plane already taken: it cannot beat itself
        if c.normal_aggregation and not _faces_sources(c, mask, d, hyp_n, ray):
            continue
        prior_i = _prior_term(c, pix, d, hyp_n)
        if not _scored(c, &patch, w, den, prior_i, best_agg, row, col, d, hyp_n, ray, trial_costs, &evals):
            continue
        photo = _aggregate(c, trial_costs, w)
        agg = photo + prior_i
        if agg < best_agg:
            best_agg = agg
            best_photo = photo
            best_d = d
            for k in range(3):
                best_n[k] = hyp_n[k]
            for j in range(c.S):
                best_costs[j] = trial_costs[j]
    if best_d > 0:
        c.depth[pix] = best_d
        for k in range(3):
            n[k] = best_n[k]
        for j in range(c.S):
            vc[j] = best_costs[j]
    if c.keep_view_costs and (best_d > 0 or best_i >= NUM_CANDIDATES or (best_i >= 0 and sparse[best_i])):
        # A refinement, an anchor's plane or a candidate scored again in full (``sparse``) was
        # scored on the selected sources only; the others' costs are needed when the next
        # selection differs. Not after the last sweep of a state: nothing reads them then
        # (``sweep``'s ``keep_view_costs``).
        for j in range(c.S):
            if not w[j] > 0:
                vc[j] = _patches_cost(c, &patch, j, row, col, c.depth[pix], n, ray, &evals)
    c.cost[pix] = best_photo
    return evals


# -- Python entry points --------------------------------------------------------------------

cdef void _fill_ctx(Ctx* c, const float[:, ::1] ref, const float[:, :, ::1] src, const int32_t[:, ::1] src_size,
                    const double[:, ::1] K, const float[:, ::1] A,
                    const float[:, ::1] b, const float[:, ::1] rel_R, const float[:, ::1] rel_t,
                    const float[:, ::1] src_K, const float[:, ::1] src_K_inv,
                    float[:, ::1] depth, float[:, :, ::1] normal, float[:, ::1] cost,
                    float[:, :, ::1] view_cost, float[:, :, ::1] weights, uint32_t[:, ::1] selected,
                    dict params, src_depth) except *:
    # The pointers stay valid while the caller holds the arrays (its arguments).
    cdef int i, k, radius, step
    cdef double sigma_s, sigma_c
    c.ref = &ref[0, 0]
    c.H = ref.shape[0]
    c.W = ref.shape[1]
    c.src = &src[0, 0, 0]
    c.S = src.shape[0]
    c.SH = src.shape[1]
    c.SW = src.shape[2]
    if c.S < 1 or c.S > MAX_SOURCES:
        raise ValueError(f"between 1 and {MAX_SOURCES} source views are supported, got {c.S}")
    c.src_size = &src_size[0, 0]
    c.A = &A[0, 0]
    c.b = &b[0, 0]
    c.rel_R = &rel_R[0, 0]
    c.rel_t = &rel_t[0, 0]
    c.src_K = &src_K[0, 0]
    c.src_K_inv = &src_K_inv[0, 0]
    cdef const float[:, :, ::1] sd
    c.src_depth = NULL
    if src_depth is not None:
        sd = src_depth
        c.src_depth = &sd[0, 0, 0]
    c.prior_depth = NULL
    c.prior_normal = NULL
    c.anchors = NULL
    c.anchor_visible = NULL
    c.fit_depth = NULL
    c.fit_normal = NULL
    c.min_anchors = params.get("min_anchors", 2)
    c.deform_lambda = params.get("deform_lambda", 0.25)
    c.prior_weight = params.get("prior_weight", 0.0)
    sd_ = params.get("prior_sigma_depth", 0.01)
    sa_ = params.get("prior_sigma_angle", 0.1)
    c.prior_inv_two_sigma_depth_sq = 1.0 / (2.0 * sd_ * sd_)
    c.prior_inv_sigma_angle_sq = 1.0 / (sa_ * sa_)
    Ki = _inverse3(K)
    for i in range(9):
        c.K[i] = K[i // 3, i % 3]
        c.K_inv[i] = Ki[i]
    c.depth = &depth[0, 0]
    c.normal = &normal[0, 0, 0]
    c.cost = &cost[0, 0]
    c.view_cost = &view_cost[0, 0, 0]
    c.weights = &weights[0, 0, 0]
    c.selected = &selected[0, 0]
    radius = params["window_radius"]
    step = params["window_step"]
    sigma_s = params["sigma_spatial"]
    sigma_c = params["sigma_color"]
    c.num_samples = _window_table(radius, step, sigma_s, c.off_x, c.off_y, c.spatial, "window_step")
    c.inv_two_sigma_color_sq = 1.0 / (2.0 * sigma_c * sigma_c)
    c.coarse_num_samples = _window_table(radius, params.get("deform_centre_step", 5), sigma_s, c.coarse_off_x,
                                         c.coarse_off_y, c.coarse_spatial, "deform_centre_step")
    c.anchor_num_samples = _window_table(radius, params.get("deform_anchor_step", step), sigma_s, c.anchor_off_x,
                                         c.anchor_off_y, c.anchor_spatial, "deform_anchor_step")
    c.select_num_samples = 0
    if params.get("deform_select_step", 0) > 0:
        c.select_num_samples = _window_table(radius, params["deform_select_step"], sigma_s, c.select_off_x,
                                             c.select_off_y, c.select_spatial, "deform_select_step")
    c.select_rescore = params.get("deform_select_rescore", NUM_CANDIDATES)
    c.depth_min = params["depth_min"]
    c.depth_max = params["depth_max"]
    c.search_min = params.get("search_min", c.depth_min)
    c.search_max = params.get("search_max", c.depth_max)
    c.geom_weight = params["geom_weight"]
    c.geom_max_error = params["geom_max_error"]
    c.good_cost = params["good_cost"]
    c.bad_cost = params["bad_cost"]
    c.perturbation = params["perturbation"]
    c.num_view_draws = params["num_view_draws"]
    c.early_stop = params["early_stop"]
    c.keep_view_costs = params.get("keep_view_costs", True)
    for i in range(c.S):  # C_j = -R_j^T t_j
        for k in range(3):
            c.centre[3 * i + k] = -(rel_R[i, k] * rel_t[i, 0] + rel_R[i, 3 + k] * rel_t[i, 1]
                                    + rel_R[i, 6 + k] * rel_t[i, 2])
    c.normal_aggregation = params.get("normal_aggregation", False)
    c.depth_aggregation = params.get("depth_aggregation", False)
    c.aggregation_inner = params.get("aggregation_inner", 1.0)
    c.aggregation_outer = params.get("aggregation_outer", 5.0)
    c.aggregation_views = params.get("aggregation_views", 3)
    c.seed = <uint64_t>params["seed"]
    c.iteration = params["iteration"]


cdef int _window_table(int radius, int step, double sigma_s, int* off_x, int* off_y, float* spatial,
                       str step_name) except -1:
    """Offsets and spatial weights of a (2 radius + 1)^2 window sampled every ``step`` pixels, row
    by row; returns the number of samples."""
    cdef int dx, dy, n = 0
    for dy in range(-radius, radius + 1, step):
        for dx in range(-radius, radius + 1, step):
            if n >= MAX_SAMPLES:
                raise ValueError(f"the matching window has more than {MAX_SAMPLES} samples; raise {step_name}")
            off_x[n] = dx
            off_y[n] = dy
            spatial[n] = exp(-(dx * dx + dy * dy) / (2.0 * sigma_s * sigma_s))
            n += 1
    return n


def _inverse3(const double[:, ::1] K):
    import numpy as np
    return np.linalg.inv(np.asarray(K)).astype(np.float32).ravel()


cdef void _attach_anchors(Ctx* c, anchors, anchor_visible) except *:
    cdef const int32_t[:, :, ::1] an
    cdef const uint32_t[:, ::1] vis
    if anchors is None:
        return
    an = anchors
    if an.shape[0] != c.H or an.shape[1] != c.W or an.shape[2] != MAX_ANCHORS:
        raise ValueError(f"anchors must be ({c.H}, {c.W}, {MAX_ANCHORS}) int32")
    c.anchors = &an[0, 0, 0]
    if anchor_visible is not None:
        vis = anchor_visible
        if vis.shape[0] != c.H or vis.shape[1] != c.W:
            raise ValueError(f"anchor_visible must be ({c.H}, {c.W}) uint32")
        c.anchor_visible = &vis[0, 0]


cdef void _attach_planes(Ctx* c, depth, normal, const float** depth_ptr, const float** normal_ptr,
                         str what) except *:
    """Point ``depth_ptr`` / ``normal_ptr`` at an optional per-pixel plane map ((H, W) depth, 0 for
    none, and (H, W, 3) normals); the caller holds the arrays."""
    cdef const float[:, ::1] d
    cdef const float[:, :, ::1] n
    if depth is None:
        return
    d = depth
    n = normal
    if d.shape[0] != c.H or d.shape[1] != c.W or n.shape[0] != c.H or n.shape[1] != c.W:
        raise ValueError(f"{what} does not match the image")
    depth_ptr[0] = &d[0, 0]
    normal_ptr[0] = &n[0, 0, 0]


def initialise(ref, src, src_size, K, A, b, rel_R, rel_t, src_K, src_K_inv, src_depth,
               depth, normal, cost, view_cost, weights, selected, dict params, bint randomise,
               int top_k, int num_threads, anchors=None, anchor_visible=None):
    """Random (``randomise``) or given hypotheses -> their costs, weights and selections.
    ``anchors`` (H, W, 8) int32: deformable PatchMatch anchors (pixel indices, -1 none);
    ``anchor_visible`` (H, W) uint32: per pixel, the bit mask of the sources it is visible in
    (an anchor's window is matched in those sources only), or None for all."""
    cdef Ctx c
    _fill_ctx(&c, ref, src, src_size, K, A, b, rel_R, rel_t, src_K, src_K_inv, depth, normal,
              cost, view_cost, weights, selected, params, src_depth)
    _attach_anchors(&c, anchors, anchor_visible)
    cdef int row, col
    cdef int rnd = randomise
    with nogil:
        for row in prange(c.H, schedule="dynamic", num_threads=num_threads):
            for col in range(c.W):
                _initial_pixel(&c, row, col, top_k, rnd)
    return <long long>c.H * c.W * c.S


def sweep(ref, src, src_size, K, A, b, rel_R, rel_t, src_K, src_K_inv, src_depth,
          depth, normal, cost, view_cost, weights, selected, dict params, int colour, int num_threads,
          prior_depth=None, prior_normal=None, anchors=None, fit_depth=None, fit_normal=None,
          anchor_visible=None):
    """Update every pixel with (row + col) % 2 == colour: propagation, view selection, refinement.
    ``prior_depth`` (H, W) / ``prior_normal`` (H, W, 3): an optional planar prior; ``anchors``
    (H, W, 8) int32: deformable PatchMatch anchors, ``anchor_visible`` their visibility (as in
    :func:`initialise`); ``fit_depth`` / ``fit_normal``: fitted planes
    of weak pixels (:func:`fit_anchor_planes`, or their region's plane), one more refinement
    hypothesis. ``params["keep_view_costs"]`` false (default true): a pixel whose plane changes
    keeps in ``view_cost`` only its selected sources' costs, the others' are left stale; for the
    last sweep of a state, which no later sweep reads before ``initialise`` rescores it (depth,
    normal, cost, weights and selections are the same either way)."""
    cdef Ctx c
    _fill_ctx(&c, ref, src, src_size, K, A, b, rel_R, rel_t, src_K, src_K_inv, depth, normal,
              cost, view_cost, weights, selected, params, src_depth)
    _attach_anchors(&c, anchors, anchor_visible)
    _attach_planes(&c, prior_depth, prior_normal, &c.prior_depth, &c.prior_normal, "the planar prior")
    _attach_planes(&c, fit_depth, fit_normal, &c.fit_depth, &c.fit_normal, "the fitted planes")
    cdef int row, col
    cdef long long evaluations = 0
    with nogil:
        for row in prange(c.H, schedule="dynamic", num_threads=num_threads):
            col = (row + colour) % 2
            while col < c.W:
                evaluations += _update_pixel(&c, row, col)
                col = col + 2
    return evaluations


def patch_costs(ref, src, src_size, K, A, b, rel_R, rel_t, src_K, src_K_inv, src_depth,
                const float[:, ::1] depth, const float[:, :, ::1] normal, dict params,
                const int32_t[:, ::1] pixels):
    """Per-source cost of the hypotheses ``depth``/``normal`` at ``pixels`` (N, 2) [row, col]:
    an (N, S) array (the kernel's cost, exposed for tests and diagnostics)."""
    import numpy as np
    cdef Ctx c
    H, W = depth.shape[0], depth.shape[1]
    dummy_cost = np.zeros((H, W), np.float32)
    S = src.shape[0]
    dummy_vc = np.zeros((H, W, S), np.float32)
    dummy_w = np.zeros((H, W, S), np.float32)
    dummy_sel = np.zeros((H, W), np.uint32)
    depth_c = np.array(depth, np.float32)
    normal_c = np.array(normal, np.float32)
    _fill_ctx(&c, ref, src, src_size, K, A, b, rel_R, rel_t, src_K, src_K_inv, depth_c, normal_c,
              dummy_cost, dummy_vc, dummy_w, dummy_sel, params, src_depth)
    out = np.zeros((pixels.shape[0], S), np.float32)
    cdef float[:, ::1] out_v = out
    cdef RefPatch patch
    cdef float ray[3]
    cdef int i, j, row, col
    cdef Py_ssize_t pix
    for i in range(pixels.shape[0]):
        row = pixels[i, 0]
        col = pixels[i, 1]
        pix = <Py_ssize_t>row * c.W + col
        _ray(&c, col, row, ray)
        _ref_patch(&c, row, col, &patch)
        for j in range(c.S):
            out_v[i, j] = _view_cost(&c, &patch, j, row, col, c.depth[pix], c.normal + 3 * pix, ray)
    return out


cdef uint8_t _classify_pixel(const Ctx* c, int row, int col, float max_cost, float min_margin) noexcept nogil:
    """1 (strong) when the pixel's cost is low and rises by at least ``min_margin`` when its depth
    moves 2 or 4 pixels along the epipolar line of its most-weighted source; 0 (weak) otherwise."""
    cdef Py_ssize_t pix = <Py_ssize_t>row * c.W + col
    cdef RefPatch patch
    cdef float ray[3]
    cdef float costs[MAX_SOURCES]
    cdef const float* w = c.weights + pix * c.S
    cdef const float* n = c.normal + 3 * pix
    cdef float d = c.depth[pix], cost0, cost_s, lowest = 1e30, best_w = 0, g, shift
    cdef int j, k, top = -1
    cdef float u0, v0, u1, v1
    if not d > 0:
        return 0
    for j in range(c.S):
        if w[j] > best_w:
            best_w = w[j]
            top = j
    if top < 0:
        return 0
    _ray(c, col, row, ray)
    _ref_patch(c, row, col, &patch)
    for j in range(c.S):
        costs[j] = _view_cost(c, &patch, j, row, col, d, n, ray) if w[j] > 0 else MAX_COST
    cost0 = _aggregate(c, costs, w)
    if cost0 > max_cost:
        return 0
    # Pixels per unit relative depth change in the top source (the baseline's scale).
    shift = 1.01  # a float: the depth step stays in single precision
    if not (_project(c, top, d, ray, &u0, &v0) and _project(c, top, d * shift, ray, &u1, &v1)):
        return 0
    g = sqrt((u1 - u0) * (u1 - u0) + (v1 - v0) * (v1 - v0)) / 0.01
    if g < 1e-6:
        return 0
    for k in range(4):
        shift = (2.0 * (k - 2) if k < 2 else 2.0 * (k - 1)) / g  # -4, -2, 2, 4 pixels
        if not (1.0 + shift > 0.05):
            continue
        for j in range(c.S):
            costs[j] = _view_cost(c, &patch, j, row, col, d * (1.0 + shift), n, ray) if w[j] > 0 else MAX_COST
        cost_s = _aggregate(c, costs, w)
        if cost_s < lowest:
            lowest = cost_s
    return 1 if lowest - cost0 >= min_margin else 0


def classify(ref, src, src_size, K, A, b, rel_R, rel_t, src_K, src_K_inv,
             depth, normal, cost, view_cost, weights, selected, dict params, uint8_t[:, ::1] strong,
             float max_cost, float min_margin, int num_threads):
    """Strong (1) / weak (0) pixels of an estimate by matching ambiguity (photometric cost under
    its current view-selection ``weights``)."""
    cdef Ctx c
    _fill_ctx(&c, ref, src, src_size, K, A, b, rel_R, rel_t, src_K, src_K_inv, depth, normal,
              cost, view_cost, weights, selected, params, None)
    cdef int row, col
    with nogil:
        for row in prange(c.H, schedule="dynamic", num_threads=num_threads):
            for col in range(c.W):
                strong[row, col] = _classify_pixel(&c, row, col, max_cost, min_margin)


def visible_sources(ref, src, src_size, K, A, b, rel_R, rel_t, src_K, src_K_inv, src_depth,
                    depth, normal, cost, view_cost, weights, selected, dict params,
                    uint32_t[:, ::1] visible, float max_error, int num_threads, src_cost=None,
                    int restore_radius=0):
    """Per pixel, the bit mask of the sources it is visible in (paper section 3.4): those its
    view selection chose (``selected``), and with the sources' depth maps (``src_depth``, else
    None) also those where its point's forward-backward reprojection error is at most
    ``max_error`` pixels: the restoration of textureless pixels, whose costs are too high for
    the selection to see them. With the sources' cost maps (``src_cost``, shaped as
    ``src_depth``), the reprojection takes the depth of the lowest-cost pixel within
    ``restore_radius`` of the projected one (``_restored_reprojection_error``). 0 where the
    pixel has no depth."""
    cdef Ctx c
    cdef const float[:, :, ::1] sc
    cdef const float* sc_ptr = NULL
    _fill_ctx(&c, ref, src, src_size, K, A, b, rel_R, rel_t, src_K, src_K_inv, depth, normal,
              cost, view_cost, weights, selected, params, src_depth)
    if visible.shape[0] != c.H or visible.shape[1] != c.W:
        raise ValueError(f"visible must be ({c.H}, {c.W}) uint32")
    if src_cost is not None:
        if c.src_depth == NULL:
            raise ValueError("src_cost needs src_depth")
        if restore_radius < 0:
            raise ValueError("restore_radius must be >= 0")
        sc = src_cost
        if sc.shape[0] != c.S or sc.shape[1] != c.SH or sc.shape[2] != c.SW:
            raise ValueError(f"src_cost must be ({c.S}, {c.SH}, {c.SW}) float32")
        sc_ptr = &sc[0, 0, 0]
    cdef int row, col
    with nogil:
        for row in prange(c.H, schedule="static", num_threads=num_threads):
            for col in range(c.W):
                visible[row, col] = _visible_pixel(&c, row, col, max_error, sc_ptr, restore_radius)


def geometry_constraints(ref, src, src_size, K, A, b, rel_R, rel_t, src_K, src_K_inv, src_depth,
                         depth, normal, cost, view_cost, weights, selected, dict params,
                         float[:, :, ::1] intervals, uint8_t[:, ::1] facing, int num_threads):
    """The geometry-driven constraints (paper section 3.5) of every pixel's plane under its
    ``selected`` sources: ``intervals`` (H, W, 4) the near and far depth intervals of depth
    aggregation (``params["aggregation_*"]``; 0 where no source gives one), ``facing`` (H, W)
    1 where the plane faces every selected source (normal aggregation). For tests and
    diagnostics; ``sweep`` applies them with ``params["normal_aggregation"]`` and
    ``params["depth_aggregation"]``."""
    cdef Ctx c
    _fill_ctx(&c, ref, src, src_size, K, A, b, rel_R, rel_t, src_K, src_K_inv, depth, normal,
              cost, view_cost, weights, selected, params, src_depth)
    if (intervals.shape[0] != c.H or intervals.shape[1] != c.W or intervals.shape[2] != 4
            or facing.shape[0] != c.H or facing.shape[1] != c.W):
        raise ValueError(f"intervals must be ({c.H}, {c.W}, 4) float32 and facing ({c.H}, {c.W}) uint8")
    cdef int row, col
    with nogil:
        for row in prange(c.H, schedule="static", num_threads=num_threads):
            for col in range(c.W):
                facing[row, col] = _constrained_pixel(&c, row, col, &intervals[row, col, 0])


cdef uint8_t _constrained_pixel(const Ctx* c, int row, int col, float* intervals) noexcept nogil:
    cdef Py_ssize_t pix = <Py_ssize_t>row * c.W + col
    cdef float ray[3]
    cdef int k
    _ray(c, col, row, ray)
    if not _epipolar_intervals(c, c.selected[pix], c.depth[pix], row, col, intervals):
        for k in range(4):
            intervals[k] = 0
    return _faces_sources(c, c.selected[pix], c.depth[pix], c.normal + 3 * pix, ray)


cdef uint32_t _visible_pixel(const Ctx* c, int row, int col, float max_error, const float* src_cost,
                             int radius) noexcept nogil:
    cdef Py_ssize_t pix = <Py_ssize_t>row * c.W + col
    cdef float ray[3]
    cdef uint32_t mask
    cdef int j
    cdef float err
    if not c.depth[pix] > 0:
        return 0
    mask = c.selected[pix]
    if c.src_depth != NULL:
        _ray(c, col, row, ray)
        for j in range(c.S):
            if src_cost != NULL:
                err = _restored_reprojection_error(c, j, col, row, c.depth[pix], ray, src_cost, radius)
            else:
                err = _reprojection_error(c, j, col, row, c.depth[pix], ray)
            if err <= max_error:
                mask = mask | (<uint32_t>1 << j)
    return mask


cdef float _restored_reprojection_error(const Ctx* c, int j, float x, float y, float depth, const float* ray,
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
        return c.geom_max_error
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


cdef struct AnchorSearch:
    # The 24 search lines (8 sectors x centre, +15, -15 degrees) as unit steps (sin and cos
    # once, not at every step of every walk).
    double dir_r[3 * MAX_ANCHORS]
    double dir_c[3 * MAX_ANCHORS]
    # Area maximisation's plane check (``find_anchors``' ``plane_error``): NULL depth, none.
    const float* depth
    const float* normal
    float K_inv[9]
    double plane_error


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
                        int max_distance, int step, bint area_max, double max_spread) noexcept nogil:
    """The anchors of pixel (row, col) into ``out`` (see ``find_anchors``). Each sector's
    candidates are the first strong pixel on each of its three search lines; without
    ``area_max`` the nearest of them is the anchor (ties: the centre line first), and the walk
    stops at it."""
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
            # Fixed steps: steps growing to an eighth of the distance were 26 % faster but jumped
            # over thin strong strips (400x300 suite: F1 54.96 / 78.10 instead of 55.15 / 78.58).
            r = r + step
        if first >= 0:
            out[a] = candidates[first]
    if area_max:
        if s.depth != NULL:
            _drop_off_plane(s, candidates, out, W)
        _maximise_area(candidates, out, row, col, W, max_spread)


cdef void _drop_off_plane(const AnchorSearch* s, int32_t* candidates, const int32_t* out, int W) noexcept nogil:
    """Leave out each sector's candidates whose point lies off the plane of the sector's nearest
    anchor (its current depth and normal) by more than ``s.plane_error`` of their depth: a
    farther anchor is worth its spread only on the surface the nearest one is on."""
    cdef int a, k
    cdef int32_t q, q0
    cdef float ray0[3]
    cdef float ray[3]
    cdef float on_plane
    for a in range(MAX_ANCHORS):
        q0 = out[a]
        if q0 < 0:
            continue
        _ray_from(s.K_inv, q0 % W, q0 // W, ray0)
        for k in range(3):
            q = candidates[3 * a + k]
            if q < 0 or q == q0:
                continue
            _ray_from(s.K_inv, q % W, q // W, ray)
            on_plane = _plane_depth(s.normal + 3 * q0, s.depth[q0], ray0, ray)
            if not (s.depth[q] > 0 and on_plane > 0 and fabs(on_plane - s.depth[q]) <= s.plane_error * s.depth[q]):
                candidates[3 * a + k] = -1


cdef inline double _pixel_distance(int32_t q, int W, int row, int col) noexcept nogil:
    """How far pixel q (row-major index) lies from (row, col)."""
    cdef int dr = q // W - row, dc = q % W - col
    return sqrt(<double>(dr * dr + dc * dc))


cdef inline long long _area_gain(int32_t q, int W, int row, int col, long long ur, long long uc) noexcept nogil:
    """(q - p) x u for pixel q, p = (row, col): twice the area q adds, up to a constant."""
    return (q % W - col) * ur - (q // W - row) * uc


cdef void _maximise_area(int32_t* candidates, int32_t* out, int row, int col, int W,
                         double max_spread) noexcept nogil:
    """Paper eq. 12: each sector's anchor becomes the candidate that adds the most area to the
    polygon of the anchors around the pixel, its neighbouring sectors' anchors held fixed. With
    u = (next anchor) - (previous anchor), the growth of triangle areas is half the cross
    product (c - p) x u plus a constant, so the candidate maximising (c - p) x u wins (exact
    integer arithmetic; ties keep the current anchor). The sectors are visited in order, each
    with its neighbours' current anchors, until a visit changes nothing (at most 4 rounds:
    each change grows the polygon, so the rounds converge). Candidates farther from the pixel
    than ``max_spread`` times the nearest one are left out first."""
    cdef int a, k, prev, nxt, m, rounds
    cdef int32_t q, best
    cdef long long ur, uc, gain, best_gain
    cdef double reach
    cdef bint changed
    for a in range(MAX_ANCHORS):
        if out[a] < 0:
            continue
        reach = max_spread * _pixel_distance(out[a], W, row, col)
        for k in range(3):
            q = candidates[3 * a + k]
            if q >= 0 and _pixel_distance(q, W, row, col) > reach:
                candidates[3 * a + k] = -1
    for rounds in range(4):
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
                 int max_distance, int step, int num_threads, bint area_max=False,
                 double max_spread=INFINITY, depth=None, normal=None, K=None, double plane_error=INFINITY):
    """For every weak pixel, one strong anchor per 45-degree sector, searched outward from
    ``min_distance`` to ``max_distance`` pixels in steps of ``step``; with ``labels`` (H, W) int32 only anchors of the
    pixel's own region (eq. 9), and none for boundary pixels (label 0). The nearest strong pixel
    of the sector's three search lines, or with ``area_max`` the one of the lines' first strong
    pixels that maximises the anchors' area (paper eq. 12, ``_maximise_area``). With a finite
    ``plane_error`` (and ``depth`` (H, W) float32, ``normal`` (H, W, 3) float32 and ``K``), only
    candidates within that relative depth of the plane of their sector's nearest anchor compete
    (``_drop_off_plane``)."""
    import numpy as np
    cdef const int32_t[:, ::1] lab
    cdef const float[:, ::1] dep
    cdef const float[:, :, ::1] nor
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
    search.depth = NULL
    search.normal = NULL
    search.plane_error = plane_error
    if not plane_error >= 0:
        raise ValueError("plane_error must be >= 0")
    if area_max and plane_error < INFINITY and H * W > 0:
        if depth is None or normal is None or K is None:
            raise ValueError("a finite plane_error needs depth, normal and K")
        dep = depth
        nor = normal
        if dep.shape[0] != H or dep.shape[1] != W or nor.shape[0] != H or nor.shape[1] != W or nor.shape[2] != 3:
            raise ValueError("depth / normal do not match the strong-pixel map")
        Ki = _inverse3(K)
        for k in range(9):
            search.K_inv[k] = Ki[k]
        search.depth = &dep[0, 0]
        search.normal = &nor[0, 0, 0]
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
                              min_distance, max_distance, step, area_max, max_spread)


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


def random_uniform(uint64_t seed, uint64_t pixel, uint64_t stage, int count):
    """``count`` numbers of the kernel's counter-based generator (for tests)."""
    import numpy as np
    out = np.empty(count, np.float32)
    cdef uint64_t key = _pixel_key(seed, pixel, stage)
    cdef int i
    for i in range(count):
        out[i] = _uniform(key, i)
    return out
