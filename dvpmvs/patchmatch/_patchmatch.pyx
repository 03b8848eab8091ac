# cython: language_level=3
"""Private PatchMatch kernels (ACMH/ACMM family); use :mod:`dvpmvs.patchmatch` instead.

The entry points below run one step of the estimator over every pixel of one reference view at
one scale: ``initialise`` (costs of given or random hypotheses), ``sweep`` (propagation, view
selection and refinement of one checkerboard colour), ``classify`` (strong and weak pixels),
``visible_sources`` and ``geometry_constraints`` (paper sections 3.4 and 3.5). Their concepts
live in units of inline functions: ``_context.pxd`` (state, parameters, rays and planes),
``_window_cost.pxd`` (the matching cost, eq. 3), ``_visibility.pxd`` (reprojection and
visibility, eq. 10-11), ``_propagation.pxd`` (candidates and view selection) and
``_refinement.pxd`` (refinement and section 3.5's constraints). The anchors (eq. 9, 12) are
the separate module ``_anchors.pyx``.

Every call takes the level's views as the leading arguments (``ref``, ``src``, ``src_size``,
``K``, ``A``, ``b``, ``rel_R``, ``rel_t``, ``src_K``, ``src_K_inv``, ``src_depth``; see
``_context.pxd``), the state, and a :class:`KernelParams`.

Determinism: one call updates the pixels of one checkerboard colour; a pixel reads only its own
state and that of the other colour, and random numbers come from a counter-based hash of
(seed, pixel, iteration, draw), so the result does not depend on the number of threads.
"""

from cython.parallel cimport prange
from libc.math cimport exp, sqrt, INFINITY
from libc.stdint cimport uint64_t, uint32_t, int32_t, uint8_t

from dvpmvs.patchmatch._context cimport (Ctx, Params, Window, Work, _no_work, MAX_COST, MAX_SAMPLES, MAX_SOURCES,
                                         NUM_CANDIDATES, _pixel_key, _project, _random_depth, _random_normal, _ray,
                                         _uniform)
from dvpmvs.patchmatch._window_cost cimport (Patches, _aggregate, _all_sources, _colour_weight, _patches,
                                             _plain_patches, _prior_term, _sources_cost, _weight_sum,
                                             dvpmvs_simd_select,
                                             DVPMVS_SIMD_SCALAR, DVPMVS_SIMD_AVX2)
from dvpmvs.patchmatch._visibility cimport _visible_pixel
from dvpmvs.patchmatch._propagation cimport Candidates, _adopt_best_candidate, _propagated, _select_views
from dvpmvs.patchmatch._refinement cimport _epipolar_intervals, _faces_sources, _refine

from dvpmvs._digest cimport DVPMVS_SOURCE_DIGEST

# Checked against this file on import (dvpmvs._kernel_sources.require_current).
SOURCE_DIGEST = (<bytes>DVPMVS_SOURCE_DIGEST).decode("ascii")


# -- the vector path of the matching cost ---------------------------------------------------

SIMD_PATHS = ("scalar", "avx2")


def select_simd(str path="auto"):
    """Choose the matching cost's vector path: ``"auto"`` (the widest this CPU runs), ``"avx2"``
    or ``"scalar"`` (the portable loop); a path the CPU cannot run falls back to the widest one it
    can. Every path gives the same costs, bit for bit. Returns the path taken. At import, the
    environment variable ``DVPMVS_SIMD`` chooses (default auto)."""
    levels = {"scalar": DVPMVS_SIMD_SCALAR, "avx2": DVPMVS_SIMD_AVX2, "auto": DVPMVS_SIMD_AVX2}
    if path not in levels:
        raise ValueError(f"unknown vector path {path!r}: choose one of auto, {', '.join(SIMD_PATHS)} "
                         f"(for example DVPMVS_SIMD=scalar)")
    return SIMD_PATHS[dvpmvs_simd_select(levels[path])]


def _simd_from_environment():
    import os
    path = os.environ.get("DVPMVS_SIMD", "auto").strip().lower() or "auto"
    try:
        return select_simd(path)
    except ValueError as error:
        raise ImportError(f"DVPMVS_SIMD={os.environ['DVPMVS_SIMD']!r}: {error}") from None


SIMD = _simd_from_environment()  # the path chosen at import


# -- parameters -----------------------------------------------------------------------------

# The keys of a KernelParams: every value of the method comes from the estimator
# (``_kernel_params``: the options and the constants beside their equations), so the kernels keep
# no defaults of their own; only the state of a sweep has a starting value.
_REQUIRED = ("window_radius", "window_step", "sigma_spatial", "sigma_color", "depth_min", "depth_max",
             "geom_weight", "geom_max_error", "good_cost", "bad_cost", "perturbation", "num_view_draws",
             "early_stop", "seed", "prior_weight", "prior_sigma_depth", "prior_sigma_angle", "min_anchors",
             "deform_lambda", "deform_centre_step", "deform_anchor_step", "restore_margin",
             "normal_aggregation", "depth_aggregation", "aggregation_inner", "aggregation_outer",
             "aggregation_views")
_OPTIONAL = {"iteration": 0, "keep_view_costs": True}


