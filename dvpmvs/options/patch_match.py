"""Options of the PatchMatch estimator (validated on construction)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

from dvpmvs.validation import check_field_types, check_threads

__all__ = ["PatchMatchOptions"]


MAX_SOURCES = 32  # view-selection masks are 32-bit
# Paper eq. 11: a source sees an anchor when the anchor's forward-backward reprojection error
# there is at most this many pixels (the restoration's threshold; ``estimator.py`` applies it).
# The geometric term clips that error at ``geom_max_error``, which must therefore exceed it.
VISIBILITY_MAX_ERROR = 2.0
# ACMM's refinement: the relative perturbation halves every iteration down to this
# (``estimator.py``); a ``perturbation`` under it would never be used.
MIN_PERTURBATION = 0.005


@dataclass(frozen=True)
class PatchMatchOptions:
    """Parameters of the ACMH/ACMM-class estimator with DVP-MVS++'s deformable PatchMatch.

    Defaults follow ACMM / ACMMP and the paper; where dvpmvs's default differs from the paper's
    method, ``docs/method.md`` gives the measured reason (``method=paper`` sets the paper's values).
    The method's other constants are named beside their equation (``dvpmvs.patchmatch.estimator``,
    ``planar_prior``).

    Parameters
    ----------
    window_radius, window_step : int
        The matching window (11x11 sampled every 2 pixels).
    sigma_spatial, sigma_color : float
        Bilateral weights of the NCC (pixels; intensity in [0, 1]).
    image_sigma : float
        The images are matched after ``dvpmvs.image.smooth_untextured`` (pixels, at full resolution; 0: as they
        are): Gaussian-smoothed where their texture is within ``FLAT_NOISE_SCALE`` times their estimated noise,
        kept elsewhere (a blur everywhere would cost fine texture the detail sub-pixel precision needs).
    num_scales, min_scale_size : int
        Pyramid levels of the photometric pass (1: full resolution only); levels stop before the longer image
        side drops under ``min_scale_size``.
    num_iterations : int
        Red-black iterations per pyramid level (photometric pass).
    geom_iterations : int
        Red-black iterations of the geometric-consistency pass.
    geom_weight, geom_max_error : float
        Cost += geom_weight * min(reprojection error, geom_max_error). ``geom_max_error`` must exceed the
        anchors' visibility threshold (``VISIBILITY_MAX_ERROR``, 2 pixels), which reads the clipped error.
    perturbation : float
        Relative depth / normal perturbation of the refinement at iteration 0 (0.02: ACMM's value); it is halved
        every iteration down to ``MIN_PERTURBATION`` (0.005).
    max_sources : int
        At most this many source views per reference (the best-ranked ones).
    filter_max_cost : float
        Estimates whose final cost exceeds this are removed (depth 0).
    filter_min_region : int
        Connected regions of depth (1 % steps) smaller than this are removed.
    planar_prior, prior_iterations : bool or int
        Triangulate reliable pixels into a planar prior (ACMMP's idea) for ``prior_iterations`` extra iterations
        at full resolution and the whole geometric pass. With ``deformable`` these iterations deform
        (``quality=medium``: 1).
    deformable, deform_centre_step, deform_anchor_step : bool or int
        Deformable PatchMatch (paper eq. 3) in the iterations after the first estimate at full resolution (the
        planar prior's iterations) and in the geometric pass: weak pixels match an 11x11 centre window sampled
        every ``deform_centre_step`` pixels plus one 11x11 window sampled every ``deform_anchor_step`` pixels
        (the paper's B_s: 2) around each of up to 8 anchors (strong pixels of the same region, one per 45
        degrees), weighted ``DEFORM_LAMBDA`` : 1 - ``DEFORM_LAMBDA`` (``estimator.py``); anchors are also
        candidates.
    geom_deformable : bool
        With ``deformable``, the geometric pass deforms too (the default); false keeps it plain (planar prior
        and reprojection term only; ``quality=low``): less time, lower F1.
    strong_max_cost : float
        A pixel is strong (reliable) when its cost is at most ``strong_max_cost`` and moving its depth 2 or 4
        pixels along the epipolar line of its best source raises the cost by at least ``STRONG_MIN_MARGIN``
        (``estimator.py``); others are weak. A weak pixel with fewer than ``MIN_ANCHORS`` anchors keeps its
        plain window; the anchor search (``find_anchors``) covers the whole image, as APD-MVS's: a large
        textureless region has its strong pixels only at its border.
    area_maximisation : bool
        Paper section 3.4, eq. 12: a sector's candidates are the first strong pixel on each of its three search
        lines (its centre and 15 degrees either side), and its anchor is the candidate that adds the most area
        to the polygon of the anchors around the pixel, the neighbouring sectors' anchors held fixed (sectors
        visited in turn until nothing changes), instead of the nearest candidate.
    anchor_coplanar : bool
        APD-MVS's reliability rule: once found, a weak pixel keeps only the anchors on its anchor plane (the
        plane through three of its anchors that the most anchors agree with, which every weak pixel also tries
        as a candidate: ``fit_anchor_planes``, from the state reached); without a plane that enough anchors
        agree with, it loses its
        anchors and matches its plain window. On in ``method=w_o_agn`` (APD-MVS's deformation, anchors
        anywhere); off with the aligned prior's regions, which already keep the anchors on the pixel's surface.
    sparse_seed : bool
        At the coarsest level of the photometric pass, each pixel also scores the plane of the sparse points'
        triangle it falls in (``dvpmvs.patchmatch.sparse_seed``; needs the problem's ``sparse_points``) and
        starts from it where it beats its random hypothesis. On by default: it finds the ground running toward
        the camera that random draws miss.
    anchor_visibility, visibility_restoration : bool
        A deformed pixel matches each anchor's window only in the sources the anchor is visible in (paper
        section 3.4, eq. 10-11; a source that sees none of them is judged by the centre window alone). Visible:
        chosen by the anchor's own view selection (the state before each deformed iteration), or, in the
        geometric pass, with a forward-backward reprojection error of at most ``VISIBILITY_MAX_ERROR`` pixels:
        the paper's restoration, which reprojects the source pixel with the depth of the lowest-cost pixel
        within ``VISIBILITY_RESTORE_RADIUS`` of it in that source's photometric maps (``estimator.py``: the
        paper's 2 pixels and 11x11 window). ``visibility_restoration`` false: no restoration, the view selection
        alone (the paper's ``w/o Res``).
    normal_aggregation : bool
        Paper section 3.5, normal aggregation: a propagated or refined plane is not taken where a source the
        pixel selected would see its back (n . (P - C_j) > 0 for the plane's point P and the source's centre
        C_j). Every pass and level.
    depth_aggregation : bool
        Paper section 3.5, depth aggregation: the refinement's perturbed depths are drawn, nearer or farther
        with equal chance, from intervals that move the pixel's point by ``AGGREGATION_INNER`` to
        ``AGGREGATION_OUTER`` pixels along its epipolar line in the ``AGGREGATION_VIEWS``-th most sensitive of
        its selected sources (``estimator.py``: the paper's alpha = 1, alpha + beta = 5 and mu = 3), instead of
        by a fixed relative ``perturbation``.
    highlight_multiview : bool
        Before the geometric pass, every view's highlight mask is joined with the multi-view evidence of the
        photometric maps (``dvpmvs.highlight.multiview_highlight``: brighter than the darkest source that sees
        the same point), and its corrected image takes that source's level there.
    early_stop : bool
        After view selection, a hypothesis is given up as soon as a lower bound of its aggregated cost shows it
        cannot win (every source's cost is >= 0); the maps are bit for bit those of scoring it fully (false, for
        verification).
    seed : int
        The same seed gives the same maps, whatever the thread count.
    num_threads : int
        OpenMP threads of the kernels; 0 uses every core.
    """

    # -- matching cost (eq. 1): the window, its bilateral weights, the images matched --
    window_radius: int = 5  # 11x11 matching window ...
    window_step: int = 2  # ... sampled every 2 pixels
    sigma_spatial: float = 5.0  # bilateral NCC weights: pixels
    sigma_color: float = 0.1  # and intensity (images in [0, 1])
    # images smoothed (Gaussian, pixels) where flat before matching; 0: as they are
    image_sigma: float = 1.0
    # give up hypotheses that cannot win (same maps; false: score every one fully)
    early_stop: bool = True

    # -- photometric pass: pyramid levels, iterations, upsampling between levels --
    num_scales: int = 3  # pyramid levels of the photometric pass (coarse to fine)
    min_scale_size: int = 160  # no level with a longer side under this
    num_iterations: int = 1  # red-black iterations per level (photometric pass)

    # -- geometric pass --
    geom_iterations: int = 1  # red-black iterations of the geometric pass
    geom_weight: float = 0.2  # cost += geom_weight * min(reprojection error, geom_max_error)
    geom_max_error: float = 3.0  # pixels

    # -- view selection (eq. 2, ACMMP's) --
    max_sources: int = 10  # source views per reference (best ranked first)

    # -- hypotheses: random draws, sparse seeding, refinement --
    sparse_seed: bool = True  # the coarsest level also tries the sparse points' triangulated planes
    # refinement: relative perturbation at the first iteration (ACMM's), halved each one
    perturbation: float = 0.02

    # -- filtering of the final maps --
    # estimates with a higher final cost are removed (unless on the planar prior)
    filter_max_cost: float = 1.0
    filter_min_region: int = 20  # connected depth regions smaller than this (pixels) are removed

    # -- planar prior (ACMMP's) --
    planar_prior: bool = True  # planar prior from triangulated reliable pixels (ACMMP's idea)
    prior_iterations: int = 2  # extra full-resolution iterations with the prior (photometric pass)

    # -- deformable PatchMatch (eq. 3) --
    deformable: bool = True  # deformable PatchMatch (paper eq. 3) after the first estimate
    geom_deformable: bool = True  # ... and in the geometric pass (false: plain there, faster)
    deform_centre_step: int = 5  # the deformed pixel's own 11x11 window is sampled every 5 pixels
    deform_anchor_step: int = 2  # each anchor's 11x11 window every 2 pixels

    # -- strong pixels and the anchor search (section 3.4, eq. 12) --
    strong_max_cost: float = 0.3  # strong (reliable) pixel: cost <= this ...
    # paper eq. 12: each sector's anchor the candidate that most grows the anchors' area
    area_maximisation: bool = False

    # -- planes through anchors (APD-MVS's) --
    # APD-MVS rule: keep only the anchors on the plane through 3 of them (none without one)
    anchor_coplanar: bool = False

    # -- anchor visibility (section 3.4, eq. 10-11) --
    # match an anchor's window only in the sources it is visible in (paper 3.4): its selected
    # sources, and in the geometric pass those it reprojects into (restoration)
    anchor_visibility: bool = True
    # false: no restoration, visibility from view selection alone (paper's w/o Res)
    visibility_restoration: bool = True

    # -- geometry-driven refinement (section 3.5): normal and depth aggregation --
    normal_aggregation: bool = False  # paper 3.5: no plane a selected source would see from behind
    # paper 3.5: perturbed depths move the point along the sources' epipolar lines
    depth_aggregation: bool = False

    # -- highlight perception (section 3.5; the rules of ``estimate`` where a view has a mask) --
    # geometric pass: masks joined with the views' disagreement (a highlight moves)
    highlight_multiview: bool = True

    # -- the run --
    seed: int = 0
    num_threads: int = 0

    def __post_init__(self):
        check_field_types(self, "patch_match.")

        def check(ok: bool, message: str) -> None:
            if not ok:
                raise ValueError(message)

        def check_window_step(name: str, window: str) -> None:
            # A window of 2 * window_radius + 1 pixels sampled every `name` pixels, per axis;
            # the kernel's sample tables hold 256.
            step = getattr(self, name)
            check(
                1 <= step <= self.window_radius, f"{name} must be in [1, window_radius], got {step}"
            )
            check(
                ((2 * self.window_radius) // step + 1) ** 2 <= 256,
                f"{window} has more than 256 samples; raise {name}",
            )

        check(self.window_radius >= 1, f"window_radius must be >= 1, got {self.window_radius}")
        check_window_step("window_step", "the matching window")
        check(
            self.sigma_spatial > 0 and self.sigma_color > 0,
            "sigma_spatial and sigma_color must be > 0",
        )
        check(
            0 <= self.image_sigma <= 5,
            f"image_sigma must be in [0, 5] pixels, got {self.image_sigma}",
        )
        check(self.num_scales >= 1, f"num_scales must be >= 1, got {self.num_scales}")
        check(self.min_scale_size >= 16, f"min_scale_size must be >= 16, got {self.min_scale_size}")
        check(self.num_iterations >= 1, f"num_iterations must be >= 1, got {self.num_iterations}")
        check(
            self.geom_iterations >= 1, f"geom_iterations must be >= 1, got {self.geom_iterations}"
        )
        check(self.geom_weight >= 0, f"geom_weight must be >= 0, got {self.geom_weight}")
        check(
            self.geom_max_error > VISIBILITY_MAX_ERROR,
            f"geom_max_error must be > {VISIBILITY_MAX_ERROR} pixels (the anchors' visibility "
            f"threshold reads the error clipped there), got {self.geom_max_error}",
        )
        check(
            MIN_PERTURBATION <= self.perturbation < 1,
            f"perturbation must be in [{MIN_PERTURBATION}, 1), got {self.perturbation}",
        )
        check(1 <= self.max_sources <= MAX_SOURCES, f"max_sources must be in [1, {MAX_SOURCES}]")
        check(
            0 < self.filter_max_cost <= 2,
            f"filter_max_cost must be in (0, 2], got {self.filter_max_cost}",
        )
        check(self.filter_min_region >= 0, "filter_min_region must be >= 0")
        check(
            self.prior_iterations >= 1,
            f"prior_iterations must be >= 1, got {self.prior_iterations}",
        )
        check_window_step("deform_centre_step", "the deformed centre window")
        check_window_step("deform_anchor_step", "the anchor window")
        check(
            0 < self.strong_max_cost <= 2,
            f"strong_max_cost must be in (0, 2], got {self.strong_max_cost}",
        )
        check(self.seed >= 0, f"seed must be >= 0, got {self.seed}")
        check_threads("num_threads", self.num_threads)

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any]) -> PatchMatchOptions:
        """Build from a config mapping, naming unknown keys (typos) in the error."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(
                f"unknown patch-match option(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}"
            )
        return cls(**dict(values))

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)
