"""The matching cost (paper eq. 3, ``_window_cost.pxd``): the kernel's costs against NumPy
references, plain and deformed, the geometric term, and the vector paths against the scalar loops."""

import os
import subprocess
import sys

import numpy as np
import pytest

from dvpmvs.maps import Pass
from dvpmvs.patchmatch import (
    PatchMatchOptions,
    Problem,
    ViewData,
    _patchmatch,
    estimate,
    hypothesis_costs,
)
from dvpmvs.patchmatch.estimator import DEFORM_LAMBDA, _kernel_params, _Level, _matching_images
from tests.plane_scenes import K, kernel_state, numpy_cost, plane_scene, sources_on_the_plane

# Also run on the other Pythons `make test` checks (scripts/other_pythons.py).
pytestmark = pytest.mark.smoke


def test_kernel_cost_matches_a_numpy_reference():
    problem, plane_depth, normals = plane_scene()
    options = PatchMatchOptions()
    rng = np.random.default_rng(1)
    depth = (plane_depth * rng.uniform(0.95, 1.05, plane_depth.shape)).astype(np.float32)
    normal = normals + rng.normal(0, 0.1, normals.shape).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    pixels = np.array([[30, 40], [5, 7], [0, 0], [59, 79], [12, 70], [45, 20]], np.int32)
    got = hypothesis_costs(problem, depth, normal, pixels, options)
    want = np.array([numpy_cost(problem, depth, normal, r, c, options) for r, c in pixels])
    assert got.shape == (len(pixels), 2)
    np.testing.assert_allclose(got, want, atol=2e-4)
    assert (got < 2).sum() >= 8  # most cases are real NCC evaluations, not the out-of-image cost


def test_true_plane_has_the_lowest_cost():
    problem, plane_depth, normals = plane_scene()
    pixels = np.array([[r, c] for r in range(15, 45, 6) for c in range(20, 60, 8)], np.int32)
    true_cost = hypothesis_costs(problem, plane_depth, normals, pixels)
    assert true_cost.mean() < 0.05
    # Disparity is ~5 px per source at this depth: 20 % off moves the patch by ~1 px.
    for factor in (0.8, 1.25):
        wrong = hypothesis_costs(problem, plane_depth * factor, normals, pixels)
        assert (wrong > true_cost).mean() > 0.95 and wrong.mean() > true_cost.mean() + 0.1


def _noisy(problem, sigma, seed):
    rng = np.random.default_rng(seed)

    def noisy(view):
        image = (view.image + rng.normal(0, sigma, view.image.shape)).astype(np.float32)
        return ViewData(view.name, image, view.K, view.R, view.t, view.depth)

    return Problem(
        noisy(problem.reference), [noisy(v) for v in problem.sources], problem.depth_range
    )


def test_image_sigma_matches_the_smoothed_images():
    from dvpmvs.image import smooth_untextured

    problem, plane_depth, normals = plane_scene()
    problem = _noisy(problem, 0.03, 5)

    def smoothed(view):
        return ViewData(
            view.name, smooth_untextured(view.image, 1.0, 2.0), view.K, view.R, view.t, view.depth
        )

    smooth = Problem(
        smoothed(problem.reference), [smoothed(v) for v in problem.sources], problem.depth_range
    )
    pixels = np.array([[r, c] for r in range(5, 55, 7) for c in range(4, 76, 9)], np.int32)
    options = PatchMatchOptions(image_sigma=1.0)  # FLAT_NOISE_SCALE: 2
    got = hypothesis_costs(problem, plane_depth, normals, pixels, options)
    as_they_are = PatchMatchOptions(image_sigma=0.0)
    np.testing.assert_array_equal(
        got, hypothesis_costs(smooth, plane_depth, normals, pixels, as_they_are)
    )
    assert not np.array_equal(
        got, hypothesis_costs(problem, plane_depth, normals, pixels, as_they_are)
    )


