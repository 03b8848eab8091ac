"""The classic prior providers (plugins/classic): edges, sparse, from_depth, file and coarse_mvs."""

from functools import partial

import numpy as np
import pytest

from dvpmvs import registry
from dvpmvs.maps import write_extra_map
from dvpmvs.priors import PriorContext, PriorError, PriorProviders, compute_priors, read_prior_array
from tests.prior_scenes import H, W, plane_depth, prior_context


def test_classic_providers_are_registered():
    assert {"coarse_mvs", "sparse", "file"} <= set(registry.available("depth_prior"))
    assert {"from_depth", "file"} <= set(registry.available("normal_prior"))
    assert {"roberts", "canny"} <= set(registry.available("edge"))
    assert "none" in registry.available("highlight")


@pytest.mark.parametrize("name", ["roberts", "canny"])
def test_edge_detectors_find_a_step_and_nothing_on_flat_grey(tmp_path, name):
    edges = registry.create("edge", name)(prior_context(tmp_path))
    assert edges.dtype == bool and edges.shape == (H, W)
    assert edges[:, 38:42].any(axis=1).all()  # every row finds the step
    assert not edges[:, :30].any() and not edges[:, 52:].any()


def test_sparse_depth_interpolates_a_plane(tmp_path):
    prior = registry.create("depth_prior", "sparse")(prior_context(tmp_path))
    truth = plane_depth()
    # Linear interpolation of a plane's depth is not exact (depth is not linear in pixels), but close.
    assert np.median(np.abs(prior.depth - truth) / truth) < 0.01 and prior.metric


def test_from_depth_normals_match_the_plane(tmp_path):
    normal = registry.create("normal_prior", "from_depth")(prior_context(tmp_path), plane_depth())
    expected = np.array([0.2, -0.1, -1.0]) / np.linalg.norm([0.2, -0.1, -1.0])
    assert np.degrees(np.arccos(np.clip(normal[5:-5, 5:-5] @ expected, -1, 1))).max() < 1.0


@pytest.mark.parametrize("suffix", [".npy", ".pfm", ".bin"])
def test_file_depth_prior_reads_each_format_and_is_aligned(tmp_path, suffix):
    truth = plane_depth()
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
    priors = compute_priors(prior_context(tmp_path), providers)
    assert np.abs(priors.depth - truth).max() < 1e-3 * truth.max()


def test_relative_inverse_depth_file_is_aligned_in_inverse_depth(tmp_path):
    # A disparity-like prior's unknown shift is a shift of inverse depth: aligning it after
    # inverting (in depth) would bend the plane.
    truth = plane_depth()
    folder = tmp_path / "priors"
    folder.mkdir()
    np.save(folder / "im.npy", (3.0 / truth + 0.2).astype(np.float32))
    providers = PriorProviders.from_configs(
        {"depth_prior": {"name": "file", "path": "priors", "kind": "inverse_depth"}}
    )
    priors = compute_priors(prior_context(tmp_path), providers)
    assert np.abs(priors.depth - truth).max() < 1e-3 * truth.max()


def test_file_prior_errors_name_the_problem(tmp_path):
    providers = PriorProviders.from_configs({"depth_prior": {"name": "file", "path": "missing"}})
    with pytest.raises(PriorError, match="depth_prior.path: folder not found"):
        compute_priors(prior_context(tmp_path), providers)
    providers = PriorProviders.from_configs({"depth_prior": {"name": "file"}})
    with pytest.raises(PriorError, match="set depth_prior.path"):
        compute_priors(prior_context(tmp_path), providers)
    folder = tmp_path / "priors"
    folder.mkdir()
    providers = PriorProviders.from_configs({"depth_prior": {"name": "file", "path": str(folder)}})
    with pytest.raises(PriorError, match="no prior for image im.png"):
        compute_priors(prior_context(tmp_path), providers)
    bad = plane_depth()
    bad[3, 4] = np.nan
    np.save(folder / "im.npy", bad)
    with pytest.raises(PriorError, match="NaN"):
        compute_priors(prior_context(tmp_path), providers)


def test_coarse_mvs_recovers_a_textured_plane(tmp_path):
    from dvpmvs.patchmatch.low_resolution import low_resolution_depth
    from tests.plane_scenes import K as PLANE_K
    from tests.plane_scenes import plane_scene

    problem, truth, _ = plane_scene(num_sources=2)
    image = problem.reference.image
    ctx = PriorContext(
        "ref",
        image,
        PLANE_K,
        problem.depth_range,
        np.zeros((0, 3)),
        root=tmp_path,
        low_resolution_depth=partial(low_resolution_depth, problem, None),
    )
    within = {}
    for median_size in (0, 5):
        prior = registry.create(
            "depth_prior", {"name": "coarse_mvs", "max_size": 64, "median_size": median_size}
        )(ctx)
        assert prior.depth.shape == truth.shape and prior.metric
        within[median_size] = np.mean(np.abs(prior.depth - truth) / truth < 0.02)
    # The columns on the right are outside the sources' view; the median cleans up stray pixels
    # (measured 82.5 % -> 88.3 % within 2 %).
    assert within[5] > 0.85 and within[5] > within[0] + 0.02, within
    with pytest.raises(registry.PluginError, match="median_size must be >= 0"):
        registry.create("depth_prior", {"name": "coarse_mvs", "median_size": -1})
