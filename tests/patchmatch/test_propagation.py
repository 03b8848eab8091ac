"""Propagation and view selection (``_propagation.pxd``): the early stop, and the rescoring of
unselected sources."""

import numpy as np

from dvpmvs.maps import Pass
from dvpmvs.patchmatch import PatchMatchOptions, _patchmatch, estimate
from tests.plane_scenes import kernel_state, plane_scene


def _both_passes(problem, variants):
    """Each of ``variants`` (name -> options) run through the photometric pass, then the geometric
    pass from the first variant's photometric maps (the sources' maps shifted, so that the
    reprojection term varies)."""
    results = {}
    for pass_ in (Pass.PHOTOMETRIC, Pass.GEOMETRIC):
        if pass_ is Pass.GEOMETRIC:
            photometric = next(iter(results[Pass.PHOTOMETRIC].values()))
            for k, src in enumerate(problem.sources):
                src.depth = np.roll(photometric.depth, k + 1, axis=1)
            problem.initial = (photometric.depth, photometric.normal)
        results[pass_] = {
            name: estimate(problem, options, pass_) for name, options in variants.items()
        }
    return results


def _assert_same_maps(a, b):
    for name in ("depth", "normal", "cost", "visibility"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name


def test_early_stop_gives_the_maps_of_full_scoring():
    # Giving up a hypothesis once a lower bound of its cost shows it cannot win must not change
    # any map: photometric and geometric passes, plain and deformed pixels, planar prior.
    problem, depth, normal = plane_scene(num_sources=3)
    problem.labels = np.ones(problem.reference.shape, np.int32)
    options = PatchMatchOptions(
        num_scales=2,
        min_scale_size=32,
        num_iterations=2,
        seed=7,
        strong_max_cost=0.05,
        num_threads=2,
    )
    exhaustive = PatchMatchOptions(**{**options.as_dict(), "early_stop": False})
    for results in _both_passes(problem, {"fast": options, "full": exhaustive}).values():
        fast, full = results["fast"], results["full"]
        assert fast.deformed is not None and fast.deformed.any()
        _assert_same_maps(fast, full)
        assert fast.hypothesis_evaluations < 0.97 * full.hypothesis_evaluations


def test_sweep_rescores_unselected_sources_only_when_view_costs_are_kept():
    """``keep_view_costs`` (default): after a sweep every updated pixel's ``view_cost`` is the
    cost of its new plane in every source; without it, only in the sources it selected (the
    others are stale, which the last sweep of a state may leave), and every other map is the same."""
    problem, _, _ = plane_scene(num_sources=4)
    h, w = problem.reference.shape
    from dvpmvs.patchmatch.estimator import _kernel_params, _Level

    level = _Level.build(problem, 1.0, use_depth=False)
    S = len(problem.sources)
    params = _kernel_params(problem, PatchMatchOptions())
    start = kernel_state(np.zeros((h, w), np.float32), np.zeros((h, w, 3), np.float32), S)
    _patchmatch.initialise(level.views, start, params, True, 2, 1)
    states, evaluations = {}, {}
    for keep in (True, False):
        states[keep] = start.copy()
        evaluations[keep] = _patchmatch.sweep(
            level.views, states[keep], params.replace(keep_view_costs=keep), 0, 2
        )
    for name in ("depth", "normal", "cost", "weights", "selected"):  # all but view_cost
        assert np.array_equal(getattr(states[True], name), getattr(states[False], name))
    rows, cols = np.mgrid[0:h, 0:w]
    swept = (rows + cols) % 2 == 0
    pixels = np.ascontiguousarray(np.argwhere(swept), np.int32)
    depth, normal = states[True].depth, states[True].normal
    truth = _patchmatch.patch_costs(level.views, depth, normal, params, pixels)
    kept = states[True].view_cost[swept]
    lean = states[False].view_cost[swept]
    selected = states[True].weights[swept] > 0
    np.testing.assert_allclose(kept, truth, atol=1e-6)
    np.testing.assert_allclose(lean[selected], truth[selected], atol=1e-6)
    assert np.mean(np.abs(lean[~selected] - truth[~selected]) > 1e-3) > 0.2  # stale
    assert evaluations[False] < evaluations[True]