cdef class KernelParams:
    """Every option of the kernel calls of one pyramid level, converted once into the typed
    ``Params`` struct that the kernels read (window sample tables included).

    ``KernelParams(values)`` takes a mapping of the keys of ``_REQUIRED`` and ``_OPTIONAL``;
    an unknown or missing key is an error. The estimator changes the per-iteration values with
    :meth:`set_iteration`; :meth:`replace` gives a copy with other values."""

    cdef Params p
    cdef dict _values

    def __init__(self, values):
        values = dict(values)
        unknown = sorted(set(values) - set(_REQUIRED) - set(_OPTIONAL))
        missing = [key for key in _REQUIRED if key not in values]
        if unknown or missing:
            raise ValueError(f"kernel parameters: unknown {unknown}, missing {missing}")
        for key, default in _OPTIONAL.items():
            values.setdefault(key, default)
        self._values = values
        cdef Params* p = &self.p
        radius = values["window_radius"]
        sigma_s = values["sigma_spatial"]
        sigma_c = values["sigma_color"]
        _window_table(radius, values["window_step"], sigma_s, &p.plain, "window_step")
        _window_table(radius, values["deform_centre_step"], sigma_s, &p.coarse, "deform_centre_step")
        _window_table(radius, values["deform_anchor_step"], sigma_s, &p.anchor, "deform_anchor_step")
        p.inv_two_sigma_color_sq = 1.0 / (2.0 * sigma_c * sigma_c)
        p.min_anchors = values["min_anchors"]
        p.deform_lambda = values["deform_lambda"]
        p.prior_weight = values["prior_weight"]
        p.restore_margin = values["restore_margin"]
        sd = values["prior_sigma_depth"]
        sa = values["prior_sigma_angle"]
        p.prior_inv_two_sigma_depth_sq = 1.0 / (2.0 * sd * sd)
        p.prior_inv_sigma_angle_sq = 1.0 / (sa * sa)
        p.depth_min = values["depth_min"]
        p.depth_max = values["depth_max"]
        p.geom_weight = values["geom_weight"]
        p.geom_max_error = values["geom_max_error"]
        p.bad_cost = values["bad_cost"]
        p.num_view_draws = values["num_view_draws"]
        p.early_stop = values["early_stop"]
        p.normal_aggregation = values["normal_aggregation"]
        p.depth_aggregation = values["depth_aggregation"]
        p.aggregation_inner = values["aggregation_inner"]
        p.aggregation_outer = values["aggregation_outer"]
        p.aggregation_views = values["aggregation_views"]
        p.seed = <uint64_t>values["seed"]
        self.set_iteration(values["iteration"], values["good_cost"], values["perturbation"],
                           values["keep_view_costs"])

    def set_iteration(self, int iteration, float good_cost, float perturbation, bint keep_view_costs):
        """The values that change from one iteration to the next: the iteration (it seeds the
        random numbers), view selection's good-cost threshold, the refinement's perturbation,
        and whether a changed plane's unselected sources are rescored (a later sweep reads them)."""
        self.p.iteration = iteration
        self.p.good_cost = good_cost
        self.p.perturbation = perturbation
        self.p.keep_view_costs = keep_view_costs
        self._values.update(iteration=iteration, good_cost=good_cost, perturbation=perturbation,
                            keep_view_costs=keep_view_costs)

    def replace(self, **changes):
        """A copy with ``changes``."""
        return KernelParams({**self._values, **changes})

    def as_dict(self):
        return dict(self._values)

    def __repr__(self):
        return f"KernelParams({self._values!r})"


cdef int _window_table(int radius, int step, double sigma_s, Window* window, str step_name) except -1:
    """Offsets and spatial weights of a (2 radius + 1)^2 window sampled every ``step`` pixels, row
    by row."""
    cdef int dx, dy, n = 0
    if step < 1:
        raise ValueError(f"{step_name} must be >= 1, got {step}")
    for dy in range(-radius, radius + 1, step):
        for dx in range(-radius, radius + 1, step):
            if n >= MAX_SAMPLES:
                raise ValueError(f"the matching window has more than {MAX_SAMPLES} samples; raise {step_name}")
            window.off_x[n] = dx
            window.off_y[n] = dy
            window.spatial[n] = exp(-(dx * dx + dy * dy) / (2.0 * sigma_s * sigma_s))
            n += 1
    window.n = n
    return n


# -- what a call reads and updates -----------------------------------------------------------

