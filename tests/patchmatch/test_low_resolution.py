"""low_resolution_depth (dvpmvs/patchmatch/low_resolution.py): the photometric pass on downscaled views."""

import numpy as np
import pytest

from dvpmvs.options import PatchMatchOptions
from dvpmvs.patchmatch.low_resolution import low_resolution_depth
from tests.plane_scenes import plane_scene


def _within(depth, truth, tolerance=0.02):
    """The share of the pixels whose depth is within ``tolerance`` of the truth (sampled at nearest)."""
    h, w = depth.shape
    rows = (np.arange(h) + 0.5) * truth.shape[0] / h
    cols = (np.arange(w) + 0.5) * truth.shape[1] / w
    sampled = truth[rows.astype(int)[:, None], cols.astype(int)[None, :]]
    return np.mean(np.abs(depth - sampled) / sampled < tolerance)


def test_the_depth_is_the_downscaled_views_and_recovers_the_plane():
    problem, truth, _ = plane_scene(num_sources=2)
    depth = low_resolution_depth(
        problem, None, max_size=40, num_scales=1, num_iterations=3, max_cost=0.5, max_sources=2
    )
    assert depth.shape == (30, 40) and depth.dtype == np.float32  # the 80x60 reference at half size
    assert _within(depth, truth) > 0.65, _within(
        depth, truth
    )  # measured 0.691 (77 % of the pixels estimated)
    # Views no larger than max_size are matched at their own size.
    full = low_resolution_depth(
        problem, None, max_size=200, num_scales=1, num_iterations=3, max_cost=0.5, max_sources=1
    )
    assert full.shape == truth.shape and _within(full, truth) > 0.78  # measured 0.834
    # With the views matched at half their size (a resolution level), the prior shrinks with them.
    scaled = low_resolution_depth(
        problem,
        None,
        max_size=80,
        num_scales=1,
        num_iterations=3,
        max_cost=0.5,
        max_sources=2,
        size_scale=0.5,
    )
    assert np.array_equal(scaled, depth)


def test_a_stricter_cost_bound_removes_estimates_and_the_runs_seed_is_kept():
    problem, _, _ = plane_scene(num_sources=2)
    args = dict(max_size=40, num_scales=1, num_iterations=3, max_sources=2)
    loose = low_resolution_depth(problem, None, max_cost=0.5, **args)
    strict = low_resolution_depth(problem, None, max_cost=0.05, **args)
    assert (strict > 0).sum() < (loose > 0).sum()  # measured 890 of 928
    seeded = [
        low_resolution_depth(problem, PatchMatchOptions(seed=seed), max_cost=0.5, **args)
        for seed in (0, 0, 1)
    ]
    assert np.array_equal(seeded[0], seeded[1]) and not np.array_equal(seeded[0], seeded[2])


def test_an_empty_source_list_is_the_problems_error():
    problem, _, _ = plane_scene(num_sources=2)
    with pytest.raises(ValueError, match="has no source views"):
        low_resolution_depth(
            problem, None, max_size=40, num_scales=1, num_iterations=1, max_cost=0.5, max_sources=0
        )
