"""The estimator's photometric pass on a view at low resolution: the depth a weight-free prior
(``coarse_mvs``) starts from, offered to prior providers through
:attr:`dvpmvs.priors.PriorContext.low_resolution_depth` so that they need not know the estimator."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from dvpmvs.geometry import scale_intrinsics
from dvpmvs.options.patch_match import PatchMatchOptions
from dvpmvs.patchmatch.estimator import estimate, unobserved
from dvpmvs.patchmatch.problem import Problem, ViewData

__all__ = ["low_resolution_depth"]


def low_resolution_depth(
    problem: Problem,
    options: PatchMatchOptions | None,
    max_size: int,
    num_scales: int,
    num_iterations: int,
    max_cost: float,
    max_sources: int,
    size_scale: float = 1.0,
) -> np.ndarray:
    """The filtered photometric depth (0: none) of ``problem``'s reference, every image
    downscaled so that the reference's longer side is at most ``max_size`` x ``size_scale``
    (``max_size`` is given for the images at resolution level 0, and ``size_scale`` is
    ``Workspace.resolution_scale``: with a ``resolution_level`` the prior shrinks with the
    images it serves, so that it keeps its share of the work), matched against its
    first ``max_sources`` sources with ``num_scales`` pyramid levels of ``num_iterations``
    iterations, a planar prior and no deformation; estimates costlier than ``max_cost`` removed.
    The other estimator options are ``options``' (the run's)."""
    h, w = problem.reference.shape
    factor = min(1.0, max_size * size_scale / max(h, w))

    def small(view: ViewData) -> ViewData:
        vh, vw = view.shape
        size = (max(8, round(vw * factor)), max(8, round(vh * factor)))
        image = (
            cv2.resize(view.image, size, interpolation=cv2.INTER_AREA) if factor < 1 else view.image
        )
        K = scale_intrinsics(view.K, size[0] / vw, size[1] / vh)
        return ViewData(view.name, image, K, view.R, view.t)

    sources = problem.sources[:max_sources]
    coarse = Problem(
        small(problem.reference),
        [small(v) for v in sources],
        problem.depth_range,
        sparse_points=problem.sparse_points,
    )
    base = options or PatchMatchOptions()
    options = replace(
        base,
        num_scales=num_scales,
        num_iterations=num_iterations,
        filter_max_cost=max_cost,
        max_sources=len(sources),
        planar_prior=True,
        deformable=False,
        min_scale_size=16,
    )
    with unobserved():  # a prior's own estimate, not the view's
        return estimate(coarse, options).depth
