"""The PatchMatch estimator: Python orchestration of the kernels in ``_patchmatch.pyx`` and ``_anchors.pyx``.

Photometric pass: coarse to fine over an image pyramid; random hypotheses at the coarsest level
(with ``sparse_seed``, the sparse points' planes where they score better), joint bilateral
upsampling of the planes between levels, ``num_iterations`` red-black iterations per level.
Geometric pass: at full resolution from the view's photometric estimate, with the sources'
depth maps adding the reprojection term to the cost. Then unreliable estimates are filtered out.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import cv2
import numpy as np

from dvpmvs._kernel_sources import require_current
from dvpmvs.geometry import scale_intrinsics
from dvpmvs.image import smooth_untextured
from dvpmvs.options.patch_match import MIN_PERTURBATION, VISIBILITY_MAX_ERROR, PatchMatchOptions
from dvpmvs.passes import Pass
from dvpmvs.patchmatch import _anchors, _patchmatch, _upsample
from dvpmvs.patchmatch.planar_prior import (
    PRIOR_SIGMA_ANGLE,
    PRIOR_SIGMA_DEPTH,
    PRIOR_WEIGHT,
    holds_plane,
    planar_prior,
)
from dvpmvs.patchmatch.problem import LevelWork, Problem, Result
from dvpmvs.patchmatch.sparse_seed import sparse_planes
from dvpmvs.validation import resolve_threads

require_current(_anchors)
require_current(_patchmatch)
require_current(_upsample)

__all__ = [
    "estimate",
    "hypothesis_costs",
    "pyramid_sizes",
    "upsample_planes",
    "filter_estimate",
    "find_anchors",
    "observe_stages",
    "unobserved",
    "Stage",
    "StageObserver",
]

_INITIAL_TOP_K = 4  # before view selection, a hypothesis is judged by its best 4 sources


@dataclass(frozen=True)
class Stage:
    """Where an estimate stands: the view, the pass, the pyramid level (0 the coarsest; the
    geometric pass has one) and the stage's name."""

    view: str
    pass_: Pass
    level: int
    name: str


# Called with the stage, a copy of its depth map and the intrinsics of its level.
StageObserver = Callable[[Stage, np.ndarray, np.ndarray], None]
_observers: list[StageObserver] = []


@contextmanager
def observe_stages(observer: StageObserver) -> Iterator[None]:
    """Call ``observer`` with a copy of the depth map at each stage of every estimate made in
    this process while the block runs (but in an :func:`unobserved` block): per pyramid level
    ``start`` (the state handed over from the level below, upsampled), ``propagation`` (after
    the plain iterations), at the finest
    level ``prior`` (after the planar-prior and deformable iterations), then ``filtered`` (the
    result). For diagnostics (where an estimate is gained or lost); the maps do not change."""
    _observers.append(observer)
    try:
        yield
    finally:
        _observers.remove(observer)


def _observe(
    problem: Problem, pass_: Pass, level: int, stage: str, depth: np.ndarray | None, K: np.ndarray
) -> None:
    if depth is None:
        return
    for observer in list(_observers):
        observer(
            Stage(problem.reference.name, pass_, level, stage), depth.copy(), np.asarray(K).copy()
        )


@contextmanager
def unobserved() -> Iterator[None]:
    """Estimates made in the block are not observed: those a depth prior makes for itself
    (``coarse_mvs``) are not the view's estimate."""
    saved = _observers[:]
    _observers.clear()
    try:
        yield
    finally:
        _observers[:] = saved


def _threads(options: PatchMatchOptions) -> int:
    return resolve_threads(options.num_threads)


def pyramid_sizes(width: int, height: int, num_scales: int, min_size: int) -> list[tuple[int, int]]:
    """(width, height) per level, coarsest first; each level halves the one above it and none
    has a longer side under ``min_size`` (the full size is always kept)."""
    sizes = [(width, height)]
    while len(sizes) < num_scales:
        w, h = sizes[-1]
        nw, nh = max(1, round(w / 2)), max(1, round(h / 2))
        if max(nw, nh) < min_size:
            break
        sizes.append((nw, nh))
    return sizes[::-1]