cdef class LevelViews:
    """The reference and its sources at one pyramid level, as every kernel call reads them:
    ``ref`` (H, W) float32 grey image; ``src`` (S, SH, SW) float32 the sources' images stacked
    (each in its top-left corner) with ``src_size`` (S, 2) int32 their (width, height); ``K``
    (3, 3) float64 the reference's intrinsics; per source, ``A`` (S, 9) and ``b`` (S, 3) float32
    the plane-induced homography's terms (K_j R K^-1 and K_j t), ``rel_R`` (S, 9) and ``rel_t``
    (S, 3) the pose relative to the reference, ``src_K`` and ``src_K_inv`` (S, 9) the
    intrinsics and their inverse; ``src_depth`` (S, SH, SW) float32 the sources' depth maps (the
    geometric pass) or None."""

    cdef readonly object ref, src, src_size, K, A, b, rel_R, rel_t, src_K, src_K_inv, src_depth

    def __init__(self, ref, src, src_size, K, A, b, rel_R, rel_t, src_K, src_K_inv, src_depth=None):
        self.ref, self.src, self.src_size, self.K = ref, src, src_size, K
        self.A, self.b, self.rel_R, self.rel_t = A, b, rel_R, rel_t
        self.src_K, self.src_K_inv, self.src_depth = src_K, src_K_inv, src_depth

    def without_depths(self):
        """The same views without the sources' depth maps (what view selection alone sees)."""
        return LevelViews(self.ref, self.src, self.src_size, self.K, self.A, self.b, self.rel_R, self.rel_t,
                          self.src_K, self.src_K_inv, None)


cdef class PlaneState:
    """The per-pixel state the kernels read and update: ``depth`` (H, W) and ``normal``
    (H, W, 3) float32 the plane hypotheses (camera frame), ``cost`` (H, W) their aggregated
    cost, ``view_cost`` and ``weights`` (H, W, S) float32 the per-source costs and view-selection
    weights, ``selected`` (H, W) uint32 the bit mask of the sources selected. Iterates over the
    six arrays in that order."""

    cdef readonly object depth, normal, cost, view_cost, weights, selected

    def __init__(self, depth, normal, cost, view_cost, weights, selected):
        self.depth, self.normal, self.cost = depth, normal, cost
        self.view_cost, self.weights, self.selected = view_cost, weights, selected

    @classmethod
    def empty(cls, int height, int width, int num_sources):
        """A state of zeros (no hypothesis)."""
        import numpy as np
        return cls(np.zeros((height, width), np.float32), np.zeros((height, width, 3), np.float32),
                   np.zeros((height, width), np.float32), np.zeros((height, width, num_sources), np.float32),
                   np.zeros((height, width, num_sources), np.float32), np.zeros((height, width), np.uint32))

    def __iter__(self):
        return iter((self.depth, self.normal, self.cost, self.view_cost, self.weights, self.selected))

    def copy(self):
        """A state of copies of the arrays."""
        import numpy as np
        return PlaneState(*(np.array(array, copy=True) for array in self))


# -- the context of a call ------------------------------------------------------------------

cdef void _fill_ctx(Ctx* c, LevelViews views, PlaneState state, KernelParams params) except *:
    # The pointers stay valid while the caller holds ``views`` and ``state``.
    cdef const float[:, ::1] ref = views.ref
    cdef const float[:, :, ::1] src = views.src
    cdef const int32_t[:, ::1] src_size = views.src_size
    cdef const double[:, ::1] K = views.K
    cdef const float[:, ::1] A = views.A
    cdef const float[:, ::1] b = views.b
    cdef const float[:, ::1] rel_R = views.rel_R
    cdef const float[:, ::1] rel_t = views.rel_t
    cdef const float[:, ::1] src_K = views.src_K
    cdef const float[:, ::1] src_K_inv = views.src_K_inv
    cdef float[:, ::1] depth = state.depth
    cdef float[:, :, ::1] normal = state.normal
    cdef float[:, ::1] cost = state.cost
    cdef float[:, :, ::1] view_cost = state.view_cost
    cdef float[:, :, ::1] weights = state.weights
    cdef uint32_t[:, ::1] selected = state.selected
    cdef int i, k
    c.p = &params.p
    c.ref = &ref[0, 0]
    c.H = ref.shape[0]
    c.W = ref.shape[1]
    c.src = &src[0, 0, 0]
    c.S = src.shape[0]
    c.SH = src.shape[1]
    c.SW = src.shape[2]
    if c.S < 1 or c.S > MAX_SOURCES:
        raise ValueError(f"between 1 and {MAX_SOURCES} source views are supported, got {c.S}")
    c.batch_indices = <long long>c.S * c.SH * c.SW + c.SW + 2 < 2147483647
    if src_size.shape[0] != c.S or src_size.shape[1] != 2:
        raise ValueError(f"src_size must be ({c.S}, 2) int32")
    for i in range(c.S):
        # The windows' bilinear samples read 2x2 texels inside each source (_window_cost_simd.h).
        if not (2 <= src_size[i, 0] <= c.SW and 2 <= src_size[i, 1] <= c.SH):
            raise ValueError(f"source {i} is {src_size[i, 0]}x{src_size[i, 1]} pixels: the sources must be at least "
                             f"2x2 and fit the stack ({c.SW}x{c.SH})")
    c.src_size = &src_size[0, 0]
    c.A = &A[0, 0]
    c.b = &b[0, 0]
    c.rel_R = &rel_R[0, 0]
    c.rel_t = &rel_t[0, 0]
    c.src_K = &src_K[0, 0]
    c.src_K_inv = &src_K_inv[0, 0]
    cdef const float[:, :, ::1] sd
    c.src_depth = NULL
    if views.src_depth is not None:
        sd = views.src_depth
        c.src_depth = &sd[0, 0, 0]
    c.prior_depth = NULL
    c.prior_normal = NULL
    c.anchors = NULL
    c.anchor_visible = NULL
    c.centre_dropped = NULL
    c.anchor_slot = NULL
    c.anchor_weight = NULL
    c.plain_cached = False
    c.fit_depth = NULL
    c.fit_normal = NULL
    c.handed_cost = NULL
    c.frozen = NULL
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
    for i in range(c.S):  # C_j = -R_j^T t_j
        for k in range(3):
            c.centre[3 * i + k] = -(rel_R[i, k] * rel_t[i, 0] + rel_R[i, 3 + k] * rel_t[i, 1]
                                    + rel_R[i, 6 + k] * rel_t[i, 2])


