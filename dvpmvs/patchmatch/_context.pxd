# The state and parameters every PatchMatch kernel reads, and the small geometry they share.
#
# A unit of declarations and inline functions (no .pyx of its own), cimported by the kernels of
# this package. State of one reference view at one scale, all C-contiguous float32 unless noted:
# ``depth`` (H, W), ``normal`` (H, W, 3) unit camera-frame normals facing the camera, ``cost``
# (H, W) the view-selection-weighted matching cost, ``view_cost`` (H, W, S) the cost of the
# pixel's hypothesis against every source, ``weights`` (H, W, S) the last view-selection weights,
# ``selected`` (H, W) uint32 bit j set when source j was selected.
#
# Sources are padded into one (S, SH, SW) stack with their true sizes in ``src_size`` (S, 2)
# int32 ``(width, height)``. ``A`` (S, 9) = K_j R_j K^-1 and ``b`` (S, 3) = K_j t_j give the
# plane-induced homography H = A + b m^T with m = K^-T n / (n . X) for the plane through the
# camera-frame point X with normal n (R_j, t_j: reference camera -> source camera).
#
# Pixel convention: array index [row, col] is the image point (col, row) (COLMAP's dense stage).

from libc.math cimport sqrt, fabs, cos, sin, M_PI
from libc.stdint cimport uint64_t, uint32_t, int32_t, uint8_t

cdef enum:
    MAX_SOURCES = 32
    MAX_SAMPLES = 256
    NUM_CANDIDATES = 8  # adaptive checkerboard candidates (view selection looks at these)
    MAX_ANCHORS = 8  # deformable PatchMatch: one anchor per 45-degree sector
    MAX_CANDIDATES = 16  # checkerboard candidates + anchors
    NUM_REFINE = 5
    MAX_GROUP = 8  # hypotheses whose windows are matched together (_window_cost._score_group)
    NEAR_DEPTH = 3  # rows of the V-shaped near regions
    FAR_SAMPLES = 11  # samples of the far strips (stride 2)

cdef extern from *:
    """
    #define DVPMVS_MAX_COST 2.0f
    """
    # 1 - NCC lies in [0, 2]
    const float MAX_COST "DVPMVS_MAX_COST"


cdef struct Window:
    # A (2 radius + 1)^2 window sampled every ``step`` pixels, row by row: offsets and spatial
    # weights of its ``n`` samples.
    int n
    int off_x[MAX_SAMPLES]
    int off_y[MAX_SAMPLES]
    float spatial[MAX_SAMPLES]


cdef struct Params:
    # Every option of a kernel call, typed (built once per level by ``KernelParams``).
    Window plain  # the matching window
    Window coarse  # the centre window of a deformed pixel
    Window anchor  # an anchor's window
    float inv_two_sigma_color_sq
    int min_anchors  # a weak pixel with fewer anchors keeps the plain window
    float deform_lambda  # weight of the centre window in the deformed cost (eq. 3)
    float prior_weight
    # The detail restorer at a hand-over between pyramid levels (ACMM's): a pixel leaves the plane
    # handed over only for one whose cost beats the handed plane's cost at this level
    # (``Ctx.handed_cost``) by this margin.
    float restore_margin
    float prior_inv_two_sigma_depth_sq  # relative depth
    float prior_inv_sigma_angle_sq  # on 1 - cos(angle), ~ angle^2 / 2
    float depth_min
    float depth_max
    float geom_weight
    float geom_max_error
    float good_cost
    float bad_cost
    float perturbation
    int num_view_draws
    bint early_stop  # give up hypotheses that cannot win (``_group_scored``); the maps are the same
    bint keep_view_costs  # rescore the unselected sources of a changed plane (another sweep reads them)
    bint normal_aggregation  # paper section 3.5: normals must face every selected source
    bint depth_aggregation  # paper section 3.5: perturbed depths from epipolar intervals
    float aggregation_inner  # ... moving the point this many pixels along the epipolar lines (alpha) ...
    float aggregation_outer  # ... to this many (alpha + beta) ...
    int aggregation_views  # ... in this many of the selected sources (mu)
    uint64_t seed
    int iteration


cdef struct Work:
    # What a kernel call matched (the estimator's workload report): plane hypotheses scored (once
    # per scoring against any number of sources), windows matched (hypothesis x source x window)
    # and the samples those windows read.
    long long hypotheses
    long long windows
    long long samples


cdef inline Work _no_work() noexcept nogil:
    cdef Work work
    work.hypotheses = 0
    work.windows = 0
    work.samples = 0
    return work


cdef inline void _add_work(Work* total, const Work* part) noexcept nogil:
    total.hypotheses += part.hypotheses
    total.windows += part.windows
    total.samples += part.samples