def _resize(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    if image.shape[1] == size[0] and image.shape[0] == size[1]:
        return image
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


@dataclass
class _Level:
    """Everything the kernels need at one pyramid level."""

    ref: np.ndarray
    K: np.ndarray
    views: _patchmatch.LevelViews  # what every kernel call of the level reads
    # (S, SH, SW) the sources' costs beside their depths, if all have one
    src_cost: np.ndarray | None = None
    # At full resolution, with highlight masks: the reference's (H, W) bool and the sources'
    # (S, SH, SW) uint8 (None where no view has one).
    ref_highlight: np.ndarray | None = None
    src_highlight: np.ndarray | None = None

    @classmethod
    def build(
        cls,
        problem: Problem,
        fraction: float,
        use_depth: bool,
        images: list[np.ndarray] | None = None,
    ) -> _Level:
        """``images``: the reference's and the sources' full-resolution images to match (default:
        the problem's own; see ``_matching_images``)."""
        ref_view = problem.reference
        h, w = ref_view.shape
        size = (
            (w, h) if fraction == 1 else (max(1, round(w * fraction)), max(1, round(h * fraction)))
        )
        if images is None:
            images = [ref_view.image] + [view.image for view in problem.sources]
        ref = np.ascontiguousarray(_resize(images[0], size))
        K = scale_intrinsics(ref_view.K, size[0] / w, size[1] / h)
        K_inv = np.linalg.inv(K)
        sources, src_K = [], []
        for view, image in zip(problem.sources, images[1:]):
            sh, sw = view.shape
            ssize = (
                (sw, sh)
                if fraction == 1
                else (max(1, round(sw * fraction)), max(1, round(sh * fraction)))
            )
            sources.append(_resize(image, ssize))
            src_K.append(scale_intrinsics(view.K, ssize[0] / sw, ssize[1] / sh))
        S = len(sources)
        SH = max(s.shape[0] for s in sources)
        SW = max(s.shape[1] for s in sources)
        stack = np.zeros((S, SH, SW), np.float32)
        depth_stack = np.zeros((S, SH, SW), np.float32) if use_depth else None
        with_cost = use_depth and all(view.cost is not None for view in problem.sources)
        cost_stack = np.full((S, SH, SW), np.inf, np.float32) if with_cost else None
        sizes = np.zeros((S, 2), np.int32)
        A = np.zeros((S, 9), np.float32)
        b = np.zeros((S, 3), np.float32)
        rel_R = np.zeros((S, 9), np.float32)
        rel_t = np.zeros((S, 3), np.float32)
        Ks = np.zeros((S, 9), np.float32)
        Ks_inv = np.zeros((S, 9), np.float32)
        for j, (view, image, Kj) in enumerate(zip(problem.sources, sources, src_K)):
            stack[j, : image.shape[0], : image.shape[1]] = image
            sizes[j] = (image.shape[1], image.shape[0])
            if use_depth:
                if view.depth is None:
                    raise ValueError(
                        f"the geometric pass needs the depth map of source view {view.name}"
                    )
                depth_stack[j, : image.shape[0], : image.shape[1]] = (
                    view.depth
                )  # full resolution only
                if with_cost:
                    cost_stack[j, : image.shape[0], : image.shape[1]] = view.cost
            R = view.R @ ref_view.R.T
            t = view.t - R @ ref_view.t
            A[j] = (Kj @ R @ K_inv).ravel()
            b[j] = Kj @ t
            rel_R[j] = R.ravel()
            rel_t[j] = t
            Ks[j] = Kj.ravel()
            Ks_inv[j] = np.linalg.inv(Kj).ravel()
        views = _patchmatch.LevelViews(
            ref, stack, sizes, np.ascontiguousarray(K), A, b, rel_R, rel_t, Ks, Ks_inv, depth_stack
        )
        ref_highlight = src_highlight = None
        if fraction == 1:
            ref_highlight = (
                ref_view.highlight
                if ref_view.highlight is not None and ref_view.highlight.any()
                else None
            )
            if any(view.highlight is not None and view.highlight.any() for view in problem.sources):
                src_highlight = np.zeros((S, SH, SW), np.uint8)
                for j, view in enumerate(problem.sources):
                    if view.highlight is not None:
                        src_highlight[j, : view.shape[0], : view.shape[1]] = view.highlight
        return cls(
            ref=ref,
            K=K,
            views=views,
            src_cost=cost_stack,
            ref_highlight=ref_highlight,
            src_highlight=src_highlight,
        )


def _matching_images(problem: Problem, options: PatchMatchOptions) -> list[np.ndarray]:
    """The reference's and the sources' images as matched: the highlight corrector's images
    where the views carry them (paper section 3.5; edges and fused colours keep the originals),
    smoothed where flat (``options.image_sigma``, ``FLAT_NOISE_SCALE``), once at full resolution
    before any pyramid level is taken."""
    views = [problem.reference, *problem.sources]
    images = [view.image if view.corrected is None else view.corrected for view in views]
    return [smooth_untextured(image, options.image_sigma, FLAT_NOISE_SCALE) for image in images]


# The images are matched smoothed where their texture is within FLAT_NOISE_SCALE times their
# estimated noise (``smooth_untextured``): walls and sky lose their sensor noise, texture stays.
FLAT_NOISE_SCALE = 2.0
# ACMM's detail restorer, at every hand-over between pyramid levels: in the iterations that do not
# deform, a pixel leaves the plane handed over only for one whose cost beats the handed plane's
# cost at the finer level by RESTORE_MARGIN (``restorer`` of ``_run_level``).
RESTORE_MARGIN = 0.1
# Paper eq. 3: a deformed pixel's cost is DEFORM_LAMBDA x its centre window's + (1 -
# DEFORM_LAMBDA) x the mean of its anchors' windows' (``_deformed``); a weak pixel with fewer
# than MIN_ANCHORS anchors keeps its plain window.
DEFORM_LAMBDA = 0.25
MIN_ANCHORS = 2
# Paper section 3.4, the anchor search (``find_anchors``): outward from ANCHOR_SEARCH_START
# pixels in steps of ANCHOR_SEARCH_STEP, over the whole image by default, as APD-MVS searches (a
# large textureless region has its strong pixels only at its border).
ANCHOR_SEARCH_START = 3
ANCHOR_SEARCH_STEP = 2
# Paper eq. 10-11, the anchors' visibility restored in the geometric pass: a source pixel is
# reprojected with the depth of the lowest-cost pixel within VISIBILITY_RESTORE_RADIUS of it in
# that source's photometric maps (the paper's 11x11 window), and the source sees the anchor when
# the forward-backward error is at most VISIBILITY_MAX_ERROR pixels (``options.patch_match``).
VISIBILITY_RESTORE_RADIUS = 5
# Paper eq. 13, depth aggregation (``depth_aggregation``): the refinement's perturbations move the
# pixel's point AGGREGATION_INNER (alpha) to AGGREGATION_OUTER (alpha + beta) pixels along the
# epipolar line of the AGGREGATION_VIEWS-th (mu) most sensitive of its selected sources.
AGGREGATION_INNER = 1.0
AGGREGATION_OUTER = 5.0
AGGREGATION_VIEWS = 3
# ACMMP's view selection (paper eq. 2): a source's cost counts as good under GOOD_COST *
# exp(-iteration^2 / 90) and as bad above BAD_COST; the weights are the counts of VIEW_DRAWS
# Monte-Carlo draws from the sources' selection probabilities (``_select_views``).
GOOD_COST = 0.8
BAD_COST = 1.2
VIEW_DRAWS = 15
# A pixel is strong (section 3.4) when, besides its cost, moving its depth 2 or 4 pixels along the
# epipolar line of its best source raises the cost by at least STRONG_MIN_MARGIN (``classify``).
STRONG_MIN_MARGIN = 0.25
# APD-MVS's fitted plane of a weak pixel: through three of its anchors, agreed with (depth within
# ANCHOR_PLANE_MAX_ERROR, relative) by at least ANCHOR_PLANE_MIN_INLIERS of them; the same test
# keeps a pixel's anchors under the coplanar rule (``anchor_coplanar``).
ANCHOR_PLANE_MAX_ERROR = 0.01
ANCHOR_PLANE_MIN_INLIERS = 4

# The joint bilateral upsampling of the planes between pyramid levels (ACMM's): the coarse
# neighbours within UPSAMPLE_RADIUS coarse pixels, weighted by a spatial Gaussian (coarse pixels)
# times a colour Gaussian of the guide's intensities (in [0, 1]).
UPSAMPLE_RADIUS = 2
UPSAMPLE_SIGMA_SPATIAL = 1.0
UPSAMPLE_SIGMA_COLOR = 0.1


def upsample_planes(
    depth: np.ndarray,
    normal: np.ndarray,
    K_coarse: np.ndarray,
    guide: np.ndarray,
    K_fine: np.ndarray,
    radius: int = UPSAMPLE_RADIUS,
    sigma_spatial: float = UPSAMPLE_SIGMA_SPATIAL,
    sigma_color: float = UPSAMPLE_SIGMA_COLOR,
    num_threads: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Joint bilateral upsampling of a plane map to the size of ``guide`` (the finer grey image).

    Each coarse neighbour's plane is intersected with the fine pixel's ray; the depths and
    normals are averaged with spatial (coarse pixels) x colour (guide intensity) weights.
    """
    out_depth = np.zeros(guide.shape, np.float32)
    out_normal = np.zeros(guide.shape + (3,), np.float32)
    _upsample.upsample_planes(
        np.ascontiguousarray(depth, np.float32),
        np.ascontiguousarray(normal, np.float32),
        np.ascontiguousarray(guide, np.float32),
        np.linalg.inv(K_coarse),
        np.linalg.inv(K_fine),
        out_depth,
        out_normal,
        radius,
        sigma_spatial,
        sigma_color,
        resolve_threads(num_threads),
    )
    return out_depth, out_normal


class _SweepCounter:
    def __init__(self, total: int, callback: Callable[[int, int], None] | None):
        self.total, self.done, self.callback = total, 0, callback

    def step(self) -> None:
        self.done += 1
        if self.callback is not None:
            self.callback(self.done, self.total)


def _run_level(
    level: _Level,
    problem: Problem,
    options: PatchMatchOptions,
    iterations: int,
    initial: tuple[np.ndarray, np.ndarray] | None,
    seed_stage: int,
    counter: _SweepCounter,
    prior_iterations: int = 0,
    deform: bool = False,
    seeds: tuple[np.ndarray, np.ndarray] | None = None,
    observe: Callable[[str, np.ndarray], None] | None = None,
    labels: np.ndarray | None = None,
    restorer: bool = False,
    empty: np.ndarray | None = None,
):
    """From random hypotheses (or ``initial`` where it has a depth; or the plane ``seeds``
    (depth, normal; 0 where none) gives a pixel, where it scores better than the random one):
    ``iterations`` red-black iterations, then ``prior_iterations`` more with the planar prior
    built from the state reached (when ``options.planar_prior``) and, with ``deform``, deformable
    PatchMatch (pixels classified strong/weak on the state reached, anchors found in the region
    ``labels`` of this level). With the reference's highlight mask (``level.ref_highlight``)
    the ``options.highlight_*`` rules apply.

    ``restorer``: ``initial`` is the plane map the level below handed over; in the iterations
    that do not deform, a pixel leaves its handed plane only for one whose cost beats the handed
    plane's cost at this level by ``RESTORE_MARGIN`` (ACMM's detail restorer). ``empty``
    (H, W) bool: pixels never estimated (depth 0: masked).

    Returns depth, normal, cost, weights, what was matched (hypotheses, windows, samples), the
    prior depth (or None), the anchors (or None) and the strong pixels of the classification (or
    None; classified on the final state when deformation did not classify them and a highlight
    rule needs them). The refinement's perturbation and the view-selection threshold restart at
    every level and pass (shrinking them over the whole run instead lost several F1 points at
    2 cm on the 400x300 room)."""
    h, w = level.ref.shape
    S = len(problem.sources)
    if initial is None:
        depth = np.zeros((h, w), np.float32)
        normal = np.zeros((h, w, 3), np.float32)
    else:
        depth = np.ascontiguousarray(initial[0], np.float32).copy()
        normal = np.ascontiguousarray(initial[1], np.float32).copy()
    cost = np.zeros((h, w), np.float32)
    view_cost = np.zeros((h, w, S), np.float32)
    weights = np.zeros((h, w, S), np.float32)
    selected = np.zeros((h, w), np.uint32)
    params = _kernel_params(
        problem, options, seed=(options.seed * 1_000_003 + seed_stage) & 0x7FFFFFFFFFFFFFFF
    )
    state = _patchmatch.PlaneState(depth, normal, cost, view_cost, weights, selected)
    threads = _threads(options)
    frozen = None
    if empty is not None and empty.any():
        depth[empty] = 0
        normal[empty] = 0
        frozen = np.ascontiguousarray(empty, np.uint8)
    # Unknown pixels of a given estimate start from random hypotheses.
    randomise = initial is None and frozen is None
    handed = None
    if not randomise:
        holes = ~(depth > 0)
        if empty is not None:
            holes &= ~empty
        if restorer:
            handed = ~holes & (depth > 0)
        if holes.any():
            rnd = _random_state(level, problem, params, threads)
            depth[holes] = rnd[0][holes]
            normal[holes] = rnd[1][holes]
    matched = np.asarray(
        _patchmatch.initialise(
            level.views, state, params, randomise, _INITIAL_TOP_K, threads, frozen=frozen
        ),
        np.int64,
    )
    if seeds is not None:
        if empty is not None:
            seeds = (np.where(empty, 0, seeds[0]).astype(np.float32), seeds[1])
        matched += _take_better_seeds(level, state, seeds, params, threads)
    handed_cost = None
    if handed is not None:
        handed_cost = np.where(handed, cost, np.inf).astype(np.float32)
    prior = anchors = windows = strong = visible = centre_dropped = None
    highlight = level.ref_highlight
    # Deformation starts at the first prior iteration, where ``initialise`` rescores every pixel.
    deform_from = iterations if deform else None
    for iteration in range(iterations + prior_iterations):
        if iteration == iterations and iterations and observe is not None:
            observe("propagation", depth)
        if iteration == deform_from:
            strong = _strong_pixels(level, options, state, params, threads)
        if iteration == iterations and options.planar_prior:
            # A region's dominant plane is for its weak pixels: a strong one's own plane is
            # the images' word, finer than the region's (a facade's relief).
            weak = None if strong is None else strong == 0
            prior = planar_prior(depth, cost, level.K, labels=labels, weak=weak)
        if iteration == deform_from:
            anchor_pixels = strong
            if highlight is not None:
                # Paper section 3.5: strong pixels in the highlight are dropped from this view's
                # map, so they are no anchors either; weak ones there match with their anchors'
                # windows only (eq. 3 without its centre term).
                anchor_pixels = np.where(highlight, 0, strong).astype(np.uint8)
                centre_dropped = highlight.astype(np.uint8)
            anchors = find_anchors(anchor_pixels, labels, options.area_maximisation, threads)
            if options.anchor_coplanar:
                _anchors.keep_coplanar_anchors(
                    depth,
                    anchors,
                    level.K,
                    ANCHOR_PLANE_MAX_ERROR,
                    ANCHOR_PLANE_MIN_INLIERS,
                    threads,
                )
            visible = _visible_sources(level, options, state, params, threads)
            # Every update of a deformed pixel matches its anchors' windows: their colour weights
            # depend on the reference image only, so they are computed once for the level.
            windows = _patchmatch.anchor_windows(level.ref, anchors, params, threads)
            # The current hypotheses are re-scored with the deformed cost, so that they compete
            # with the candidates on equal terms.
            matched += _patchmatch.initialise(
                level.views,
                state,
                params,
                False,
                _INITIAL_TOP_K,
                threads,
                anchors=anchors,
                anchor_visible=visible,
                centre_dropped=centre_dropped,
                frozen=frozen,
                anchor_windows=windows,
            )
        elif anchors is not None:
            # From the selections of the iteration before (the anchors' own visibility).
            visible = _visible_sources(level, options, state, params, threads)
        deformed = anchors is not None
        good_cost = GOOD_COST * float(np.exp(-(iteration**2) / 90.0))
        perturbation = max(MIN_PERTURBATION, options.perturbation * 0.5**iteration)
        fit = None
        if anchors is not None:
            # APD-MVS's plane through three anchors, a candidate of every weak pixel; from the
            # state reached: the anchors' depths change from one iteration to the next.
            fit = (np.zeros((h, w), np.float32), np.zeros((h, w, 3), np.float32))
            _anchors.fit_anchor_planes(
                depth,
                anchors,
                level.K,
                *fit,
                ANCHOR_PLANE_MAX_ERROR,
                ANCHOR_PLANE_MIN_INLIERS,
                threads,
            )
        # The view costs of sources a pixel did not select are rescored after a change only where
        # a later sweep of this state reads them: not after the last one, nor before deformation
        # rescores every pixel (the same maps in less time).
        params.set_iteration(
            iteration,
            good_cost,
            perturbation,
            iteration + 1 not in (iterations + prior_iterations, deform_from),
        )
        for colour in (0, 1):
            matched += _patchmatch.sweep(
                level.views,
                state,
                params,
                colour,
                threads,
                *(prior if prior is not None else (None, None)),
                anchors=anchors,
                fit_depth=None if fit is None else fit[0],
                fit_normal=None if fit is None else fit[1],
                anchor_visible=visible,
                centre_dropped=centre_dropped,
                handed_cost=None if deformed else handed_cost,
                frozen=frozen,
                anchor_windows=windows,
            )
            counter.step()
    if observe is not None:
        observe("prior" if prior_iterations else "propagation", depth)
    if strong is None and highlight is not None:
        strong = _strong_pixels(level, options, state, params, threads)
    return (
        depth,
        normal,
        cost,
        weights,
        matched,
        None if prior is None else prior[0],
        anchors,
        strong,
    )


def _with_masked(
    empty: np.ndarray | None, problem: Problem, size: tuple[int, int]
) -> np.ndarray | None:
    """``empty`` (pixels left unestimated at a level of ``size``) with the pixels the problem's
    mask leaves out: at a coarse level those whose whole footprint is masked (a coarse pixel
    partly on a kept surface hands its plane to the kept pixels of the finer level)."""
    if problem.mask is None:
        return empty
    masked = ~problem.mask
    if masked.shape[::-1] != tuple(size):
        masked = (
            cv2.resize(masked.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 1.0 - 1e-3
        )
    return masked if empty is None else empty | masked


def _take_better_seeds(
    level: _Level,
    state: _patchmatch.PlaneState,
    seeds: tuple[np.ndarray, np.ndarray],
    params: _patchmatch.KernelParams,
    threads: int,
) -> np.ndarray:
    """Score the seeded planes and, where one beats the pixel's current plane, take it (in
    ``state``, in place). Returns what was matched (hypotheses, windows, samples)."""
    seeded = seeds[0] > 0
    if not seeded.any():
        return np.zeros(3, np.int64)
    trial = _patchmatch.PlaneState.empty(*state.depth.shape, state.weights.shape[2])
    trial.depth[...] = np.where(seeded, seeds[0], state.depth)
    trial.normal[...] = np.where(seeded[..., None], seeds[1], state.normal)
    matched = _patchmatch.initialise(level.views, trial, params, False, _INITIAL_TOP_K, threads)
    better = seeded & (trial.cost < state.cost)
    for array, candidate in zip(state, trial):
        array[better] = candidate[better]
    return np.asarray(matched, np.int64)


def _strong_pixels(
    level: _Level,
    options: PatchMatchOptions,
    state: _patchmatch.PlaneState,
    params: _patchmatch.KernelParams,
    threads: int,
) -> np.ndarray:
    """(H, W) uint8: 1 where the state reached is unambiguous (``options.strong_max_cost`` and
    ``STRONG_MIN_MARGIN``)."""
    strong = np.zeros(level.ref.shape, np.uint8)
    _patchmatch.classify(
        level.views, state, params, strong, options.strong_max_cost, STRONG_MIN_MARGIN, threads
    )
    return strong


def _visible_sources(
    level: _Level,
    options: PatchMatchOptions,
    state: _patchmatch.PlaneState,
    params: _patchmatch.KernelParams,
    threads: int,
) -> np.ndarray | None:
    """(H, W) uint32 source masks of where each pixel is visible, for the anchors' windows
    (``options.anchor_visibility``; with the sources' highlight masks, less the sources whose
    highlight the pixel's point lands in: paper section 3.5), or None when every anchor is
    matched in every source."""
    highlight = level.src_highlight
    if not options.anchor_visibility and highlight is None:
        return None
    visible = np.zeros(level.ref.shape, np.uint32)
    if not options.anchor_visibility:
        _patchmatch.visible_sources(
            level.views.without_depths(),
            state,
            params,
            visible,
            VISIBILITY_MAX_ERROR,
            threads,
            src_highlight=highlight,
            all_sources=True,
        )
        return visible
    # Without restoration, no depths: view selection only.
    views = level.views if options.visibility_restoration else level.views.without_depths()
    restore = options.visibility_restoration and level.src_cost is not None
    _patchmatch.visible_sources(
        views,
        state,
        params,
        visible,
        VISIBILITY_MAX_ERROR,
        threads,
        src_cost=level.src_cost if restore else None,
        restore_radius=VISIBILITY_RESTORE_RADIUS,
        src_highlight=highlight,
    )
    return visible


def find_anchors(
    strong: np.ndarray,
    labels: np.ndarray | None,
    area_maximisation: bool = False,
    num_threads: int = 0,
    reach: float = 1.0,
    step: int = ANCHOR_SEARCH_STEP,
) -> np.ndarray:
    """For every weak pixel (``strong`` == 0) one strong anchor per 45-degree sector, the nearest
    found walking outward from ``ANCHOR_SEARCH_START`` pixels in steps of ``step`` up to
    ``reach`` times the longer image side, or with ``area_maximisation`` the one of the sector's
    candidates that maximises the anchors' area (paper eq. 12); with ``labels`` only within the
    pixel's own region (paper eq. 9) and none for boundary pixels (label 0).
    (H, W, 8) int32, -1 for none."""
    h, w = strong.shape
    anchors = np.full((h, w, 8), -1, np.int32)
    _anchors.find_anchors(
        np.ascontiguousarray(strong, np.uint8),
        None if labels is None else np.ascontiguousarray(labels, np.int32),
        anchors,
        ANCHOR_SEARCH_START,
        max(ANCHOR_SEARCH_START, int(round(reach * max(h, w)))),
        step,
        resolve_threads(num_threads),
        area_maximisation,
    )
    return anchors


def _random_state(level: _Level, problem: Problem, params: _patchmatch.KernelParams, threads: int):
    """The random hypotheses ``initialise`` would draw for the whole level (for its holes)."""
    h, w = level.ref.shape
    depth = np.zeros((h, w), np.float32)
    normal = np.zeros((h, w, 3), np.float32)
    _patchmatch.random_hypotheses(
        np.ascontiguousarray(level.K, np.float64), depth, normal, params, threads
    )
    return depth, normal


def filter_estimate(
    depth: np.ndarray,
    cost: np.ndarray,
    max_cost: float,
    min_region: int,
    keep: np.ndarray | None = None,
) -> np.ndarray:
    """Depth with unreliable estimates set to 0: cost above ``max_cost`` (unless ``keep``), and
    connected regions (neighbours within 1 % depth) smaller than ``min_region`` pixels (speckles)."""
    reliable = cost <= max_cost if keep is None else (cost <= max_cost) | keep
    depth = np.where(reliable & (depth > 0), depth, 0).astype(np.float32)
    if min_region > 1:
        # filterSpeckles works on 16-bit maps: log-depth in steps of ~1 % keeps the 1 % rule.
        valid = depth > 0
        log_depth = np.zeros(depth.shape, np.int16)
        log_depth[valid] = np.clip(np.round(np.log(depth[valid]) / np.log(1.01)) + 16384, 1, 32767)
        speckled = log_depth.copy()
        cv2.filterSpeckles(speckled, 0, min_region, 1)
        depth[(speckled == 0) & valid] = 0
    return depth


def _kernel_params(
    problem: Problem, options: PatchMatchOptions, seed: int | None = None
) -> _patchmatch.KernelParams:
    """The kernels' typed parameters for ``problem`` (``seed``: the random numbers' seed, by
    default ``options.seed``)."""
    return _patchmatch.KernelParams(
        {
            "window_radius": options.window_radius,
            "window_step": options.window_step,
            "sigma_spatial": options.sigma_spatial,
            "sigma_color": options.sigma_color,
            "depth_min": problem.depth_range[0],
            "depth_max": problem.depth_range[1],
            "geom_weight": options.geom_weight,
            "geom_max_error": options.geom_max_error,
            "good_cost": GOOD_COST,
            "bad_cost": BAD_COST,
            "perturbation": options.perturbation,
            "num_view_draws": VIEW_DRAWS,
            "seed": (options.seed if seed is None else seed) & 0x7FFFFFFFFFFFFFFF,
            "iteration": 0,
            "prior_weight": PRIOR_WEIGHT,
            "prior_sigma_depth": PRIOR_SIGMA_DEPTH,
            "restore_margin": RESTORE_MARGIN,
            "prior_sigma_angle": PRIOR_SIGMA_ANGLE,
            "deform_lambda": DEFORM_LAMBDA,
            "deform_centre_step": options.deform_centre_step,
            "deform_anchor_step": options.deform_anchor_step,
            "min_anchors": MIN_ANCHORS,
            "early_stop": options.early_stop,
            "normal_aggregation": options.normal_aggregation,
            "depth_aggregation": options.depth_aggregation,
            "aggregation_inner": AGGREGATION_INNER,
            "aggregation_outer": AGGREGATION_OUTER,
            "aggregation_views": AGGREGATION_VIEWS,
        }
    )


def hypothesis_costs(
    problem: Problem,
    depth: np.ndarray,
    normal: np.ndarray,
    pixels: np.ndarray,
    options: PatchMatchOptions | None = None,
) -> np.ndarray:
    """The kernel's cost of the plane hypotheses (``depth`` (H, W), camera-frame ``normal``
    (H, W, 3)) at ``pixels`` ((N, 2) [row, col]) against every source: an (N, S) array.

    1 - bilateral-weighted NCC, plus the geometric term when the sources carry depth maps.
    For diagnostics and tests; the estimator evaluates the same function.
    """
    options = options or PatchMatchOptions()
    use_depth = all(view.depth is not None for view in problem.sources)
    level = _Level.build(
        problem, 1.0, use_depth=use_depth, images=_matching_images(problem, options)
    )
    return _patchmatch.patch_costs(
        level.views,
        np.ascontiguousarray(depth, np.float32),
        np.ascontiguousarray(normal, np.float32),
        _kernel_params(problem, options),
        np.ascontiguousarray(pixels, np.int32),
    )


def estimate(
    problem: Problem,
    options: PatchMatchOptions | None = None,
    pass_: Pass | str = Pass.PHOTOMETRIC,
    on_sweep: Callable[[int, int], None] | None = None,
) -> Result:
    """Depth, normal, cost and per-source visibility of ``problem.reference`` for one pass.

    ``on_sweep(done, total)`` is called after every red or black half-iteration (progress).
    """
    options = options or PatchMatchOptions()
    pass_ = Pass(pass_)
    if len(problem.sources) > options.max_sources:
        problem = Problem(
            problem.reference,
            problem.sources[: options.max_sources],
            problem.depth_range,
            problem.initial,
            problem.labels,
            problem.sparse_points,
        )
    start = time.perf_counter()
    h, w = problem.reference.shape
    work: list[LevelWork] = []
    if pass_ is Pass.GEOMETRIC:
        if problem.initial is None:
            raise ValueError(
                f"the geometric pass of {problem.reference.name} needs its photometric estimate"
            )
        level = _Level.build(
            problem, 1.0, use_depth=True, images=_matching_images(problem, options)
        )
        counter = _SweepCounter(2 * options.geom_iterations, on_sweep)
        # With the prior (and deformation), it is built from the photometric estimate and used throughout.
        deform = options.deformable and options.geom_deformable
        guided = options.planar_prior or deform
        plain, with_prior = (0, options.geom_iterations) if guided else (options.geom_iterations, 0)
        observe = (
            (lambda stage, d: _observe(problem, pass_, 0, stage, d, level.K))
            if _observers
            else None
        )
        if observe is not None:
            observe("start", problem.initial[0])
        empty = _with_masked(None, problem, (w, h))
        depth, normal, cost, weights, level_work, prior_depth, anchors, strong = _run_level(
            level,
            problem,
            options,
            plain,
            problem.initial,
            100,
            counter,
            with_prior,
            deform,
            observe=observe,
            labels=problem.labels,
            empty=empty,
        )
        work.append(LevelWork(0, w, h, *map(int, level_work)))
    else:
        sizes = pyramid_sizes(w, h, options.num_scales, options.min_scale_size)
        extra = options.prior_iterations if options.planar_prior or options.deformable else 0
        counter = _SweepCounter(2 * (options.num_iterations * len(sizes) + extra), on_sweep)
        state = problem.initial
        images = _matching_images(problem, options)
        previous: _Level | None = None
        for index, (lw, lh) in enumerate(sizes):
            finest = index == len(sizes) - 1
            level = _Level.build(
                problem, lw / w if (lw, lh) != (w, h) else 1.0, use_depth=False, images=images
            )
            handed_over = previous is not None and state is not None
            if state is not None and state[0].shape != level.ref.shape:
                if previous is None:  # a given initial estimate at the full size, coarse level
                    state = (_resize(state[0], (lw, lh)), _resize(state[1], (lw, lh)))
                else:
                    state = upsample_planes(
                        state[0],
                        state[1],
                        previous.K,
                        level.ref,
                        level.K,
                        num_threads=_threads(options),
                    )
            empty = _with_masked(None, problem, (lw, lh))
            seeds = None
            if state is None and options.sparse_seed and problem.sparse_points is not None:
                ref = problem.reference
                seeds = sparse_planes(
                    problem.sparse_points,
                    level.K,
                    ref.R,
                    ref.t,
                    level.ref.shape[::-1],
                )
            observe = (
                (lambda stage, d, i=index, K=level.K: _observe(problem, pass_, i, stage, d, K))
                if _observers
                else None
            )
            if observe is not None and state is not None:
                observe("start", state[0])
            # The planar prior's and deformable iterations run at full resolution only, where the
            # labels (validated by Problem) fit.
            depth, normal, cost, weights, level_work, prior_depth, anchors, strong = _run_level(
                level,
                problem,
                options,
                options.num_iterations,
                state,
                index,
                counter,
                extra if finest else 0,
                options.deformable and finest,
                seeds,
                observe,
                problem.labels if finest else None,
                restorer=handed_over and RESTORE_MARGIN > 0,
                empty=empty,
            )
            work.append(LevelWork(index, lw, lh, *map(int, level_work)))
            state = (depth, normal)
            previous = level
    # Pixels on their planar prior are kept whatever their photometric cost: that is the
    # prior's purpose (textureless surfaces); fusion still demands agreement between views.
    on_prior = None
    if prior_depth is not None:
        on_prior = (prior_depth > 0) & holds_plane(depth, prior_depth)
    if strong is not None and level.ref_highlight is not None:
        # Paper section 3.5: a reliable pixel in the reference's highlight is left to the views
        # that see no highlight there.
        depth[level.ref_highlight & (strong == 1)] = 0
    depth = filter_estimate(
        depth, cost, options.filter_max_cost, options.filter_min_region, keep=on_prior
    )
    if problem.mask is not None:
        depth[~problem.mask] = 0
    if _observers:
        _observe(
            problem,
            pass_,
            0 if pass_ is Pass.GEOMETRIC else len(sizes) - 1,
            "filtered",
            depth,
            level.K,
        )
    normal[depth <= 0] = 0
    weak = None if anchors is None else (anchors >= 0).sum(axis=2) >= MIN_ANCHORS
    return Result(
        depth=depth,
        normal=normal,
        cost=cost,
        visibility=weights,
        sources=[view.name for view in problem.sources],
        seconds=time.perf_counter() - start,
        hypothesis_evaluations=sum(level.windows for level in work),
        work=work,
        deformed=weak,
    )