def test_image_sigma_lowers_the_true_planes_cost_on_a_faint_texture():
    # A texture barely above the sensor noise: the raw windows are mostly noise; smoothed, the
    # true plane costs far less, and a plane 20 % off still costs more than it.
    problem, plane_depth, normals = plane_scene()

    def faint(view):
        return ViewData(
            view.name,
            (0.5 + 0.15 * (view.image - view.image.mean())).astype(np.float32),
            view.K,
            view.R,
            view.t,
            view.depth,
        )

    problem = _noisy(
        Problem(faint(problem.reference), [faint(v) for v in problem.sources], problem.depth_range),
        0.01,
        6,
    )
    pixels = np.array([[r, c] for r in range(15, 45, 6) for c in range(20, 60, 8)], np.int32)
    smoothing = PatchMatchOptions(image_sigma=1.0)
    raw = hypothesis_costs(
        problem, plane_depth, normals, pixels, PatchMatchOptions(image_sigma=0.0)
    )
    smooth = hypothesis_costs(problem, plane_depth, normals, pixels, smoothing)
    assert smooth.mean() < 0.5 * raw.mean()  # measured 0.56 -> 0.21
    for factor in (0.8, 1.25):
        wrong = hypothesis_costs(problem, plane_depth * factor, normals, pixels, smoothing)
        # Per source (measured 1.0 and 0.88, as without smoothing), and per pixel over its
        # sources (measured 1.0 for both).
        assert (wrong > smooth).mean() > 0.85
        assert (wrong.mean(axis=1) > smooth.mean(axis=1)).mean() > 0.97


def test_geometric_term_adds_the_clamped_reprojection_error():
    problem, plane_depth, normals = plane_scene()
    pixels = np.array([[30, 40], [20, 25]], np.int32)
    photometric = hypothesis_costs(problem, plane_depth, normals, pixels)
    # Sources' depth maps of the true plane: consistent, so the geometric term is ~0.
    sources_on_the_plane(problem, plane_depth, normals)
    consistent = hypothesis_costs(problem, plane_depth, normals, pixels)
    # Reference: project, read the source depth at the nearest pixel, back-project, reproject.
    expected = photometric.astype(np.float64).copy()
    for i, (row, col) in enumerate(pixels):
        X = plane_depth[row, col] * np.linalg.inv(K) @ np.array([col, row, 1.0])
        for j, src in enumerate(problem.sources):
            q = K @ (src.R @ X + src.t)
            u, v = (int(np.floor(q[0] / q[2] + 0.5)), int(np.floor(q[1] / q[2] + 0.5)))
            back = src.R.T @ (src.depth[v, u] * np.linalg.inv(K) @ np.array([u, v, 1.0]) - src.t)
            p = K @ back
            expected[i, j] += 0.2 * min(np.hypot(p[0] / p[2] - col, p[1] / p[2] - row), 3.0)
    np.testing.assert_allclose(consistent, expected, atol=1e-4)
    assert (consistent - photometric).max() < 0.2 * 0.75  # rounding to the nearest source pixel
    # Far-off source depths: the term saturates at 0.2 * 3 px.
    for src in problem.sources:
        src.depth = src.depth * 10  # ~4.7 px of epipolar displacement or more
    inconsistent = hypothesis_costs(problem, plane_depth, normals, pixels)
    np.testing.assert_allclose(inconsistent, photometric + 0.2 * 3.0, atol=1e-4)


