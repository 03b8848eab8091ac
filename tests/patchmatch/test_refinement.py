"""Refinement (``_refinement.pxd``): section 3.5's normal and depth aggregation, random hypotheses
and the search range."""

from dataclasses import replace

import numpy as np
import pytest

from dvpmvs.patchmatch import PatchMatchOptions, Problem, ViewData, _patchmatch, estimate
from tests.plane_scenes import (
    kernel_state,
    plane_scene,
    random_texture,
    rays_through,
    rotation_about,
)


def test_random_numbers_are_counter_based():
    a = _patchmatch.random_uniform(7, 1234, 3, 10000)
    assert np.array_equal(a, _patchmatch.random_uniform(7, 1234, 3, 10000))
    assert not np.array_equal(a, _patchmatch.random_uniform(8, 1234, 3, 10000))
    assert not np.array_equal(a, _patchmatch.random_uniform(7, 1235, 3, 10000))
    assert 0 <= a.min() and a.max() < 1 and abs(a.mean() - 0.5) < 0.01


def _geometry_scene(seed=0):
    """A reference camera and 4 sources with baselines of 0.2-0.8 at 4-6 m and a focal length
    of 700 px, so that every epipolar line runs far beyond 5 px on both sides of each point;
    random depths and normals facing the reference camera."""
    rng = np.random.default_rng(seed)
    h, w = 30, 40
    K700 = np.array([[700.0, 0, 19.5], [0, 700.0, 14.5], [0, 0, 1]])
    image = random_texture((h, w), seed)
    sources = [
        ViewData(
            f"s{j}",
            image,
            K700,
            rotation_about((0.1, 1, 0.3), (-1) ** j * 2.0 * (j + 1)),
            np.array([0.2 * (j + 1) * (-1) ** j, 0.1 * j, 0.05]),
        )
        for j in range(4)
    ]
    problem = Problem(ViewData("ref", image, K700, np.eye(3), np.zeros(3)), sources, (2.0, 8.0))
    depth = rng.uniform(4.0, 6.0, (h, w)).astype(np.float32)
    normal = rng.normal(size=(h, w, 3))
    normal[..., 2] = -np.abs(normal[..., 2]) - 0.2
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return problem, depth, normal.astype(np.float32), K700


def _geometry_constraints(problem, depth, normal, selected, **params):
    from dvpmvs.patchmatch.estimator import _kernel_params, _Level

    h, w = depth.shape
    S = len(problem.sources)
    level = _Level.build(problem, 1.0, use_depth=False)
    state = kernel_state(depth, normal, S, selected)
    intervals = np.zeros((h, w, 4), np.float32)
    facing = np.zeros((h, w), np.uint8)
    _patchmatch.geometry_constraints(
        level.views,
        state,
        _kernel_params(problem, PatchMatchOptions()).replace(**params),
        intervals,
        facing,
        2,
    )
    return intervals, facing


def test_depth_aggregation_intervals_move_the_point_along_the_epipolar_lines():
    """Paper section 3.5 (NumPy reference): the near and far intervals are those of the mu-th
    most sensitive selected source on each side. At an inner end at least mu of the pixel's
    selected sources move its point by >= alpha px along their epipolar lines, one of them by
    exactly alpha; at an outer end that one moves it by alpha + beta, and at least (sources -
    mu + 1) by <= alpha + beta."""
    problem, depth, normal, K700 = _geometry_scene()
    h, w = depth.shape
    rng = np.random.default_rng(1)
    selected = rng.integers(0, 16, (h, w)).astype(np.uint32)
    alpha, outer, mu = 1.5, 6.0, 2
    intervals, _ = _geometry_constraints(
        problem,
        depth,
        normal,
        selected,
        aggregation_inner=alpha,
        aggregation_outer=outer,
        aggregation_views=mu,
    )
    rows, cols = np.mgrid[0:h, 0:w]
    rays = rays_through(K700, rows, cols)

    def moved(t):  # (h, w, 4): how far source j sees the point move from depth to depth t
        out = np.zeros((h, w, 4))
        for j, src in enumerate(problem.sources):

            def project(z):
                q = (z[..., None] * rays) @ src.R.T + src.t
                q = q @ K700.T
                return q[..., :2] / q[..., 2:]

            out[..., j] = np.linalg.norm(
                project(t.astype(np.float64)) - project(depth.astype(np.float64)), axis=-1
            )
        return out

    count = np.stack([(selected >> j) & 1 for j in range(4)], -1).astype(bool)
    none = count.sum(-1) == 0
    assert np.all(intervals[none] == 0)
    has = ~none
    near_lo, near_hi, far_lo, far_hi = (intervals[..., k] for k in range(4))
    assert np.all(
        (near_lo < near_hi)[has]
        & (near_hi < depth)[has]
        & (depth < far_lo)[has]
        & (far_lo < far_hi)[has]
    )
    mu_ = np.minimum(mu, count.sum(-1))
    for inner, outer_end in ((near_hi, near_lo), (far_lo, far_hi)):
        m_in, m_out = moved(np.where(has, inner, depth)), moved(np.where(has, outer_end, depth))
        assert np.all((((m_in >= alpha - 1e-2) & count).sum(-1) >= mu_)[has])
        assert np.all((((m_out <= outer + 1e-2) & count).sum(-1) >= count.sum(-1) - mu_ + 1)[has])
        # One source, the same at both ends, moves by exactly alpha and alpha + beta.
        assert np.all(
            ((np.abs(m_in - alpha) < 1e-2) & (np.abs(m_out - outer) < 1e-2) & count).any(-1)[has]
        )


