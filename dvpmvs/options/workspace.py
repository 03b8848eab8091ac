"""Options of the dense workspace (:class:`dvpmvs.workspace.Workspace`): image size, depth ranges, sources."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from dvpmvs.validation import check_field_types

__all__ = ["MIN_IMAGE_SIZE", "WorkspaceOptions"]


MIN_IMAGE_SIZE = 32  # the smallest max_image_size: a few matching windows across


@dataclass(frozen=True)
class WorkspaceOptions:
    """How a workspace is read. Validates itself on construction.

    Parameters
    ----------
    max_image_size : int
        Longest image side after downscaling; <= 0 keeps the original size.
    resolution_level, min_resolution : int
        Match at 1 / 2^level of the largest image's longest side (OpenMVS's ``--resolution-level``), but at
        least ``min_resolution`` pixels (its ``--min-resolution``), never above the images' own size nor
        ``max_image_size``: one limit for every view (``Workspace.max_image_size``), as COLMAP's
        ``max_image_size`` is.
    depth_quantiles : tuple[float, float]
        Lower/upper quantile of the sparse points' depths (COLMAP: 0.01, 0.99).
    depth_margin : float
        The range is stretched to [lo * (1 - m), hi * (1 + m)] (COLMAP: 0.25).
    min_points_for_range : int
        A view observing fewer sparse points gets the fallback range.
    depth_range : tuple[float, float] | None
        A fixed (min, max) for every view, replacing the sparse estimate.
    default_num_sources : int
        Sources per view when ``stereo/patch-match.cfg`` is missing.
    view_selector : Mapping[str, Any]
        Config of the view-selection plugin resolving ``__auto__, N``.
    """

    max_image_size: int = -1  # longest image side after downscaling; -1 keeps the original size
    # match at 1/2^level of the largest image side (OpenMVS's --resolution-level) ...
    resolution_level: int = 0
    min_resolution: int = 640  # ... but at least this many pixels (OpenMVS's --min-resolution)
    depth_quantiles: tuple[float, float] = (
        0.01,
        0.99,
    )  # quantiles of the sparse points' depths (as COLMAP)
    depth_margin: float = 0.25  # the range is stretched by this fraction on both ends (as COLMAP)
    # fewer sparse points: the view gets the scene's range and a warning
    min_points_for_range: int = 3
    # [min, max] for every view instead of the sparse-point estimate
    depth_range: tuple[float, float] | None = None
    default_num_sources: int = 20  # `__auto__, N` used when stereo/patch-match.cfg is missing
    view_selector: Mapping[str, Any] = field(default_factory=lambda: {"name": "colmap_cfg"})

    def __post_init__(self):
        check_field_types(self)
        lo, hi = self.depth_quantiles
        if not 0.0 <= lo < hi <= 1.0:
            raise ValueError(
                f"depth_quantiles must satisfy 0 <= lo < hi <= 1, got {self.depth_quantiles}"
            )
        if not 0.0 <= self.depth_margin < 1.0:
            raise ValueError(f"depth_margin must be in [0, 1), got {self.depth_margin}")
        if self.min_points_for_range < 1:
            raise ValueError(f"min_points_for_range must be >= 1, got {self.min_points_for_range}")
        if self.depth_range is not None:
            dmin, dmax = (float(v) for v in self.depth_range)
            if not (math.isfinite(dmin) and math.isfinite(dmax) and 0.0 < dmin < dmax):
                raise ValueError(
                    f"depth_range must be finite with 0 < min < max, got {self.depth_range}"
                )
        if self.default_num_sources < 1:
            raise ValueError(f"default_num_sources must be >= 1, got {self.default_num_sources}")
        if self.resolution_level < 0:
            raise ValueError(
                f"resolution_level must be >= 0 (0: the images' own size), got {self.resolution_level}"
            )
        if self.min_resolution < MIN_IMAGE_SIZE:
            raise ValueError(
                f"min_resolution must be at least {MIN_IMAGE_SIZE} pixels, got {self.min_resolution}"
            )
        if 0 < self.max_image_size < MIN_IMAGE_SIZE:
            raise ValueError(
                f"max_image_size must be -1 (the images' own size) or at least {MIN_IMAGE_SIZE} "
                f"pixels, got {self.max_image_size}: smaller views leave no room for the "
                f"11x11 matching window and give an empty cloud"
            )
