"""Anchor visibility and its restoration (``_visibility.pxd``, eq. 10-11)."""

import numpy as np
import pytest

from dvpmvs.patchmatch import PatchMatchOptions, _patchmatch, estimate
from dvpmvs.patchmatch.estimator import DEFORM_LAMBDA
from tests.plane_scenes import (
    K,
    kernel_state,
    numpy_cost,
    pixel_rays,
    plane_scene,
    sources_on_the_plane,
)


def test_anchor_visibility_matches_each_window_only_where_its_anchor_is_seen():
    """Paper eq. 10-11: in source j the mean runs over the anchors visible in j; a source that
    sees none of them is judged by the centre window alone; all-visible masks change nothing."""
    problem, depth, normal = plane_scene(num_sources=2)
    h, w = problem.reference.shape
    from dvpmvs.patchmatch.estimator import _kernel_params, _Level

    options = PatchMatchOptions(num_threads=1)
    level = _Level.build(problem, 1.0, use_depth=False)
    S = len(problem.sources)
    wrong = (depth * 1.04).astype(np.float32)
    tilted = normal + np.array([0.3, 0.1, 0.0], np.float32)
    tilted /= np.linalg.norm(tilted, axis=-1, keepdims=True)
    anchors = np.full((h, w, 8), -1, np.int32)
    at = [(30, 50), (20, 40), (30, 28), (42, 41)]
    anchors[30, 40, :4] = [r * w + c for r, c in at]
    params = _kernel_params(problem, options)

    def view_costs(visible):
        state = kernel_state(wrong.copy(), tilted.copy(), S)
        _patchmatch.initialise(level.views, state, params, False, S, 1, anchors, visible)
        return state.view_cost

    visible = np.zeros((h, w), np.uint32)
    for (r, c), mask in zip(at, (0b01, 0b01, 0b11, 0b00)):
        visible[r, c] = mask
    costs = view_costs(visible)[30, 40]
    centre = numpy_cost(problem, wrong, tilted, 30, 40, options, step=options.deform_centre_step)
    windows = np.array(
        [
            numpy_cost(
                problem,
                wrong,
                tilted,
                30,
                40,
                options,
                window_at=a,
                step=options.deform_anchor_step,
            )
            for a in at
        ]
    )
    lam = DEFORM_LAMBDA
    expected = [
        lam * centre[0] + (1 - lam) * windows[:3, 0].mean(),
        lam * centre[1] + (1 - lam) * windows[2, 1],
    ]
    np.testing.assert_allclose(costs, expected, atol=2e-4)
    np.testing.assert_allclose(view_costs(np.zeros((h, w), np.uint32))[30, 40], centre, atol=2e-4)
    assert np.array_equal(view_costs(np.full((h, w), 0b11, np.uint32)), view_costs(None))


def test_visible_sources_adds_the_reprojection_consistent_ones():
    """A pixel is visible in its selected sources and, with the sources' depth maps, in those
    where its forward-backward reprojection error is at most the threshold (NumPy reference)."""
    problem, depth, normal = plane_scene(num_sources=2)
    h, w = problem.reference.shape
    from dvpmvs.patchmatch.estimator import _kernel_params, _Level

    rows, cols, rays = pixel_rays(h, w)
    sources_on_the_plane(problem, depth, normal)
    # The reference depth a little off the plane, more to the right: errors from 0 to several px.
    ref_depth = (depth * (1 + 0.08 * cols / w)).astype(np.float32)
    ref_depth[:5] = 0  # no depth: visible nowhere
    errors = np.full((h, w, 2), np.inf)
    for j, src in enumerate(problem.sources):
        q = (ref_depth[..., None] * rays) @ src.R.T + src.t
        q = q @ K.T
        u = np.floor(q[..., 0] / q[..., 2] + 0.5).astype(int)
        v = np.floor(q[..., 1] / q[..., 2] + 0.5).astype(int)
        inside = (u >= 0) & (v >= 0) & (u < w) & (v < h) & (ref_depth > 0)
        ds = src.depth[v[inside], u[inside]]
        back = (
            ds[:, None]
            * np.stack([u[inside], v[inside], np.ones_like(ds)], -1)
            @ np.linalg.inv(K).T
            - src.t
        ) @ src.R
        p = back @ K.T
        errors[inside, j] = np.hypot(
            p[:, 0] / p[:, 2] - cols[inside], p[:, 1] / p[:, 2] - rows[inside]
        )
    options = PatchMatchOptions(num_threads=2)
    S = len(problem.sources)

    def masks(use_depth, selected):
        level = _Level.build(problem, 1.0, use_depth=use_depth)
        state = kernel_state(ref_depth, normal.copy(), S, selected)
        visible = np.zeros((h, w), np.uint32)
        _patchmatch.visible_sources(
            level.views, state, _kernel_params(problem, options), visible, 2.0, 2
        )
        return visible

    geometric = masks(True, 0)
    for j in range(S):
        seen = (geometric >> j) & 1 == 1
        clear = np.abs(errors[..., j] - 2.0) > 1e-3  # rounding aside
        assert np.array_equal(seen[clear], errors[..., j][clear] <= 2.0)
        assert 0.1 < seen.mean() < 0.9  # the threshold splits the image
    assert np.array_equal(masks(True, 0b10), np.where(ref_depth > 0, geometric | 0b10, 0))
    # Without depth maps (the photometric pass) only the selection counts.
    assert np.array_equal(masks(False, 0b01), np.where(ref_depth > 0, 1, 0))