def test_normal_aggregation_keeps_planes_that_face_every_selected_source():
    """A plane faces a source when n . (P - C_j) <= 0 (NumPy reference, the sources' centres
    from their poses); only the selected sources count."""
    problem, depth, normal, K700 = _geometry_scene(seed=2)
    h, w = depth.shape
    # Planes seen at grazing angles from the reference camera, so that the sources' few degrees
    # of parallax put some of them behind.
    normal[..., 2] = -np.random.default_rng(4).uniform(0.0, 0.2, (h, w))
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    selected = np.random.default_rng(3).integers(0, 16, (h, w)).astype(np.uint32)
    _, facing = _geometry_constraints(problem, depth, normal, selected)
    rows, cols = np.mgrid[0:h, 0:w]
    points = depth[..., None] * rays_through(K700, rows, cols)
    dots = np.stack(
        [np.sum(normal * (points + src.R.T @ src.t), -1) for src in problem.sources], -1
    )
    chosen = np.stack([(selected >> j) & 1 for j in range(4)], -1).astype(bool)
    expected = np.all(~chosen | (dots <= 0), -1)
    clear = np.all(np.abs(dots) > 1e-4, -1)
    assert np.array_equal(facing.astype(bool)[clear], expected[clear])
    assert 0.2 < expected.mean() < 0.9  # the random normals face some sources and not others


@pytest.mark.parametrize("switch", ["normal_aggregation", "depth_aggregation"])
def test_estimator_with_geometry_driven_refinement_is_deterministic_and_accurate(switch):
    problem, depth, normal = plane_scene(num_sources=3)
    problem.labels = np.ones(problem.reference.shape, np.int32)
    options = PatchMatchOptions(
        num_scales=1, num_iterations=2, seed=5, strong_max_cost=0.05, **{switch: True}
    )
    one, two = (
        estimate(problem, PatchMatchOptions(**{**options.as_dict(), "num_threads": t}))
        for t in (1, 2)
    )
    assert np.array_equal(one.depth, two.depth) and np.array_equal(one.normal, two.normal)
    plain = estimate(problem, PatchMatchOptions(**{**options.as_dict(), switch: False}))
    if switch == "normal_aggregation":  # planes the sources would see from behind go unscored
        assert one.hypothesis_evaluations < plain.hypothesis_evaluations
    else:  # other perturbed depths
        assert not np.array_equal(one.depth, plain.depth)
    valid = one.depth > 0
    assert valid.mean() > 0.5
    assert np.median(np.abs(one.depth[valid] - depth[valid]) / depth[valid]) < 0.01


def test_propagation_leaves_the_sparse_depth_range():
    # A slanted plane whose far half lies beyond the view's depth range (as a surface without
    # sparse points does): random hypotheses start inside the range, and propagation and
    # refinement carry the plane past its end (as COLMAP, which bounds only its random draws).
    problem, plane_depth, _ = plane_scene(num_sources=3, normal=(0.5, -0.1, -1.0))
    hi = float(np.median(plane_depth))
    problem = Problem(problem.reference, problem.sources, (0.9 * float(plane_depth.min()), hi))
    inner = np.zeros(plane_depth.shape, bool)
    inner[8:-8, 8:-8] = True
    far = inner & (plane_depth > 1.02 * hi)
    assert far.sum() > 1000

    options = PatchMatchOptions(
        num_scales=1, num_iterations=4, seed=3, num_threads=2, filter_min_region=0
    )
    depth = estimate(problem, options).depth
    right = np.abs(depth - plane_depth) / plane_depth < 0.01
    assert right[far].mean() > 0.8 and right[inner & ~far].mean() > 0.95


def test_random_depths_spread_uniformly_in_depth():
    # Over the range [1, 10], half the random draws lie below 5.5.
    from dvpmvs.patchmatch.estimator import _kernel_params

    problem, _, _ = plane_scene()
    problem = replace(problem, depth_range=(1.0, 10.0))
    h, w = problem.reference.image.shape[:2]
    depth = np.zeros((h, w), np.float32)
    normal = np.zeros((h, w, 3), np.float32)
    _patchmatch.random_hypotheses(
        problem.reference.K, depth, normal, _kernel_params(problem, PatchMatchOptions()), 1
    )
    assert 1.0 <= depth.min() and depth.max() <= 10.0
    assert abs(np.median(depth) - 5.5) < 0.05 * 5.5