def _inverse3(const double[:, ::1] K):
    import numpy as np
    return np.linalg.inv(np.asarray(K)).astype(np.float32).ravel()


cdef void _attach_anchors(Ctx* c, anchors, anchor_visible, centre_dropped=None, windows=None) except *:
    cdef const int32_t[:, :, ::1] an
    cdef const uint32_t[:, ::1] vis
    cdef const uint8_t[:, ::1] dropped
    cdef AnchorWindows aw
    if anchors is None:
        return
    if centre_dropped is not None:
        dropped = centre_dropped
        if dropped.shape[0] != c.H or dropped.shape[1] != c.W:
            raise ValueError(f"centre_dropped must be ({c.H}, {c.W}) uint8")
        c.centre_dropped = &dropped[0, 0]
    an = anchors
    if an.shape[0] != c.H or an.shape[1] != c.W or an.shape[2] != 8:
        raise ValueError(f"anchors must be ({c.H}, {c.W}, 8) int32")
    c.anchors = &an[0, 0, 0]
    if anchor_visible is not None:
        vis = anchor_visible
        if vis.shape[0] != c.H or vis.shape[1] != c.W:
            raise ValueError(f"anchor_visible must be ({c.H}, {c.W}) uint32")
        c.anchor_visible = &vis[0, 0]
    if windows is not None:
        aw = windows
        if aw.slot.shape[0] != c.H or aw.slot.shape[1] != c.W or aw.weight.shape[1] != c.p.anchor.n:
            raise ValueError("anchor_windows were computed for another image or window")
        if aw.weight.shape[0] > 0:  # no anchor at all: every window computes its own weights
            c.anchor_slot = &aw.slot[0, 0]
            c.anchor_weight = &aw.weight[0, 0]
            c.plain_cached = aw.plain


cdef class AnchorWindows:
    """The colour weights of the anchor windows around every pixel that is an anchor, computed
    once per level (:func:`anchor_windows`) instead of at every update of every pixel that
    matches with them. ``slot`` (H, W) int32: the row of ``weight`` (N, samples) float32 of the
    pixel's window, -1 for none; ``plain``: the matching window is the anchor window, so the
    anchors' own windows read them too."""
    cdef readonly int32_t[:, ::1] slot
    cdef readonly float[:, ::1] weight
    cdef readonly bint plain

    def __init__(self, slot, weight, bint plain):
        self.slot = slot
        self.weight = weight
        self.plain = plain


def anchor_windows(const float[:, ::1] ref, anchors, KernelParams params, int num_threads):
    """The :class:`AnchorWindows` of ``anchors`` ((H, W, 8) int32 pixel indices, -1 for none)
    on the reference image ``ref``: the same weights the kernels compute for each window
    (``_colour_weight``), so the maps are the same with or without them."""
    import numpy as np
    cdef Ctx c
    c.p = &params.p
    c.ref = &ref[0, 0]
    c.H = ref.shape[0]
    c.W = ref.shape[1]
    an = np.asarray(anchors)
    if an.shape != (c.H, c.W, 8):
        raise ValueError(f"anchors must be ({c.H}, {c.W}, 8) int32")
    used = np.unique(an[an >= 0]).astype(np.int32)
    slot_map = np.full((c.H, c.W), -1, np.int32)
    slot_map.ravel()[used] = np.arange(used.size, dtype=np.int32)
    weight_arr = np.zeros((used.size, params.p.anchor.n), np.float32)
    cdef const int32_t[::1] pixels = used
    cdef float[:, ::1] weight = weight_arr
    cdef int i, k, row, col, x, y, count = used.size
    cdef float centre
    cdef const Window* window = &params.p.anchor
    with nogil:
        for i in prange(count, schedule="static", num_threads=num_threads):
            row = pixels[i] // c.W
            col = pixels[i] - row * c.W
            centre = c.ref[row * c.W + col]
            for k in range(window.n):
                x = col + window.off_x[k]
                y = row + window.off_y[k]
                if 0 <= x < c.W and 0 <= y < c.H:
                    weight[i, k] = _colour_weight(&c, window, k, c.ref[y * c.W + x], centre)
    plain = params.p.plain.n == window.n and all(
        params.p.plain.off_x[k] == window.off_x[k] and params.p.plain.off_y[k] == window.off_y[k]
        and params.p.plain.spatial[k] == window.spatial[k] for k in range(window.n))
    return AnchorWindows(slot_map, weight_arr, plain)


