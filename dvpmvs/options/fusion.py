"""Options of depth-map fusion (:mod:`dvpmvs.fusion`; COLMAP's ``StereoFusionOptions``)."""

from __future__ import annotations

from dataclasses import dataclass

from dvpmvs.passes import Pass
from dvpmvs.validation import check_field_types, check_threads

__all__ = ["FusionOptions"]


_MAX_NEIGHBOURS = 64


@dataclass(frozen=True)
class FusionOptions:
    """Depth-map fusion, as COLMAP's ``StereoFusionOptions``.

    Parameters
    ----------
    min_consistent_views : int
        Other views that must agree with a pixel (COLMAP's ``min_num_pixels`` is this + 1).
    max_reproj_error, max_depth_error, max_normal_error : float
        Agreement: in pixels, relative depth and degrees.
    input_type : str
        Which maps to fuse (``photometric`` or ``geometric``).
    max_neighbours : int
        Neighbours checked per view (the best-ranked sources).
    cache_views : int
        Maps held in memory at once.
    num_threads : int
        0 uses every core.
    colmap_max_reproj_error : float
        The reprojection threshold handed to COLMAP's fusion. COLMAP merges every pixel within this radius of
        the reference projection into one point, so its 2 px default thins the cloud several times over against
        ours and costs completeness at 2 cm; 0.5 px keeps it as dense as ours (on the synthetic facade, F1 at 2 cm
        far higher).
    point_average : str
        How the agreeing pixels' points make the fused point: ``median`` (per coordinate, as COLMAP's fusion
        does) or ``mean``. The 1 % depth tolerance lets points up to 1 % off into the average, and the median
        ignores them: re-fusing the default configuration's 800x600 maps of the synthetic suite, the median
        scored higher at 2 cm, most on the facade (10-20 m away). Normals and colours are averaged either way.
    allow_missing : bool
        Fuse even when some views that have sources have no maps (a partial cloud, as COLMAP's
        ``--PatchMatchStereo.allow_missing_files``); by default that is an error, so that a cloud never silently
        lacks views. The cloud's record lists the views it was fused without.
    """

    # other views that must agree with a pixel (COLMAP: min_num_pixels = this + 1)
    min_consistent_views: int = 2
    max_reproj_error: float = 2.0  # pixels, forward-backward
    max_depth_error: float = 0.01  # relative
    max_normal_error: float = 30.0  # degrees
    input_type: str = "geometric"
    max_neighbours: int = 20  # neighbour views checked per view (best-ranked sources)
    cache_views: int = 32  # views whose maps are held in memory at once (dvpmvs fusion)
    num_threads: int = 0
    # fusion=colmap: COLMAP merges pixels within this radius into one point
    colmap_max_reproj_error: float = 0.5
    # the fused point from the agreeing pixels' points: median (COLMAP's) | mean
    point_average: str = "median"
    # fuse even when views with sources have no maps (a partial cloud, said so)
    allow_missing: bool = False
    # the mask provider's config (dvpmvs.masks): masked pixels neither start nor join a point
    mask: dict | None = None

    def __post_init__(self):
        check_field_types(self, "fusion_options.")
        if self.min_consistent_views < 1:
            raise ValueError(f"min_consistent_views must be >= 1, got {self.min_consistent_views}")
        if not (
            self.max_reproj_error > 0
            and self.max_depth_error > 0
            and 0 < self.max_normal_error <= 180
            and self.colmap_max_reproj_error > 0
        ):
            raise ValueError(
                "max_reproj_error, colmap_max_reproj_error and max_depth_error must be > 0, "
                "max_normal_error in (0, 180]"
            )
        Pass(self.input_type)  # ValueError names the bad value
        if not 1 <= self.max_neighbours <= _MAX_NEIGHBOURS:
            raise ValueError(
                f"max_neighbours must be in [1, {_MAX_NEIGHBOURS}], got {self.max_neighbours}"
            )
        if self.cache_views < 2:
            raise ValueError(f"cache_views must be >= 2, got {self.cache_views}")
        check_threads("num_threads", self.num_threads)
        if self.point_average not in ("median", "mean"):
            raise ValueError(
                f"point_average must be 'median' or 'mean', got {self.point_average!r}"
            )