def test_deformed_cost_mixes_centre_and_anchor_windows():
    """With anchors set, a pixel's cost is lambda * centre window (stride 5) + (1 - lambda) *
    mean of its anchors' windows, all warped with the pixel's plane; on the exact plane of a
    textured scene it stays near 0, and a wrong depth raises it."""
    problem, depth, normal = plane_scene(num_sources=2)
    h, w = problem.reference.shape
    from dvpmvs.patchmatch.estimator import _kernel_params, _Level

    options = PatchMatchOptions(num_threads=1)
    level = _Level.build(problem, 1.0, use_depth=False)
    S = len(problem.sources)
    state = kernel_state(depth.copy(), normal.copy(), S)
    params = _kernel_params(problem, options)
    anchors = np.full((h, w, 8), -1, np.int32)
    anchors[30, 40, :4] = [30 * w + 50, 20 * w + 40, 30 * w + 30, 40 * w + 40]
    _patchmatch.initialise(level.views, state, params, False, S, 1, anchors)
    deformed_true = state.cost[30, 40]
    wrong = (depth * 1.5).astype(np.float32)
    state_wrong = kernel_state(wrong, normal.copy(), S)
    _patchmatch.initialise(level.views, state_wrong, params, False, S, 1, anchors)
    assert deformed_true < 0.1 and state_wrong.cost[30, 40] > deformed_true + 0.3
    # The undeformed pixels' costs do not change when anchors are given to another pixel.
    plain = kernel_state(depth.copy(), normal.copy(), S)
    _patchmatch.initialise(level.views, plain, params, False, S, 1, None)
    mask = np.ones((h, w), bool)
    mask[30, 40] = False
    assert np.array_equal(plain.cost[mask], state.cost[mask])
    assert plain.cost[30, 40] != deformed_true


@pytest.mark.parametrize("anchor_step", [2, 5])
def test_deformed_cost_matches_a_numpy_reference(anchor_step):
    """Eq. 3 per source: lambda * the centre window sampled every deform_centre_step pixels +
    (1 - lambda) * the mean over anchors of their windows sampled every deform_anchor_step
    pixels, every window warped with the pixel's own plane (here a slightly wrong one, so the
    windows' costs differ, the more so the further a window lies from the pixel)."""
    problem, depth, normal = plane_scene(num_sources=2)
    h, w = problem.reference.shape
    from dvpmvs.patchmatch.estimator import _kernel_params, _Level

    options = PatchMatchOptions(num_threads=1, deform_anchor_step=anchor_step)
    level = _Level.build(problem, 1.0, use_depth=False)
    S = len(problem.sources)
    wrong = (depth * 1.04).astype(np.float32)
    tilted = normal + np.array([0.3, 0.1, 0.0], np.float32)
    tilted /= np.linalg.norm(tilted, axis=-1, keepdims=True)
    state = kernel_state(wrong, tilted, S)
    anchors = np.full((h, w, 8), -1, np.int32)
    at = [(30, 50), (20, 40), (30, 28), (42, 41)]
    anchors[30, 40, :4] = [r * w + c for r, c in at]
    _patchmatch.initialise(
        level.views, state, _kernel_params(problem, options), False, S, 1, anchors
    )
    centre = numpy_cost(problem, wrong, tilted, 30, 40, options, step=options.deform_centre_step)
    windows = [
        numpy_cost(problem, wrong, tilted, 30, 40, options, window_at=a, step=anchor_step)
        for a in at
    ]
    expected = DEFORM_LAMBDA * centre + (1 - DEFORM_LAMBDA) * np.mean(windows, axis=0)
    assert np.ptp(windows) > 0.1  # the windows disagree, so a wrong window or sampling would show
    np.testing.assert_allclose(state.view_cost[30, 40], expected, atol=2e-4)