cdef void _attach_frozen(Ctx* c, frozen) except *:
    cdef const uint8_t[:, ::1] f
    if frozen is None:
        return
    f = frozen
    if f.shape[0] != c.H or f.shape[1] != c.W:
        raise ValueError(f"frozen must be ({c.H}, {c.W}) uint8")
    c.frozen = &f[0, 0]


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


# -- one pixel ------------------------------------------------------------------------------

cdef inline void _random_hypothesis(const Ctx* c, int row, int col, const float* ray) noexcept nogil:
    """A random depth in the depth range and a random normal facing the camera at (row, col)."""
    cdef Py_ssize_t pix = <Py_ssize_t>row * c.W + col
    cdef uint64_t key = _pixel_key(c.p.seed, pix, 0xFFFF)
    c.depth[pix] = _random_depth(c.p, _uniform(key, 0))
    _random_normal(key, 1, ray, c.normal + 3 * pix)


cdef Work _initial_pixel(const Ctx* c, int row, int col, int top_k, int randomise) noexcept nogil:
    cdef Py_ssize_t pix = <Py_ssize_t>row * c.W + col
    cdef Patches patch
    cdef float ray[3]
    cdef float* n = c.normal + 3 * pix
    cdef float* vc = c.view_cost + pix * c.S
    cdef float* w = c.weights + pix * c.S
    cdef int j, _pick, chosen, count = 0
    cdef float lo
    cdef uint32_t mask = 0
    cdef Work windows = _no_work()
    if c.frozen != NULL and c.frozen[pix] and not c.depth[pix] > 0:
        # Left empty: no cost, no selection (never a propagation candidate: depth 0).
        for j in range(c.S):
            vc[j] = MAX_COST
            w[j] = 0
        c.cost[pix] = MAX_COST
        c.selected[pix] = 0
        return windows
    _ray(c, col, row, ray)
    if randomise:
        _random_hypothesis(c, row, col, ray)
    elif n[0] * ray[0] + n[1] * ray[1] + n[2] * ray[2] > 0:
        n[0] = -n[0]
        n[1] = -n[1]
        n[2] = -n[2]
    _patches(c, row, col, &patch)
    _sources_cost(c, &patch, _all_sources(c), row, col, c.depth[pix], n, ray, vc, &windows)
    for j in range(c.S):
        w[j] = 0
    # Before any view selection: the mean over the top_k best sources.
    for _pick in range(min(top_k, c.S)):
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
    return windows


cdef Work _update_pixel(const Ctx* c, int row, int col) noexcept nogil:
    """Propagation, view selection and refinement of pixel (row, col); returns what it matched."""
    cdef Py_ssize_t pix = <Py_ssize_t>row * c.W + col
    cdef Patches patch
    cdef Candidates cd
    cdef float ray[3]
    cdef float w[MAX_SOURCES]
    cdef float* n = c.normal + 3 * pix
    cdef uint64_t key = _pixel_key(c.p.seed, pix, <uint64_t>c.p.iteration + 1)
    cdef uint64_t counter = 0
    cdef uint32_t mask
    cdef int j, best_i
    cdef Work evals = _no_work()
    cdef float den, best_agg, best_photo, kept_photo, kept_depth
    cdef float kept_normal[3]
    cdef float kept_costs[MAX_SOURCES]
    cdef bint refined, restorer

    if c.frozen != NULL and c.frozen[pix]:
        return evals
    _ray(c, col, row, ray)
    _patches(c, row, col, &patch)
    if patch.centre.sum_w <= 0:
        return evals
    # 1. Candidates from the other colour, scored against every source.
    if _propagated(c, row, col, &patch, ray, &cd, &evals) == 0:
        return evals
    # 2. Multi-hypothesis joint view selection.
    mask = _select_views(c, row, col, &cd, key, &counter, w)
    if mask == 0:
        return evals
    c.selected[pix] = mask
    for j in range(c.S):
        c.weights[pix * c.S + j] = w[j] / c.p.num_view_draws
    # 3. The best of the current hypothesis and the candidates under the new weights.
    den = _weight_sum(c, w)
    best_photo = _aggregate(c, c.view_cost + pix * c.S, w)
    best_agg = best_photo + _prior_term(c, pix, c.depth[pix], n)
    restorer = c.handed_cost != NULL and c.handed_cost[pix] < INFINITY
    if restorer:
        kept_photo = best_photo
        kept_depth = c.depth[pix]
        for j in range(3):
            kept_normal[j] = n[j]
        for j in range(c.S):
            kept_costs[j] = c.view_cost[pix * c.S + j]
    best_i = _adopt_best_candidate(c, row, col, &patch, ray, &cd, w, mask, den, &best_agg, &best_photo, &evals)
    # 4. Refinement: perturbed and random depths and normals, judged by the selected views.
    refined = _refine(c, row, col, &patch, ray, w, mask, den, key, &counter, &best_agg, &best_photo, &evals)
    if restorer and (best_i >= 0 or refined) and not best_photo < c.handed_cost[pix] - c.p.restore_margin:
        # The detail restorer (ACMM's): after a hand-over the finer level's noise may not replace
        # a plane the coarser level found; a new plane must beat the handed one's cost here by
        # the margin (on a plain wall no candidate does, on texture the better one does).
        c.depth[pix] = kept_depth
        for j in range(3):
            n[j] = kept_normal[j]
        for j in range(c.S):
            c.view_cost[pix * c.S + j] = kept_costs[j]
        c.cost[pix] = kept_photo
        return evals
    if c.p.keep_view_costs and (refined or best_i >= NUM_CANDIDATES):
        # A refinement or an anchor's plane was scored on the selected sources only; the others'
        # costs are needed when the next selection differs. Not after the last sweep of a state:
        # nothing reads them then (``sweep``'s ``keep_view_costs``).
        _rescore_unselected(c, row, col, &patch, ray, w, &evals)
    c.cost[pix] = best_photo
    return evals


