"""Prior providers (plugins/classic) and the core's checks and alignment (dvpmvs.priors)."""

from functools import partial

import numpy as np
import pytest

from dvpmvs import registry
from dvpmvs.maps import write_extra_map
from dvpmvs.priors import DepthPrior, PriorContext, PriorError, PriorProviders, align_to_sparse, compute_priors, \
    read_prior_array

K = np.array([[100.0, 0, 40], [0, 100.0, 30], [0, 0, 1]])
H, W = 60, 80


def _plane_depth(a=0.2, b=-0.1, c=4.0):
    rows, cols = np.mgrid[0:H, 0:W].astype(np.float64)
    return (c / (1 - a * (cols - 40) / 100 - b * (rows - 30) / 100)).astype(np.float32)


def _ctx(tmp_path, image=None, sparse=None, name="im.png"):
    if image is None:
        image = np.zeros((H, W), np.float32)
        image[:, 40:] = 1.0  # one vertical step edge
    if sparse is None:
        depth = _plane_depth()
        rng = np.random.default_rng(0)
        cols, rows = rng.integers(0, W, 200), rng.integers(0, H, 200)
        sparse = np.stack([cols, rows, depth[rows, cols]], axis=1).astype(np.float64)
    return PriorContext(name, image, K, (2.0, 8.0), sparse, root=tmp_path)


def test_classic_providers_are_registered():
    assert {"coarse_mvs", "sparse", "file"} <= set(registry.available("depth_prior"))
    assert {"from_depth", "file"} <= set(registry.available("normal_prior"))
    assert {"roberts", "canny"} <= set(registry.available("edge"))
    assert "none" in registry.available("highlight")


@pytest.mark.parametrize("name", ["roberts", "canny"])
def test_edge_detectors_find_a_step_and_nothing_on_flat_grey(tmp_path, name):
    edges = registry.create("edge", name)(_ctx(tmp_path))
    assert edges.dtype == bool and edges.shape == (H, W)
    assert edges[:, 38:42].any(axis=1).all()  # every row finds the step
    assert not edges[:, :30].any() and not edges[:, 52:].any()


def test_sparse_depth_interpolates_a_plane(tmp_path):
    prior = registry.create("depth_prior", "sparse")(_ctx(tmp_path))
    truth = _plane_depth()
    # Linear interpolation of a plane's depth is not exact (depth is not linear in pixels), but close.
    assert np.median(np.abs(prior.depth - truth) / truth) < 0.01 and prior.metric


def test_from_depth_normals_match_the_plane(tmp_path):
    normal = registry.create("normal_prior", "from_depth")(_ctx(tmp_path), _plane_depth())
    expected = np.array([0.2, -0.1, -1.0]) / np.linalg.norm([0.2, -0.1, -1.0])
    assert np.degrees(np.arccos(np.clip(normal[5:-5, 5:-5] @ expected, -1, 1))).max() < 1.0


@pytest.mark.parametrize("suffix", [".npy", ".pfm", ".bin"])
def test_file_depth_prior_reads_each_format_and_is_aligned(tmp_path, suffix):
    truth = _plane_depth()
    relative = 0.5 * truth + 0.7  # known up to scale and shift
    folder = tmp_path / "priors"
    folder.mkdir()
    path = folder / f"im.png{suffix}"
    if suffix == ".npy":
        np.save(path, relative)
    elif suffix == ".pfm":
        with open(path, "wb") as f:
            f.write(b"Pf\n%d %d\n-1.0\n" % (W, H))
            f.write(np.ascontiguousarray(relative[::-1], "<f4").tobytes())
    else:
        write_extra_map(path, relative)
    assert np.array_equal(read_prior_array(path), relative)
    providers = PriorProviders.from_configs({"depth_prior": {"name": "file", "path": "priors"}})
    priors = compute_priors(_ctx(tmp_path), providers)
    assert np.abs(priors.depth - truth).max() < 1e-3 * truth.max()


def test_relative_inverse_depth_file_is_aligned_in_inverse_depth(tmp_path):
    # A disparity-like prior's unknown shift is a shift of inverse depth: aligning it after
    # inverting (in depth) would bend the plane.
    truth = _plane_depth()
    folder = tmp_path / "priors"
    folder.mkdir()
    np.save(folder / "im.npy", (3.0 / truth + 0.2).astype(np.float32))
    providers = PriorProviders.from_configs({"depth_prior": {"name": "file", "path": "priors",
                                                             "kind": "inverse_depth"}})
    priors = compute_priors(_ctx(tmp_path), providers)
    assert np.abs(priors.depth - truth).max() < 1e-3 * truth.max()


