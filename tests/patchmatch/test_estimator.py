"""The estimator (``estimator.py``) on rendered planes: recovery, determinism, the pyramid, the
stage observer, flat pixels and the geometric pass."""

import numpy as np
import pytest

from dvpmvs.maps import Pass
from dvpmvs.patchmatch import (
    PatchMatchOptions,
    Problem,
    ViewData,
    estimate,
    pyramid_sizes,
    scale_intrinsics,
    upsample_planes,
)
from tests.plane_scenes import K, depth_of_plane, kernel_state, plain_wall_scene, plane_scene

# Also run on the other Pythons `make test` checks (scripts/other_pythons.py).
pytestmark = pytest.mark.smoke


def test_pyramid_sizes():
    assert pyramid_sizes(800, 600, 3, 160) == [(200, 150), (400, 300), (800, 600)]
    assert pyramid_sizes(320, 240, 3, 160) == [(160, 120), (320, 240)]
    assert pyramid_sizes(100, 80, 3, 160) == [(100, 80)]


def test_upsampling_keeps_a_slanted_plane():
    problem, plane_depth, normals = plane_scene()
    K_coarse = scale_intrinsics(K, 0.5, 0.5)
    rows, cols = np.mgrid[0:30, 0:40]
    n = normals[0, 0].astype(np.float64)
    corner = plane_depth[0, 0] * np.linalg.inv(K) @ np.array([0, 0, 1.0])
    coarse_depth = depth_of_plane(K_coarse, n, corner, rows, cols).astype(np.float32)
    depth, normal = upsample_planes(
        coarse_depth, normals[:30, :40], K_coarse, problem.reference.image, K
    )
    np.testing.assert_allclose(depth, plane_depth, rtol=1e-4)
    np.testing.assert_allclose(normal, normals, atol=1e-5)


def test_estimator_recovers_the_plane_and_is_thread_independent():
    problem, plane_depth, _ = plane_scene(num_sources=3)
    options = PatchMatchOptions(
        num_scales=1, num_iterations=4, seed=3, num_threads=1, filter_min_region=0
    )
    one = estimate(problem, options)
    two = estimate(problem, PatchMatchOptions(**{**options.as_dict(), "num_threads": 2}))
    for a, b in (
        (one.depth, two.depth),
        (one.normal, two.normal),
        (one.cost, two.cost),
        (one.visibility, two.visibility),
    ):
        assert np.array_equal(a, b)
    inner = np.zeros(plane_depth.shape, bool)
    inner[8:-8, 8:-8] = True  # sources see the centre of the plane
    rel = np.abs(one.depth - plane_depth) / plane_depth
    assert (rel[inner] < 0.01).mean() > 0.9
    assert one.visibility.shape == (60, 80, 3)
    # What it matched, counted per level, the same on any number of threads: 4 iterations of
    # 8 propagated and a few refined hypotheses per pixel (measured: 75.1), each against at most
    # 3 sources (early stops: 2.5 windows per hypothesis on the vector path, 2.3 on the scalar
    # one), 33 samples per window (36 in an 11x11 window every 2 pixels, fewer at the borders).
    assert one.work == two.work and len(one.work) == 1
    work = one.work[0].per_pixel()
    assert (
        70 < work["hypotheses"] < 80
        and 2.0 * work["hypotheses"] < work["windows"] < 3 * work["hypotheses"]
    )
    assert 30 * work["windows"] < work["samples"] < 36 * work["windows"]
    assert one.hypothesis_evaluations == one.work[0].windows


def test_stage_observer_sees_every_level_and_changes_no_map():
    from dvpmvs.patchmatch.estimator import observe_stages, unobserved

    problem, _, _ = plane_scene(num_sources=2)
    options = PatchMatchOptions(
        num_scales=2, min_scale_size=32, num_iterations=2, seed=1, num_threads=1
    )
    plain = estimate(problem, options)
    seen = []
    with observe_stages(
        lambda stage, depth, K: seen.append((stage.level, depth.shape, stage.name))
    ):
        observed = estimate(problem, options)
        with unobserved():  # a depth prior's own estimate
            estimate(problem, options)
    assert np.array_equal(plain.depth, observed.depth) and np.array_equal(
        plain.normal, observed.normal
    )
    assert seen == [
        (0, (30, 40), "propagation"),
        (1, (60, 80), "start"),
        (1, (60, 80), "propagation"),
        (1, (60, 80), "prior"),
        (1, (60, 80), "filtered"),
    ]
    estimate(problem, options)  # outside the block: no observer called
    assert len(seen) == 5