cdef inline void _rescore_unselected(const Ctx* c, int row, int col, const Patches* pp, const float* ray,
                                     const float* w, Work* evals) noexcept nogil:
    """The view costs of the sources the pixel did not select (``w`` <= 0), for its plane."""
    cdef Py_ssize_t pix = <Py_ssize_t>row * c.W + col
    cdef int j
    cdef uint32_t unselected = 0
    for j in range(c.S):
        if not w[j] > 0:
            unselected = unselected | (<uint32_t>1 << j)
    _sources_cost(c, pp, unselected, row, col, c.depth[pix], c.normal + 3 * pix, ray,
                  c.view_cost + pix * c.S, evals)


cdef uint8_t _classify_pixel(const Ctx* c, int row, int col, float max_cost, float min_margin) noexcept nogil:
    """1 (strong) when the pixel's cost is low and rises by at least ``min_margin`` when its depth
    moves 2 or 4 pixels along the epipolar line of its most-weighted source; 0 (weak) otherwise."""
    cdef Py_ssize_t pix = <Py_ssize_t>row * c.W + col
    cdef Patches patch
    cdef float ray[3]
    cdef float costs[MAX_SOURCES]
    cdef const float* w = c.weights + pix * c.S
    cdef const float* n = c.normal + 3 * pix
    cdef float d = c.depth[pix], cost0, cost_s, lowest = 1e30, best_w = 0, g, shift
    cdef int j, k, top = -1
    cdef Work windows = _no_work()
    cdef float u0, v0, u1, v1
    cdef uint32_t selected = 0
    if not d > 0:
        return 0
    for j in range(c.S):
        if w[j] > best_w:
            best_w = w[j]
            top = j
        if w[j] > 0:
            selected = selected | (<uint32_t>1 << j)
        costs[j] = MAX_COST  # the aggregate reads the selected sources only
    if top < 0:
        return 0
    _ray(c, col, row, ray)
    _plain_patches(c, row, col, &patch)
    _sources_cost(c, &patch, selected, row, col, d, n, ray, costs, &windows)
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
        _sources_cost(c, &patch, selected, row, col, d * (1.0 + shift), n, ray, costs, &windows)
        cost_s = _aggregate(c, costs, w)
        if cost_s < lowest:
            lowest = cost_s
    return 1 if lowest - cost0 >= min_margin else 0


cdef uint8_t _constrained_pixel(const Ctx* c, int row, int col, float* intervals) noexcept nogil:
    cdef Py_ssize_t pix = <Py_ssize_t>row * c.W + col
    cdef float ray[3]
    cdef int k
    _ray(c, col, row, ray)
    if not _epipolar_intervals(c, c.selected[pix], c.depth[pix], row, col, intervals):
        for k in range(4):
            intervals[k] = 0
    return _faces_sources(c, c.selected[pix], c.depth[pix], c.normal + 3 * pix, ray)


# -- Python entry points --------------------------------------------------------------------

def initialise(LevelViews views, PlaneState state, KernelParams params, bint randomise, int top_k,
               int num_threads, anchors=None, anchor_visible=None, centre_dropped=None, frozen=None,
               anchor_windows=None):
    """Random (``randomise``) or given hypotheses -> their costs, weights and selections.
    ``anchors`` (H, W, 8) int32: deformable PatchMatch anchors (pixel indices, -1 none);
    ``anchor_visible`` (H, W) uint32: per pixel, the bit mask of the sources it is visible in
    (an anchor's window is matched in those sources only), or None for all; ``centre_dropped``
    (H, W) uint8: 1 where a pixel with anchors matches with their windows only (the centre
    window's term of eq. 3 dropped: a weak pixel in a highlight), or None for none; ``frozen``
    (H, W) uint8: 1 where a pixel is not estimated, and one without a depth stays empty (cost
    MAX_COST, no selection), or None; ``anchor_windows``: the anchors' :class:`AnchorWindows`
    (the same costs, fewer colour weights computed), or None. Returns what it matched:
    (hypotheses, windows, samples)."""
    cdef Ctx c
    _fill_ctx(&c, views, state, params)
    _attach_anchors(&c, anchors, anchor_visible, centre_dropped, anchor_windows)
    _attach_frozen(&c, frozen)
    cdef int row, col
    cdef int rnd = randomise
    cdef Work done
    cdef long long hypotheses = 0, windows = 0, samples = 0
    with nogil:
        for row in prange(c.H, schedule="dynamic", num_threads=num_threads):
            for col in range(c.W):
                done = _initial_pixel(&c, row, col, top_k, rnd)
                hypotheses += done.hypotheses
                windows += done.windows
                samples += done.samples
    return hypotheses, windows, samples


