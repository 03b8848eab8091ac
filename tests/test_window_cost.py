"""The matching cost's vector paths (_window_cost_simd.h) against the scalar loops: the same costs
and the same maps, bit for bit, whichever path the CPU runs or the environment forces."""

import os
import subprocess
import sys

import numpy as np
import pytest

from dvpmvs.maps import Pass
from dvpmvs.patchmatch import PatchMatchOptions, estimate
from dvpmvs.patchmatch import _patchmatch
from dvpmvs.patchmatch.estimator import _kernel_params, _Level, _matching_images

from test_patchmatch import _plane_scene


def _vector_paths():
    """The vector paths this CPU runs (each selected once to see whether it falls back)."""
    try:
        return [path for path in ("avx2", "avx512") if _patchmatch.select_simd(path) == path]
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
    problem, depth, normal = _plane_scene(num_sources=10)
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
    visible = rng.integers(0, 2 ** 10, depth.shape).astype(np.uint32)
    paths = _vector_paths()
    for extra in ({}, {"anchors": anchors}, {"anchors": anchors, "anchor_visible": visible}):
        simd("scalar")
        expected = _patchmatch.patch_costs(*level.args, depth, normal, params, pixels, **extra)
        assert (expected < 2).mean() > 0.3 and (expected == 2).any()  # both matched and unseen windows
        for path in paths:
            assert simd(path) == path
            got = _patchmatch.patch_costs(*level.args, depth, normal, params, pixels, **extra)
            np.testing.assert_array_equal(got, expected, err_msg=f"{path} {sorted(extra)}")


@pytest.mark.parametrize("variant", [
    {},  # the default: deformation, planar prior, early stop
    {"anchor_visibility": True, "area_maximisation": True, "normal_aggregation": True, "depth_aggregation": True},
    {"deform_select_step": 5},  # view selection's sparser anchor windows
])
def test_vector_paths_give_the_scalar_maps(simd, variant):
    problem, _, _ = _plane_scene(num_sources=10)
    problem.labels = np.ones(problem.reference.shape, np.int32)
    options = PatchMatchOptions(num_scales=2, min_scale_size=32, num_iterations=2, seed=7, strong_max_cost=0.05,
                                num_threads=2, **variant)
    paths = ["scalar"] + _vector_paths()
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
                np.testing.assert_array_equal(getattr(results[path], name), getattr(results["scalar"], name),
                                              err_msg=f"{path} {pass_.value} {name}")


def test_the_vector_paths_keep_the_maps_independent_of_the_thread_count(simd):
    problem, _, _ = _plane_scene(num_sources=3)
    problem.labels = np.ones(problem.reference.shape, np.int32)
    simd("auto")
    one, two = (estimate(problem, PatchMatchOptions(num_scales=1, num_iterations=2, seed=5, strong_max_cost=0.05,
                                                    num_threads=t)) for t in (1, 2))
    assert one.deformed is not None and one.deformed.any()
    assert np.array_equal(one.depth, two.depth) and np.array_equal(one.normal, two.normal)


def _simd_at_import(value):
    env = {**os.environ, "DVPMVS_SIMD": value}
    return subprocess.run([sys.executable, "-c", "from dvpmvs.patchmatch import _patchmatch; print(_patchmatch.SIMD)"],
                          env=env, capture_output=True, text=True)


def test_the_environment_chooses_the_path_at_import_and_unsupported_ones_fall_back():
    assert _simd_at_import("scalar").stdout.strip() == "scalar"
    supported = _vector_paths()
    for path in ("avx2", "avx512"):
        expected = path if path in supported else ("avx2" if "avx2" in supported else "scalar")
        assert _simd_at_import(path).stdout.strip() == expected
    auto = _simd_at_import("auto").stdout.strip()
    assert auto == (supported[-1] if supported else "scalar")
    bad = _simd_at_import("sse9")
    assert bad.returncode != 0 and "DVPMVS_SIMD='sse9'" in bad.stderr and "scalar" in bad.stderr
