"""The core's side of the priors (dvpmvs.priors): the providers' contract checked, alignment to the
sparse points, normals derived from the depth prior marked."""

import numpy as np
import pytest

from dvpmvs.priors import DepthPrior, PriorError, PriorProviders, align_to_sparse, compute_priors
from tests.prior_scenes import H, W, plane_depth, prior_context

# Also run on the other Pythons `make test` checks (scripts/other_pythons.py).
pytestmark = pytest.mark.smoke


def test_a_provider_breaking_the_contract_is_named(tmp_path):
    providers = PriorProviders(
        depth=lambda ctx: DepthPrior(np.full((H, W), np.nan, np.float32)), names={"depth": "broken"}
    )
    with pytest.raises(PriorError, match="'broken' returned NaN"):
        compute_priors(prior_context(tmp_path), providers)
    providers = PriorProviders(edge=lambda ctx: np.zeros((5, 5), bool), names={"edge": "tiny"})
    with pytest.raises(PriorError, match="'tiny' returned shape"):
        compute_priors(prior_context(tmp_path), providers)


def test_alignment_is_robust_to_outliers_and_handles_inverse_depth():
    truth = plane_depth()
    rng = np.random.default_rng(1)
    cols, rows = rng.integers(0, W, 300), rng.integers(0, H, 300)
    target = truth[rows, cols].astype(np.float64)
    target[:60] *= rng.uniform(1.5, 3.0, 60)  # 20 % gross outliers
    sparse = np.stack([cols, rows, target], axis=1)
    aligned, scale, shift = align_to_sparse(2.0 * truth - 1.0, sparse)
    assert abs(scale - 0.5) < 1e-3 and abs(shift - 0.5) < 1e-2
    assert np.abs(aligned - truth).max() < 1e-2
    inverse = (3.0 / truth).astype(np.float32)  # disparity-like, up to scale
    aligned, _, _ = align_to_sparse(inverse, sparse, inverse=True)
    assert np.median(np.abs(aligned - truth) / truth) < 1e-3
    with pytest.raises(PriorError, match="at least 3 sparse points"):
        align_to_sparse(truth, sparse[:2])


def test_alignment_keeps_the_slope_when_the_sparse_points_span_a_narrow_band():
    # Every sparse point within +-4 % of one depth (a table top) and a prior with a few per cent
    # of noise: a constant "explains" all points within a 5 % threshold, which once flattened
    # whole priors. The slope must survive.
    truth = plane_depth(a=0.04, b=0.0)
    rng = np.random.default_rng(2)
    cols, rows = rng.integers(0, W, 400), rng.integers(0, H, 400)
    target = truth[rows, cols].astype(np.float64)
    assert np.ptp(target) / target.mean() < 0.08
    sparse = np.stack([cols, rows, target], axis=1)
    relative = (3.0 * truth * (1 + rng.normal(0, 0.03, truth.shape)) + 2.0).astype(np.float32)
    aligned, scale, _ = align_to_sparse(relative, sparse)
    assert abs(scale - 1 / 3) < 0.1 / 3
    assert np.median(np.abs(aligned - truth) / truth) < 0.03


def test_normals_derived_from_the_depth_prior_are_marked(tmp_path):
    # The segmentation adds the depth-edge rule to independent normals only.
    folder = tmp_path / "priors"
    folder.mkdir()
    np.save(folder / "im.npy", plane_depth())
    normal = np.zeros((H, W, 3), np.float32)
    normal[..., 2] = -1
    depth = {"name": "file", "path": "priors"}
    derived = compute_priors(
        prior_context(tmp_path),
        PriorProviders.from_configs({"depth_prior": depth, "normal_prior": {"name": "from_depth"}}),
    )
    assert derived.normal is not None and derived.normal_from_depth
    (folder / "normals").mkdir()
    np.save(folder / "normals" / "im.npy", normal)
    independent = compute_priors(
        prior_context(tmp_path),
        PriorProviders.from_configs(
            {"depth_prior": depth, "normal_prior": {"name": "file", "path": "priors/normals"}}
        ),
    )
    assert independent.normal is not None and not independent.normal_from_depth