def random_hypotheses(const double[:, ::1] K, float[:, ::1] depth, float[:, :, ::1] normal, KernelParams params,
                      int num_threads):
    """The random hypotheses that :func:`initialise` draws with ``randomise`` (for the camera
    ``K``, (H, W) ``depth`` and (H, W, 3) ``normal``), without scoring them."""
    cdef Ctx c
    cdef int i
    if depth.shape[0] != normal.shape[0] or depth.shape[1] != normal.shape[1] or normal.shape[2] != 3:
        raise ValueError("depth (H, W) and normal (H, W, 3) do not match")
    c.p = &params.p
    c.H = depth.shape[0]
    c.W = depth.shape[1]
    if c.H * c.W == 0:
        return
    Ki = _inverse3(K)
    for i in range(9):
        c.K_inv[i] = Ki[i]
    c.depth = &depth[0, 0]
    c.normal = &normal[0, 0, 0]
    cdef int row, col
    cdef float ray[3]
    with nogil:
        for row in prange(c.H, schedule="static", num_threads=num_threads):
            for col in range(c.W):
                _ray(&c, col, row, ray)
                _random_hypothesis(&c, row, col, ray)


def sweep(LevelViews views, PlaneState state, KernelParams params, int colour, int num_threads,
          prior_depth=None, prior_normal=None, anchors=None, fit_depth=None, fit_normal=None,
          anchor_visible=None, centre_dropped=None, handed_cost=None, frozen=None, anchor_windows=None):
    """Update every pixel with (row + col) % 2 == colour: propagation, view selection, refinement.
    ``prior_depth`` (H, W) / ``prior_normal`` (H, W, 3): an optional planar prior; ``anchors``
    (H, W, 8) int32: deformable PatchMatch anchors, ``anchor_visible`` their visibility and
    ``centre_dropped`` the pixels matched with the anchors' windows only (as in
    :func:`initialise`); ``fit_depth`` / ``fit_normal``: fitted planes of weak pixels
    (``_anchors.fit_anchor_planes``, or their region's plane), one more refinement hypothesis.
    ``params``' ``keep_view_costs`` false: a pixel whose plane changes keeps in ``view_cost``
    only its selected sources' costs, the others' are left stale; for the last sweep of a state,
    which no later sweep reads before ``initialise`` rescores it (depth, normal, cost, weights
    and selections are the same either way). ``handed_cost`` (H, W): the
    detail restorer after a hand-over between levels, the handed plane's cost at this level (inf
    where none), which a new plane must beat by ``restore_margin``; ``frozen`` (H, W) uint8: 1
    where a pixel is not updated; ``anchor_windows``: as in :func:`initialise`. Returns what it
    matched: (hypotheses, windows, samples)."""
    cdef Ctx c
    _fill_ctx(&c, views, state, params)
    _attach_anchors(&c, anchors, anchor_visible, centre_dropped, anchor_windows)
    _attach_planes(&c, prior_depth, prior_normal, &c.prior_depth, &c.prior_normal, "the planar prior")
    _attach_planes(&c, fit_depth, fit_normal, &c.fit_depth, &c.fit_normal, "the fitted planes")
    _attach_frozen(&c, frozen)
    cdef const float[:, ::1] handed
    if handed_cost is not None:
        handed = handed_cost
        if handed.shape[0] != c.H or handed.shape[1] != c.W:
            raise ValueError(f"handed_cost must be ({c.H}, {c.W}) float32")
        c.handed_cost = &handed[0, 0]
    cdef int row, col
    cdef Work done
    cdef long long hypotheses = 0, windows = 0, samples = 0
    with nogil:
        for row in prange(c.H, schedule="dynamic", num_threads=num_threads):
            col = (row + colour) % 2
            while col < c.W:
                done = _update_pixel(&c, row, col)
                hypotheses += done.hypotheses
                windows += done.windows
                samples += done.samples
                col = col + 2
    return hypotheses, windows, samples


def patch_costs(LevelViews views, depth, normal, KernelParams params, const int32_t[:, ::1] pixels,
                anchors=None, anchor_visible=None, centre_dropped=None, anchor_windows=None):
    """Per-source cost of the hypotheses ``depth``/``normal`` at ``pixels`` (N, 2) [row, col]:
    an (N, S) array, as the estimator scores them (with ``anchors``, as in :func:`initialise`, the
    deformed cost of the weak pixels; ``anchor_windows`` as there). For tests and diagnostics."""
    import numpy as np
    cdef Ctx c
    depth = np.array(depth, np.float32)
    state = PlaneState.empty(depth.shape[0], depth.shape[1], views.src.shape[0])
    state.depth[...] = depth
    state.normal[...] = np.asarray(normal, np.float32)
    _fill_ctx(&c, views, state, params)
    S = c.S
    _attach_anchors(&c, anchors, anchor_visible, centre_dropped, anchor_windows)
    out = np.zeros((pixels.shape[0], S), np.float32)
    cdef float[:, ::1] out_v = out
    cdef Patches patch
    cdef float ray[3]
    cdef int i, row, col
    cdef Work windows = _no_work()
    cdef Py_ssize_t pix
    for i in range(pixels.shape[0]):
        row = pixels[i, 0]
        col = pixels[i, 1]
        if not (0 <= row < c.H and 0 <= col < c.W):
            raise ValueError(f"pixel ({row}, {col}) is outside the {c.W}x{c.H} image")
        pix = <Py_ssize_t>row * c.W + col
        _ray(&c, col, row, ray)
        _patches(&c, row, col, &patch)
        _sources_cost(&c, &patch, _all_sources(&c), row, col, c.depth[pix], c.normal + 3 * pix, ray,
                      &out_v[i, 0], &windows)
    return out