@pytest.mark.parametrize("anchor_step", [2, 3])
def test_anchor_windows_computed_once_give_the_same_costs_and_sweeps(anchor_step):
    """The anchor windows' colour weights computed once per level (``anchor_windows``) are the
    ones every update computed: the same costs bit for bit (anchors at the borders included, and
    the pixels' own plain windows where the anchor window is the matching window), and the same
    state after a sweep."""
    problem, depth, normal = plane_scene(num_sources=3)
    rng = np.random.default_rng(11)
    h, w = depth.shape
    depth = (depth * rng.uniform(0.9, 1.1, depth.shape)).astype(np.float32)
    options = PatchMatchOptions(num_threads=2, deform_anchor_step=anchor_step)
    level = _Level.build(problem, 1.0, use_depth=False, images=_matching_images(problem, options))
    params = _kernel_params(problem, options)
    anchors = _anchors(depth.shape, rng)
    windows = _patchmatch.anchor_windows(level.ref, anchors, params, 2)
    assert windows.plain == (anchor_step == options.window_step)
    assert windows.weight.shape[0] == np.unique(anchors[anchors >= 0]).size
    rows, cols = np.mgrid[0:h, 0:w]
    pixels = np.stack([rows.ravel(), cols.ravel()], 1).astype(np.int32)
    plain = _patchmatch.patch_costs(level.views, depth, normal, params, pixels, anchors)
    cached = _patchmatch.patch_costs(
        level.views, depth, normal, params, pixels, anchors, anchor_windows=windows
    )
    assert (plain < 2).mean() > 0.5
    np.testing.assert_array_equal(cached, plain)
    # Anchors that name no pixel: an empty table, and every window computes its own weights.
    none = np.full_like(anchors, -1)
    empty = _patchmatch.anchor_windows(level.ref, none, params, 2)
    assert empty.weight.shape[0] == 0
    np.testing.assert_array_equal(
        _patchmatch.patch_costs(
            level.views, depth, normal, params, pixels, none, anchor_windows=empty
        ),
        _patchmatch.patch_costs(level.views, depth, normal, params, pixels, none),
    )
    S = len(problem.sources)
    states = []
    for extra in ({}, {"anchor_windows": windows}):
        state = kernel_state(depth.copy(), normal.copy(), S)
        _patchmatch.initialise(level.views, state, params, False, S, 2, anchors, **extra)
        for colour in (0, 1):
            _patchmatch.sweep(level.views, state, params, colour, 2, anchors=anchors, **extra)
        states.append(state)
    for a, b in zip(*states):
        np.testing.assert_array_equal(a, b)


# -- the vector paths (_window_cost_simd.h) against the scalar loops: the same costs and the same
# maps, bit for bit, whichever path the CPU runs or the environment forces.


def _vector_paths():
    """The vector paths this CPU runs (each selected once to see whether it falls back)."""
    try:
        return [path for path in ("avx2",) if _patchmatch.select_simd(path) == path]
    finally:
        _patchmatch.select_simd(os.environ.get("DVPMVS_SIMD", "auto"))


@pytest.fixture
def simd():
    """Select a path for the test; the one chosen at import is restored afterwards."""
    yield _patchmatch.select_simd
    _patchmatch.select_simd(os.environ.get("DVPMVS_SIMD", "auto"))


def _anchors(shape, rng, fraction=0.5):
    """Random anchors for about ``fraction`` of the pixels (a weak pixel's anchors are pixels
    anywhere in the image, borders included), the others none."""
    h, w = shape
    anchors = rng.integers(0, h * w, (h, w, 8)).astype(np.int32)
    anchors[rng.random((h, w, 8)) < 0.3] = -1
    anchors[rng.random((h, w)) > fraction] = -1
    return anchors


def test_vector_paths_give_the_scalar_costs_on_random_windows(simd):
    # Ten sources (more than one batch of 8 lanes), random planes (many warp windows across the
    # border of a source, or out of it), plain and deformed windows, pixels at the border.
    problem, depth, normal = plane_scene(num_sources=10)
    rng = np.random.default_rng(3)
    h, w = depth.shape
    depth = (depth * rng.uniform(0.8, 1.25, depth.shape)).astype(np.float32)
    normal = normal + rng.normal(0, 0.3, normal.shape).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    rows, cols = np.mgrid[0:h, 0:w]
    pixels = np.stack([rows.ravel(), cols.ravel()], 1).astype(np.int32)
    options = PatchMatchOptions()
    level = _Level.build(problem, 1.0, use_depth=False, images=_matching_images(problem, options))
    params = _kernel_params(problem, options)
    anchors = _anchors(depth.shape, rng)
    visible = rng.integers(0, 2**10, depth.shape).astype(np.uint32)
    paths = _vector_paths()
    for extra in ({}, {"anchors": anchors}, {"anchors": anchors, "anchor_visible": visible}):
        simd("scalar")
        expected = _patchmatch.patch_costs(level.views, depth, normal, params, pixels, **extra)
        assert (expected < 2).mean() > 0.3 and (
            expected == 2
        ).any()  # both matched and unseen windows
        for path in paths:
            assert simd(path) == path
            got = _patchmatch.patch_costs(level.views, depth, normal, params, pixels, **extra)
            np.testing.assert_array_equal(got, expected, err_msg=f"{path} {sorted(extra)}")


