"""Options of the PatchMatch estimator (validated on construction)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

from dvpmvs.validation import check_field_types, check_threads

__all__ = ["PatchMatchOptions"]


MAX_SOURCES = 32  # view-selection masks are 32-bit


@dataclass(frozen=True)
class PatchMatchOptions:
    """Parameters of the ACMH/ACMM-class estimator with DVP-MVS++'s deformable PatchMatch.

    Defaults follow ACMM / ACMMP and the paper; where dvpmvs's default differs from the paper's
    method, ``docs/method.md`` gives the measured reason (``method=paper`` sets the paper's values).

    Parameters
    ----------
    window_radius, window_step : int
        The matching window (11x11 sampled every 2 pixels).
    sigma_spatial, sigma_color : float
        Bilateral weights of the NCC (pixels; intensity in [0, 1]).
    image_sigma, image_noise_scale : float
        The images are matched after ``dvpmvs.image.smooth_untextured`` (pixels, at full resolution; 0: as they
        are): Gaussian-smoothed where their texture is within ``image_noise_scale`` times their estimated noise,
        kept elsewhere (a blur everywhere would cost fine texture the detail sub-pixel precision needs).
    num_scales, min_scale_size : int
        Pyramid levels of the photometric pass (1: full resolution only); levels stop before the longer image
        side drops under ``min_scale_size``.
    num_iterations : int
        Red-black iterations per pyramid level (photometric pass).
    restore_margin : float
        ACMM's detail restorer at every hand-over between pyramid levels: in the iterations that do not deform, a
        pixel leaves the plane handed over only for one whose cost beats the handed plane's cost at the finer
        level by this margin (0.1: ACMM's; 0: no restorer).
    geom_iterations : int
        Red-black iterations of the geometric-consistency pass.
    geom_weight, geom_max_error : float
        Cost += geom_weight * min(reprojection error, geom_max_error).
    perturbation, min_perturbation : float
        Relative depth / normal perturbation of the refinement at iteration 0; it is halved every iteration down
        to ``min_perturbation`` (0.02: ACMM's value).
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
    prior_regions : bool
        With region labels (the aligned prior's segmentation), a triangle whose three support pixels do not
        share a region gives no prior (it would span a depth edge); without labels (``method=w_o_agn``,
        ``segmentation=null``) it has no effect.
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
        (``estimator.py``); others are weak.
    min_anchors : int
        A weak pixel with fewer anchors keeps its plain window.
    anchor_min_distance, anchor_step, anchor_max_distance : float or int
        The anchor search walks outward from this distance in steps of this many pixels, up to
        ``anchor_max_distance`` times the longer image side (the whole image by default, as APD-MVS searches: a
        large textureless region has its strong pixels only at its border).
    area_maximisation : bool
        Paper section 3.4, eq. 12: a sector's candidates are the first strong pixel on each of its three search
        lines (its centre and 15 degrees either side), and its anchor is the candidate that adds the most area
        to the polygon of the anchors around the pixel, the neighbouring sectors' anchors held fixed (sectors
        visited in turn until nothing changes), instead of the nearest candidate.
    anchor_plane : bool
        A weak pixel also tries the plane through three of its anchors whose triangle contains it, the one
        agreed with by the most anchors (depth within ``ANCHOR_PLANE_MAX_ERROR``, relative), if at least
        ``ANCHOR_PLANE_MIN_INLIERS`` agree (APD-MVS's fitted plane, ``estimator.py``); recomputed before every
        deformed iteration.
    anchor_coplanar : bool
        APD-MVS's reliability rule: once found, a weak pixel keeps only the anchors on its anchor plane (as
        ``anchor_plane``, from the state reached); without a plane that enough anchors agree with, it loses its
        anchors and matches its plain window. On in ``method=w_o_agn`` (APD-MVS's deformation, anchors
        anywhere); off with the aligned prior's regions, which already keep the anchors on the pixel's surface.
    range_slack : float
        Random hypotheses are drawn in the view's depth range (the sparse points' 1-99 % quantiles stretched by
        25 %, as COLMAP); propagation, refinement and the priors' planes may take depths down to min /
        range_slack and up to max * range_slack. inf (the default, as COLMAP, which bounds only its random
        draws): no bound, so that surfaces without sparse points (a facade's near street) are reached; 1: the
        range itself.
    sparse_seed : bool
        At the coarsest level of the photometric pass, each pixel also scores the plane of the sparse points'
        triangle it falls in (``dvpmvs.patchmatch.sparse_seed``; needs the problem's ``sparse_points``) and
        starts from it where it beats its random hypothesis. On by default: it finds the ground running toward
        the camera that random draws miss.
    anchor_visibility, visibility_max_error, visibility_restore_radius, visibility_restoration : bool or float or int
        A deformed pixel matches each anchor's window only in the sources the anchor is visible in (paper
        section 3.4, eq. 10-11; a source that sees none of them is judged by the centre window alone). Visible:
        chosen by the anchor's own view selection (the state before each deformed iteration), or, in the
        geometric pass, with a forward- backward reprojection error of at most ``visibility_max_error`` pixels:
        the paper's restoration, which reprojects the source pixel with the depth of the lowest-cost pixel
        within ``visibility_restore_radius`` of it in that source's photometric maps (5: the paper's 11x11
        window; 0: the pixel's own depth). ``visibility_restoration`` false: no restoration, the view selection
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
    highlight_corrected, highlight_skip_strong, highlight_drop_centre, highlight_source_invisible : bool
        Paper section 3.5, "Highlight Perception Capacity"; they act only on views with a highlight mask (a
        ``highlight`` provider other than ``none``). ``highlight_corrected``: the corrector's images replace the
        originals for matching (edges and fused colours keep the originals). ``highlight_skip_strong``: a strong
        (reliable) pixel in the reference's highlight is not reconstructed from this view (depth 0: left to
        views that see no highlight there) and is no anchor. ``highlight_drop_centre``: a weak pixel there
        matches with its anchors' windows only, eq. 3's centre term dropped. ``highlight_source_invisible``: a
        source is counted invisible for an anchor whose point lands in that source's highlight (with
        ``anchor_visibility`` off, only these sources are left out of an anchor's windows).
    highlight_multiview, highlight_multiview_excess, highlight_multiview_tolerance : bool or float
        Before the geometric pass, every view's highlight mask is joined with the multi-view evidence of the
        photometric maps (``dvpmvs.highlight.multiview_highlight``: brighter by at least
        ``highlight_multiview_excess`` than the darkest source whose depth agrees within
        ``highlight_multiview_tolerance``, relative), and its corrected image takes that source's level there.
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
    image_noise_scale: float = 2.0  # ... flat: texture within this many times the estimated noise
    # give up hypotheses that cannot win (same maps; false: score every one fully)
    early_stop: bool = True

    # -- photometric pass: pyramid levels, iterations, upsampling between levels --
    num_scales: int = 3  # pyramid levels of the photometric pass (coarse to fine)
    min_scale_size: int = 160  # no level with a longer side under this
    num_iterations: int = 1  # red-black iterations per level (photometric pass)
    # a pixel leaves a plane handed over from the level below only for one this much cheaper (0: freely)
    restore_margin: float = 0.1

    # -- geometric pass --
    geom_iterations: int = 1  # red-black iterations of the geometric pass
    geom_weight: float = 0.2  # cost += geom_weight * min(reprojection error, geom_max_error)
    geom_max_error: float = 3.0  # pixels

    # -- view selection (eq. 2, ACMMP's) --
    max_sources: int = 10  # source views per reference (best ranked first)

    # -- hypotheses: random draws, sparse seeding, refinement --
    # propagation / refinement / prior planes may leave the view's depth range by this factor (random
    # draws stay in it); .inf: unbounded, as COLMAP
    range_slack: float = float("inf")
    sparse_seed: bool = True  # the coarsest level also tries the sparse points' triangulated planes
    # refinement: relative perturbation at the first iteration (ACMM's), halved each one
    perturbation: float = 0.02
    min_perturbation: float = 0.005

    # -- filtering of the final maps --
    # estimates with a higher final cost are removed (unless on the planar prior)
    filter_max_cost: float = 1.0
    filter_min_region: int = 20  # connected depth regions smaller than this (pixels) are removed

    # -- planar prior (ACMMP's) --
    planar_prior: bool = True  # planar prior from triangulated reliable pixels (ACMMP's idea)
    prior_iterations: int = 2  # extra full-resolution iterations with the prior (photometric pass)
    # no prior from triangles whose 3 support pixels are in different regions
    prior_regions: bool = True

    # -- deformable PatchMatch (eq. 3) --
    deformable: bool = True  # deformable PatchMatch (paper eq. 3) after the first estimate
    geom_deformable: bool = True  # ... and in the geometric pass (false: plain there, faster)
    deform_centre_step: int = 5  # the deformed pixel's own 11x11 window is sampled every 5 pixels
    deform_anchor_step: int = 2  # each anchor's 11x11 window every 2 pixels

    # -- strong pixels and the anchor search (section 3.4, eq. 12) --
    strong_max_cost: float = 0.3  # strong (reliable) pixel: cost <= this ...
    min_anchors: int = 2  # weak pixels with fewer anchors keep the plain window
    anchor_min_distance: int = 3  # anchor search: from this distance (pixels) ...
    # ... to this fraction of the longer image side (1: the whole image) ...
    anchor_max_distance: float = 1.0
    anchor_step: int = 2  # ... in steps of this many pixels
    # paper eq. 12: each sector's anchor the candidate that most grows the anchors' area
    area_maximisation: bool = False

    # -- planes through anchors (APD-MVS's) --
    anchor_plane: bool = True  # weak pixels also try the plane through 3 anchors around them ...
    # APD-MVS rule: keep only the anchors on that plane (none without one)
    anchor_coplanar: bool = False

    # -- anchor visibility (section 3.4, eq. 10-11) --
    # match an anchor's window only in the sources it is visible in (paper 3.4)
    anchor_visibility: bool = True
    # ... its selected sources, and in the geometric pass those it reprojects into within this many pixels
    # (forward-backward), ...
    visibility_max_error: float = 2.0
    # ... with the depth of the lowest-cost pixel this near the projection (0: its own)
    visibility_restore_radius: int = 5
    # false: no restoration, visibility from view selection alone (paper's w/o Res)
    visibility_restoration: bool = True

    # -- geometry-driven refinement (section 3.5): normal and depth aggregation --
    normal_aggregation: bool = False  # paper 3.5: no plane a selected source would see from behind
    # paper 3.5: perturbed depths move the point along the sources' epipolar lines
    depth_aggregation: bool = False

    # -- highlight perception (section 3.5) --
    highlight_corrected: bool = True  # match the corrector's images instead of the originals
    # a strong pixel in the reference's highlight is left to other views
    highlight_skip_strong: bool = True
    # a weak one matches with its anchors' windows only (eq. 3 without its centre term)
    highlight_drop_centre: bool = True
    # an anchor is not matched in a source whose highlight its point lands in
    highlight_source_invisible: bool = True
    # geometric pass: masks joined with the views' disagreement (a highlight moves) ...
    highlight_multiview: bool = True
    # ... brighter than the darkest view that sees the point by this much ...
    highlight_multiview_excess: float = 0.06
    # ... a view sees it when its photometric depth agrees within this (relative)
    highlight_multiview_tolerance: float = 0.01

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
        check(
            self.image_noise_scale >= 0,
            f"image_noise_scale must be >= 0, got {self.image_noise_scale}",
        )
        check(self.num_scales >= 1, f"num_scales must be >= 1, got {self.num_scales}")
        check(self.min_scale_size >= 16, f"min_scale_size must be >= 16, got {self.min_scale_size}")
        check(self.num_iterations >= 1, f"num_iterations must be >= 1, got {self.num_iterations}")
        check(
            0 <= self.restore_margin <= 2,
            f"restore_margin must be in [0, 2] (a cost), got {self.restore_margin}",
        )
        check(
            self.geom_iterations >= 1, f"geom_iterations must be >= 1, got {self.geom_iterations}"
        )
        check(
            self.geom_weight >= 0 and self.geom_max_error > 0,
            "geom_weight must be >= 0, geom_max_error > 0",
        )
        check(
            0 < self.min_perturbation <= self.perturbation < 1,
            "need 0 < min_perturbation <= perturbation < 1",
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
        check(1 <= self.min_anchors <= 8, f"min_anchors must be in [1, 8], got {self.min_anchors}")
        check(
            self.anchor_min_distance >= 1 and self.anchor_step >= 1,
            "anchor_min_distance and anchor_step must be >= 1",
        )
        check(
            0 < self.anchor_max_distance <= 1,
            "anchor_max_distance is a fraction of the longer image side, in (0, 1]",
        )
        check(
            0 < self.visibility_max_error < self.geom_max_error,
            "visibility_max_error must be in (0, geom_max_error): the reprojection error is clipped there",
        )
        check(
            self.visibility_restore_radius >= 0,
            f"visibility_restore_radius must be >= 0, got {self.visibility_restore_radius}",
        )
        check(
            0 < self.highlight_multiview_excess < 1,
            f"highlight_multiview_excess must be in (0, 1) (grey levels), got {self.highlight_multiview_excess}",
        )
        check(
            0 < self.highlight_multiview_tolerance < 1,
            f"highlight_multiview_tolerance must be in (0, 1), got {self.highlight_multiview_tolerance}",
        )
        check(self.range_slack >= 1, f"range_slack must be >= 1, got {self.range_slack}")
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