def classify(LevelViews views, PlaneState state, KernelParams params, uint8_t[:, ::1] strong,
             float max_cost, float min_margin, int num_threads):
    """Strong (1) / weak (0) pixels of an estimate by matching ambiguity (photometric cost under
    its current view-selection ``weights``; the sources' depth maps are not read)."""
    cdef Ctx c
    _fill_ctx(&c, views.without_depths(), state, params)
    cdef int row, col
    with nogil:
        for row in prange(c.H, schedule="dynamic", num_threads=num_threads):
            for col in range(c.W):
                strong[row, col] = _classify_pixel(&c, row, col, max_cost, min_margin)


def visible_sources(LevelViews views, PlaneState state, KernelParams params, uint32_t[:, ::1] visible,
                    float max_error, int num_threads, src_cost=None, int restore_radius=0, src_highlight=None,
                    bint all_sources=False):
    """Per pixel, the bit mask of the sources it is visible in (paper section 3.4): those its
    view selection chose (``selected``), and with the sources' depth maps (``views.src_depth``,
    else None) also those where its point's forward-backward reprojection error is at most
    ``max_error`` pixels: the restoration of textureless pixels, whose costs are too high for
    the selection to see them. With the sources' cost maps (``src_cost``, shaped as
    ``src_depth``), the reprojection takes the depth of the lowest-cost pixel within
    ``restore_radius`` of the projected one (``_restored_reprojection_error``). ``all_sources``:
    every source the point projects into counts as visible (no selection, no restoration), for
    use with ``src_highlight`` alone. ``src_highlight`` (shaped as ``src_depth``, uint8): the
    sources' highlight masks; a source whose pixel under the point is in its highlight is counted
    invisible whatever else says it is visible (paper section 3.5, "Highlight Perception
    Capacity"). 0 where the pixel has no depth."""
    cdef Ctx c
    cdef const float[:, :, ::1] sc
    cdef const float* sc_ptr = NULL
    cdef const uint8_t[:, :, ::1] sh
    cdef const uint8_t* sh_ptr = NULL
    _fill_ctx(&c, views, state, params)
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
    if src_highlight is not None:
        sh = src_highlight
        if sh.shape[0] != c.S or sh.shape[1] != c.SH or sh.shape[2] != c.SW:
            raise ValueError(f"src_highlight must be ({c.S}, {c.SH}, {c.SW}) uint8")
        sh_ptr = &sh[0, 0, 0]
    cdef int row, col
    with nogil:
        for row in prange(c.H, schedule="static", num_threads=num_threads):
            for col in range(c.W):
                visible[row, col] = _visible_pixel(&c, row, col, max_error, sc_ptr, restore_radius, sh_ptr,
                                                   all_sources)


def geometry_constraints(LevelViews views, PlaneState state, KernelParams params, float[:, :, ::1] intervals,
                         uint8_t[:, ::1] facing, int num_threads):
    """The geometry-driven constraints (paper section 3.5) of every pixel's plane under its
    ``selected`` sources: ``intervals`` (H, W, 4) the near and far depth intervals of depth
    aggregation (``aggregation_*``; 0 where no source gives one), ``facing`` (H, W)
    1 where the plane faces every selected source (normal aggregation). For tests and
    diagnostics; ``sweep`` applies them with ``normal_aggregation`` and ``depth_aggregation``."""
    cdef Ctx c
    _fill_ctx(&c, views, state, params)
    if (intervals.shape[0] != c.H or intervals.shape[1] != c.W or intervals.shape[2] != 4
            or facing.shape[0] != c.H or facing.shape[1] != c.W):
        raise ValueError(f"intervals must be ({c.H}, {c.W}, 4) float32 and facing ({c.H}, {c.W}) uint8")
    cdef int row, col
    with nogil:
        for row in prange(c.H, schedule="static", num_threads=num_threads):
            for col in range(c.W):
                facing[row, col] = _constrained_pixel(&c, row, col, &intervals[row, col, 0])


def random_uniform(uint64_t seed, uint64_t pixel, uint64_t stage, int count):
    """``count`` numbers of the kernel's counter-based generator (for tests)."""
    import numpy as np
    out = np.empty(count, np.float32)
    cdef uint64_t key = _pixel_key(seed, pixel, stage)
    cdef int i
    for i in range(count):
        out[i] = _uniform(key, i)
    return out