def test_normals_derived_from_the_depth_prior_are_marked(tmp_path):
    # The segmentation adds the depth-edge rule to independent normals only.
    folder = tmp_path / "priors"
    folder.mkdir()
    np.save(folder / "im.npy", _plane_depth())
    normal = np.zeros((H, W, 3), np.float32)
    normal[..., 2] = -1
    depth = {"name": "file", "path": "priors"}
    derived = compute_priors(_ctx(tmp_path), PriorProviders.from_configs(
        {"depth_prior": depth, "normal_prior": {"name": "from_depth"}}))
    assert derived.normal is not None and derived.normal_from_depth
    (folder / "normals").mkdir()
    np.save(folder / "normals" / "im.npy", normal)
    independent = compute_priors(_ctx(tmp_path), PriorProviders.from_configs(
        {"depth_prior": depth, "normal_prior": {"name": "file", "path": "priors/normals"}}))
    assert independent.normal is not None and not independent.normal_from_depth


def test_file_prior_errors_name_the_problem(tmp_path):
    providers = PriorProviders.from_configs({"depth_prior": {"name": "file", "path": "missing"}})
    with pytest.raises(PriorError, match="depth_prior.path: folder not found"):
        compute_priors(_ctx(tmp_path), providers)
    providers = PriorProviders.from_configs({"depth_prior": {"name": "file"}})
    with pytest.raises(PriorError, match="set depth_prior.path"):
        compute_priors(_ctx(tmp_path), providers)
    folder = tmp_path / "priors"
    folder.mkdir()
    providers = PriorProviders.from_configs({"depth_prior": {"name": "file", "path": str(folder)}})
    with pytest.raises(PriorError, match="no prior for image im.png"):
        compute_priors(_ctx(tmp_path), providers)
    bad = _plane_depth()
    bad[3, 4] = np.nan
    np.save(folder / "im.npy", bad)
    with pytest.raises(PriorError, match="NaN"):
        compute_priors(_ctx(tmp_path), providers)


def test_a_provider_breaking_the_contract_is_named(tmp_path):
    providers = PriorProviders(depth=lambda ctx: DepthPrior(np.full((H, W), np.nan, np.float32)),
                               names={"depth": "broken"})
    with pytest.raises(PriorError, match="'broken' returned NaN"):
        compute_priors(_ctx(tmp_path), providers)
    providers = PriorProviders(edge=lambda ctx: np.zeros((5, 5), bool), names={"edge": "tiny"})
    with pytest.raises(PriorError, match="'tiny' returned shape"):
        compute_priors(_ctx(tmp_path), providers)


def test_alignment_is_robust_to_outliers_and_handles_inverse_depth():
    truth = _plane_depth()
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
    truth = _plane_depth(a=0.04, b=0.0)
    rng = np.random.default_rng(2)
    cols, rows = rng.integers(0, W, 400), rng.integers(0, H, 400)
    target = truth[rows, cols].astype(np.float64)
    assert np.ptp(target) / target.mean() < 0.08
    sparse = np.stack([cols, rows, target], axis=1)
    relative = (3.0 * truth * (1 + rng.normal(0, 0.03, truth.shape)) + 2.0).astype(np.float32)
    aligned, scale, _ = align_to_sparse(relative, sparse)
    assert abs(scale - 1 / 3) < 0.1 / 3
    assert np.median(np.abs(aligned - truth) / truth) < 0.03


def test_coarse_mvs_recovers_a_textured_plane(tmp_path):
    from test_patchmatch import K as PLANE_K, _plane_scene

    from dvpmvs.patchmatch.low_resolution import low_resolution_depth

    problem, truth, _ = _plane_scene(num_sources=2)
    image = problem.reference.image
    ctx = PriorContext("ref", image, PLANE_K, problem.depth_range, np.zeros((0, 3)), root=tmp_path,
                       low_resolution_depth=partial(low_resolution_depth, problem, None))
    within = {}
    for median_size in (0, 5):
        prior = registry.create("depth_prior", {"name": "coarse_mvs", "max_size": 64, "median_size": median_size})(ctx)
        assert prior.depth.shape == truth.shape and prior.metric
        within[median_size] = np.mean(np.abs(prior.depth - truth) / truth < 0.02)
    # The columns on the right are outside the sources' view; the median cleans up stray pixels
    # (measured 82.5 % -> 88.3 % within 2 %).
    assert within[5] > 0.85 and within[5] > within[0] + 0.02, within
    with pytest.raises(registry.PluginError, match="median_size must be >= 0"):
        registry.create("depth_prior", {"name": "coarse_mvs", "median_size": -1})