def test_visibility_restoration_reprojects_with_the_lowest_cost_depth_nearby():
    """Paper section 3.4: the projected source pixel goes back with the depth of the lowest-cost
    pixel of the window around it. Sources whose depth maps hold outliers on every other pixel
    (a checkerboard, twice too far): on the true plane, the plain reprojection fails wherever the
    projection meets an outlier, the restoration (radius 1) finds a true depth in every 3x3
    window where the outliers cost more, and meets an outlier in every one where they cost less."""
    problem, depth, normal = plane_scene(num_sources=2)
    h, w = problem.reference.shape
    from dvpmvs.patchmatch.estimator import _kernel_params, _Level

    rows, cols, _ = pixel_rays(h, w)
    sources_on_the_plane(problem, depth, normal)
    outlier = (rows + cols) % 2 == 1
    true_depths = [src.depth for src in problem.sources]
    S = len(problem.sources)
    options = PatchMatchOptions(num_threads=2)

    def masks(outlier_cost, radius, outliers=True, true_cost=0.1):
        for src, true_depth in zip(problem.sources, true_depths):
            src.depth = np.where(outlier & outliers, 2.0 * true_depth, true_depth).astype(
                np.float32
            )
            src.cost = (
                None
                if outlier_cost is None
                else np.where(outlier, outlier_cost, true_cost).astype(np.float32)
            )
        level = _Level.build(problem, 1.0, use_depth=True)
        visible = np.zeros((h, w), np.uint32)
        _patchmatch.visible_sources(
            level.views,
            kernel_state(depth.copy(), normal.copy(), S),
            _kernel_params(problem, options),
            visible,
            2.0,
            2,
            level.src_cost,
            radius,
        )
        return np.stack([(visible >> j) & 1 == 1 for j in range(S)], -1)

    clean = masks(None, 0, outliers=False)  # where the projections stay inside the sources
    plain, restored, misled = masks(None, 0), masks(1.5, 1), masks(0.05, 1)
    assert clean.mean() > 0.7
    assert 0.3 < plain[clean].mean() < 0.7
    assert np.array_equal(restored, clean)
    assert misled[clean].mean() < 0.05  # every 3x3 window holds a cheaper outlier
    # Radius 0 is the projected pixel itself: the plain reprojection, whatever the costs; so is
    # a window without known costs, and ties keep the projected pixel's depth.
    assert np.array_equal(masks(1.5, 0), plain)
    assert np.array_equal(masks(np.inf, 1, true_cost=np.inf), plain)
    assert np.array_equal(masks(0.1, 1), plain)
    with pytest.raises(ValueError, match="src_cost"):
        level = _Level.build(problem, 1.0, use_depth=True)
        _patchmatch.visible_sources(
            level.views.without_depths(),
            kernel_state(depth.copy(), normal.copy(), S),
            _kernel_params(problem, options),
            np.zeros((h, w), np.uint32),
            2.0,
            2,
            level.src_cost,
            1,
        )


def test_estimator_with_anchor_visibility_is_deterministic_and_matches_fewer_windows():
    problem, depth, normal = plane_scene(num_sources=4)
    problem.labels = np.ones(problem.reference.shape, np.int32)
    options = PatchMatchOptions(
        num_scales=1,
        num_iterations=2,
        seed=5,
        strong_max_cost=0.05,
        num_threads=2,
        anchor_visibility=False,
    )
    every = estimate(problem, options)
    visible = [
        estimate(
            problem,
            PatchMatchOptions(**{**options.as_dict(), "anchor_visibility": True, "num_threads": t}),
        )
        for t in (1, 2)
    ]
    assert np.array_equal(visible[0].depth, visible[1].depth)
    assert visible[0].deformed is not None and visible[0].deformed.any()
    # Anchors go unmatched in the sources their view selection left out.
    assert visible[0].hypothesis_evaluations < every.hypothesis_evaluations
    valid = visible[0].depth > 0
    assert valid.mean() > 0.5
    assert np.median(np.abs(visible[0].depth[valid] - depth[valid]) / depth[valid]) < 0.01