def test_estimator_rejects_bad_problems():
    problem, _, _ = plane_scene()
    bad = problem.reference.image.copy()
    bad[3, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        ViewData("x", bad, K, np.eye(3), np.zeros(3))
    with pytest.raises(ValueError, match="cost map"):
        ViewData("x", problem.reference.image, K, np.eye(3), np.zeros(3), cost=np.zeros((3, 3)))
    costs = np.full(problem.reference.shape, np.nan)
    assert np.isinf(
        ViewData("x", problem.reference.image, K, np.eye(3), np.zeros(3), cost=costs).cost
    ).all()
    with pytest.raises(ValueError, match="no source views"):
        Problem(problem.reference, [], (1, 2))
    with pytest.raises(ValueError, match="depth range"):
        Problem(problem.reference, problem.sources, (2, 1))
    with pytest.raises(ValueError, match="photometric estimate"):
        estimate(problem, PatchMatchOptions(), Pass.GEOMETRIC)


def test_estimator_with_deformation_and_regions_is_deterministic():
    problem, depth, normal = plane_scene(num_sources=2)
    problem.labels = np.ones(problem.reference.shape, np.int32)
    options = PatchMatchOptions(num_scales=1, num_iterations=2, seed=5, strong_max_cost=0.05)
    one = estimate(problem, PatchMatchOptions(**{**options.as_dict(), "num_threads": 1}))
    two = estimate(problem, PatchMatchOptions(**{**options.as_dict(), "num_threads": 2}))
    assert one.deformed is not None and one.deformed.any()
    assert np.array_equal(one.depth, two.depth)
    valid = one.depth > 0
    assert np.median(np.abs(one.depth[valid] - depth[valid]) / depth[valid]) < 0.01


def test_geometric_pass_deforms_only_with_geom_deformable():
    problem, depth, normal = plane_scene(num_sources=2)
    problem.labels = np.ones(problem.reference.shape, np.int32)
    options = PatchMatchOptions(
        num_scales=1, num_iterations=2, seed=5, strong_max_cost=0.05, num_threads=2
    )
    photometric = estimate(problem, options)
    # Source maps only so that the geometric pass runs (the reference's, not consistent with the
    # sources' poses): this checks the deformation switch, not the reprojection term.
    for src in problem.sources:
        src.depth = photometric.depth
    problem.initial = (photometric.depth, photometric.normal)
    deformed = estimate(problem, options, Pass.GEOMETRIC)
    plain = estimate(
        problem,
        PatchMatchOptions(**{**options.as_dict(), "geom_deformable": False}),
        Pass.GEOMETRIC,
    )
    assert deformed.deformed is not None and deformed.deformed.any()
    assert plain.deformed is None
    # Weak pixels match up to 8 anchor windows more (1.9x the evaluations on this plane).
    assert deformed.hypothesis_evaluations > 1.5 * plain.hypothesis_evaluations
    valid = plain.depth > 0
    assert valid.mean() > 0.5
    assert np.median(np.abs(plain.depth[valid] - depth[valid]) / depth[valid]) < 0.01


def test_the_detail_restorer_lets_a_pixel_leave_its_handed_plane_only_for_a_cheaper_one():
    # ACMM's detail restorer: after a hand-over, a pixel takes a new plane only if its cost beats
    # the handed plane's cost at this level by the margin; else it keeps the handed plane.
    from dvpmvs.patchmatch import _patchmatch
    from dvpmvs.patchmatch.estimator import _kernel_params, _Level

    problem, plane_depth, normals = plane_scene(num_sources=3)
    level = _Level.build(problem, 1.0, use_depth=False)
    params = _kernel_params(problem, PatchMatchOptions())
    handed = kernel_state(
        plane_depth * np.float32(1.02), normals.copy(), 3
    )  # 2 % off the true plane
    _patchmatch.initialise(level.views, handed, params, False, 4, 1)
    handed_cost = handed.cost.copy()
    moved = {}
    for margin in (2.0, 0.1, 0.0):
        state = handed.copy()
        _patchmatch.sweep(
            level.views,
            state,
            params.replace(restore_margin=margin),
            0,
            1,
            handed_cost=handed_cost,
        )
        moved[margin] = state.depth != handed.depth
        # Whoever moved beat the handed plane's cost by the margin.
        assert (state.cost[moved[margin]] < handed_cost[moved[margin]] - margin).all()
    assert not moved[2.0].any()  # no cost is under 0
    assert 0.05 < moved[0.1].mean() < moved[0.0].mean()
    # Where no plane was handed over (inf) nothing is held back: the maps of a sweep without it.
    free, unrestored = handed.copy(), handed.copy()
    _patchmatch.sweep(
        level.views,
        free,
        params.replace(restore_margin=2.0),
        0,
        1,
        handed_cost=np.full(plane_depth.shape, np.inf, np.float32),
    )
    _patchmatch.sweep(level.views, unrestored, params, 0, 1)
    for a, b in zip(free, unrestored):
        assert np.array_equal(a, b)
    assert (free.depth != handed.depth).mean() > moved[0.0].mean()


def test_the_detail_restorer_keeps_the_coarse_plane_of_a_plain_wall(monkeypatch):
    # A wall whose unevenness is under the noise pixel by pixel, over it once averaged 2x2: the
    # coarse level finds its plane, which full-resolution noise replaces without the margin
    # (ACMM's constant, RESTORE_MARGIN, set to 0 for the comparison).
    from dvpmvs.patchmatch import estimator

    problem, truth, plain = plain_wall_scene()
    options = PatchMatchOptions(
        num_iterations=3,
        num_scales=2,
        min_scale_size=16,
        num_threads=2,
        filter_min_region=0,
        deformable=False,
        planar_prior=False,
    )
    shares = {}
    assert estimator.RESTORE_MARGIN == 0.1
    for margin in (0.0, 0.1):
        monkeypatch.setattr(estimator, "RESTORE_MARGIN", margin)
        result = estimate(problem, options)
        right = (result.depth > 0) & (np.abs(result.depth - truth) <= 0.01 * truth)
        textured = ~plain
        textured[:, :8] = False
        shares[margin] = (right[plain].mean(), right[textured].mean())
    assert (
        shares[0.0][0] < 0.34 and shares[0.1][0] > shares[0.0][0] + 0.07
    )  # measured: 31.5 -> 41.4 %
    assert shares[0.1][1] > shares[0.0][1] - 0.005 and shares[0.1][1] > 0.94  # textured: 95.6 %
