"""The PatchMatch estimator (ACMH/ACMM class) behind COLMAP's MVSEstimator contract."""

from dvpmvs.geometry import scale_intrinsics
from dvpmvs.options.patch_match import PatchMatchOptions
from dvpmvs.patchmatch.estimator import (
    estimate,
    filter_estimate,
    hypothesis_costs,
    pyramid_sizes,
    upsample_planes,
)
from dvpmvs.patchmatch.problem import Problem, Result, ViewData

__all__ = [
    "estimate",
    "hypothesis_costs",
    "filter_estimate",
    "pyramid_sizes",
    "scale_intrinsics",
    "upsample_planes",
    "PatchMatchOptions",
    "Problem",
    "Result",
    "ViewData",
]