@pytest.mark.parametrize(
    "variant",
    [
        {},  # the default: deformation, planar prior, early stop
        {
            "anchor_visibility": True,
            "area_maximisation": True,
            "normal_aggregation": True,
            "depth_aggregation": True,
        },
    ],
)
def test_vector_paths_give_the_scalar_maps(simd, variant):
    problem, _, _ = plane_scene(num_sources=10)
    problem.labels = np.ones(problem.reference.shape, np.int32)
    options = PatchMatchOptions(
        num_scales=2,
        min_scale_size=32,
        num_iterations=2,
        seed=7,
        strong_max_cost=0.05,
        num_threads=2,
        **variant,
    )
    paths = ["scalar"] + _vector_paths()
    results = {}  # per path, the estimate of the pass before (the geometric pass reads its maps)
    for pass_ in (Pass.PHOTOMETRIC, Pass.GEOMETRIC):
        if pass_ is Pass.GEOMETRIC:  # sources' maps shifted, so that the reprojection term varies
            for k, src in enumerate(problem.sources):
                src.depth = np.roll(results["scalar"].depth, k + 1, axis=1)
            problem.initial = (results["scalar"].depth, results["scalar"].normal)
        results = {}
        for path in paths:
            assert simd(path) == path
            results[path] = estimate(problem, options, pass_)
        assert results["scalar"].deformed is not None and results["scalar"].deformed.any()
        for path in paths[1:]:
            for name in ("depth", "normal", "cost", "visibility"):
                np.testing.assert_array_equal(
                    getattr(results[path], name),
                    getattr(results["scalar"], name),
                    err_msg=f"{path} {pass_.value} {name}",
                )


def test_the_vector_paths_keep_the_maps_independent_of_the_thread_count(simd):
    problem, _, _ = plane_scene(num_sources=3)
    problem.labels = np.ones(problem.reference.shape, np.int32)
    simd("auto")
    one, two = (
        estimate(
            problem,
            PatchMatchOptions(
                num_scales=1, num_iterations=2, seed=5, strong_max_cost=0.05, num_threads=t
            ),
        )
        for t in (1, 2)
    )
    assert one.deformed is not None and one.deformed.any()
    assert np.array_equal(one.depth, two.depth) and np.array_equal(one.normal, two.normal)


def _simd_at_import(value):
    env = {**os.environ, "DVPMVS_SIMD": value}
    return subprocess.run(
        [
            sys.executable,
            "-c",
            "from dvpmvs.patchmatch import _patchmatch; print(_patchmatch.SIMD)",
        ],
        env=env,
        capture_output=True,
        text=True,
    )


def test_the_environment_chooses_the_path_at_import_and_unsupported_ones_fall_back():
    assert _simd_at_import("scalar").stdout.strip() == "scalar"
    supported = _vector_paths()
    assert _simd_at_import("avx2").stdout.strip() == ("avx2" if "avx2" in supported else "scalar")
    auto = _simd_at_import("auto").stdout.strip()
    assert auto == (supported[-1] if supported else "scalar")
    bad = _simd_at_import("sse9")
    assert bad.returncode != 0 and "DVPMVS_SIMD='sse9'" in bad.stderr and "scalar" in bad.stderr