cdef struct Ctx:
    const Params* p
    # The reference view.
    const float* ref
    int W
    int H
    float K[9]
    float K_inv[9]
    # The sources.
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
    bint batch_indices  # the stack is small enough for the vector path's 32-bit indices
    float centre[3 * MAX_SOURCES]  # the sources' camera centres in the reference camera frame
    # Per-pixel guides, NULL where the call has none.
    const float* prior_depth  # (H, W): planar prior depth, 0 where there is none
    const float* prior_normal  # (H, W, 3)
    const int32_t* anchors  # (H, W, MAX_ANCHORS) pixel indices, -1 for none; NULL: no deformation
    const uint32_t* anchor_visible  # (H, W) source bit masks of where an anchor is visible; NULL: all
    # (H, W) 1 where a deformed pixel matches with its anchors' windows only (paper section 3.5,
    # "Highlight Perception Capacity": a weak pixel in the reference's highlight); NULL: none.
    const uint8_t* centre_dropped
    # The colour weights of the anchor windows around the pixels that are anchors, computed once
    # per level (``anchor_windows``): pixel q's at ``anchor_weight + anchor_slot[q] * anchor.n``,
    # one per sample of the window (those outside the image unused); NULL, or slot -1: computed
    # where needed. ``plain_cached``: the matching window is the anchor window, so a pixel's own
    # plain window reads them too.
    const int32_t* anchor_slot
    const float* anchor_weight
    bint plain_cached
    const float* fit_depth  # (H, W): a weak pixel's fitted plane (anchors' or region's), 0 where none
    const float* fit_normal  # (H, W, 3)
    # (H, W): the cost at this level of the plane the level below handed over (inf where none was
    # handed over), for the detail restorer (``Params.restore_margin``); NULL: no restorer.
    const float* handed_cost
    # (H, W) 1 where a pixel is not updated: it keeps its plane, or stays empty (depth 0); NULL: none.
    const uint8_t* frozen
    # The state.
    float* depth
    float* normal
    float* cost
    float* view_cost
    float* weights
    uint32_t* selected


# -- random numbers -------------------------------------------------------------------------
# Counter-based: a hash of (seed, pixel, stage, draw), so that no result depends on the
# number of threads.

cdef inline uint64_t _mix(uint64_t z) noexcept nogil:
    # splitmix64 finaliser: a bijective 64-bit hash.
    z = z + <uint64_t>0x9E3779B97F4A7C15
    z = (z ^ (z >> 30)) * <uint64_t>0xBF58476D1CE4E5B9
    z = (z ^ (z >> 27)) * <uint64_t>0x94D049BB133111EB
    return z ^ (z >> 31)


cdef inline float _uniform(uint64_t key, uint64_t counter) noexcept nogil:
    """Uniform in [0, 1) from (key, counter)."""
    return <float>(_mix(key ^ _mix(counter)) >> 40) * <float>(1.0 / 16777216.0)


cdef inline float _random_depth(const Params* p, float u) noexcept nogil:
    """The depth of a random hypothesis, uniform in the depth range, from ``u`` in [0, 1)
    (COLMAP's and ACMM's draw)."""
    return p.depth_min + (p.depth_max - p.depth_min) * u


cdef inline uint64_t _pixel_key(uint64_t seed, uint64_t pixel, uint64_t stage) noexcept nogil:
    return _mix(_mix(seed) ^ _mix(pixel * <uint64_t>0x100000001B3 + stage))


# -- rays and planes ------------------------------------------------------------------------

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


cdef inline bint _plane_vector(const Ctx* c, float depth, const float* n, const float* ray, float* m) noexcept nogil:
    """m = K^-T n / (n . X) of the plane through X = depth * ray with normal n: the part of its
    homographies (``_homography``) that every source shares. False for no depth or a plane seen
    edge-on."""
    if not (depth > 0):
        return False
    cdef float nx = depth * (n[0] * ray[0] + n[1] * ray[1] + n[2] * ray[2])
    if fabs(nx) < 1e-8:
        return False
    m[0] = (n[0] * c.K_inv[0] + n[1] * c.K_inv[3] + n[2] * c.K_inv[6]) / nx
    m[1] = (n[0] * c.K_inv[1] + n[1] * c.K_inv[4] + n[2] * c.K_inv[7]) / nx
    m[2] = (n[0] * c.K_inv[2] + n[1] * c.K_inv[5] + n[2] * c.K_inv[8]) / nx
    return True


cdef inline void _homography(const Ctx* c, int j, const float* m, float* H) noexcept nogil:
    """The plane-induced homography into source j, H = A_j + b_j m^T (m: ``_plane_vector``)."""
    cdef const float* A = c.A + 9 * j
    cdef const float* b = c.b + 3 * j
    cdef int r
    for r in range(3):
        H[3 * r] = A[3 * r] + b[r] * m[0]
        H[3 * r + 1] = A[3 * r + 1] + b[r] * m[1]
        H[3 * r + 2] = A[3 * r + 2] + b[r] * m[2]


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


cdef inline bint _same_plane(float d, const float* n, float d2, const float* n2) noexcept nogil:
    """The same plane hypothesis: a normal copied unchanged, and a depth equal up to the rounding
    of carrying the plane from one pixel to another (1e-5 relative: 0.05 mm at 5 m)."""
    return (n[0] == n2[0] and n[1] == n2[1] and n[2] == n2[2]
            and fabs(d - d2) <= 1e-5 * d2)
