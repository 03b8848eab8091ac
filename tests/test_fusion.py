"""The fusion kernel on a constructed plane: which points a fused point is made of and which views
support it; the visibility file in COLMAP's layout."""

import struct

import numpy as np
import pytest

from dvpmvs import _fusion
from dvpmvs.fusion import (
    FusionError,
    FusionOptions,
    _supporting_images,
    read_visibility,
    write_visibility,
)

# Also run on the other Pythons `make test` checks (scripts/other_pythons.py).
pytestmark = pytest.mark.smoke

_W, _H, _F = 32, 24, 100.0
_K = np.array([[_F, 0, 15.5], [0, _F, 11.5], [0, 0, 1]])


def _fuse_plane(neighbour_depths, median):
    """A reference camera and one neighbour per entry of ``neighbour_depths``, all looking down +z
    at the plane z = 10 (the neighbours 0.1 m apart along x, so the plane shifts 1 px between
    them); neighbour j's depth map holds ``neighbour_depths[j]`` everywhere. Returns the fused
    points (H, W, 3), the valid mask of the reference and the masks of agreeing neighbours."""
    n = len(neighbour_depths)
    depth = np.full((_H, _W), 10.0, np.float32)
    normal = np.zeros((_H, _W, 3), np.float32)
    normal[..., 2] = -1  # facing the cameras
    rgb = np.zeros((_H, _W, 3), np.uint8)
    nb_depth = np.stack([np.full((_H, _W), d, np.float32) for d in neighbour_depths])
    nb_normal = np.repeat(normal[None], n, axis=0)
    nb_rgb = np.zeros((n, _H, _W, 3), np.uint8)
    nb_size = np.tile(np.array([_W, _H], np.int32), (n, 1))
    nb_K = np.repeat(_K[None], n, axis=0)
    nb_R = np.repeat(np.eye(3)[None], n, axis=0)
    nb_t = np.array([[-0.1 * (j + 1), 0.0, 0.0] for j in range(n)])  # centres at x = 0.1, 0.2, ...
    out_point = np.zeros((_H, _W, 3), np.float32)
    out_normal = np.zeros((_H, _W, 3), np.float32)
    out_rgb = np.zeros((_H, _W, 3), np.float32)
    valid = np.zeros((_H, _W), np.uint8)
    agreeing = np.zeros((_H, _W), np.uint64)
    _fusion.fuse_view(
        depth,
        normal,
        rgb,
        _K,
        np.eye(3),
        np.zeros(3),
        np.zeros((_H, _W), np.uint8),
        nb_depth,
        nb_normal,
        nb_rgb,
        nb_size,
        nb_K,
        nb_R,
        nb_t,
        np.zeros((n, _H, _W), np.uint8),
        2.0,
        0.01,
        30.0,
        2,
        out_point,
        out_normal,
        out_rgb,
        valid,
        agreeing,
        1,
        median,
    )
    return out_point, valid.astype(bool), agreeing


def test_median_ignores_a_neighbour_within_tolerance_but_off_the_surface():
    # Three views on the plane and one 0.8 % behind it: inside the 1 % tolerance, so it agrees.
    depths = [10.0, 10.0, 10.08]
    points, valid, _ = _fuse_plane(depths, median=True)
    inside = valid[:, 4:-4]  # pixels whose projection stays in every neighbour (1-3 px shifts)
    assert inside.all()
    assert np.allclose(points[:, 4:-4, 2], 10.0, atol=1e-5)  # median of 10, 10, 10, 10.08 (x2)
    points, valid, _ = _fuse_plane(depths, median=False)
    assert valid[:, 4:-4].all()
    assert np.allclose(points[:, 4:-4, 2], 10.02, atol=1e-4)  # the mean is pulled 0.2 % back
    # Depths on the plane: the pixel's own point whichever the average.
    for median in (True, False):
        points, valid, _ = _fuse_plane([10.0, 10.0, 10.0], median)
        ray = np.linalg.inv(_K) @ np.array([20.0, 12.0, 1.0])
        assert np.allclose(points[12, 20], 10.0 * ray, atol=1e-5)


def test_an_odd_count_takes_the_middle_point():
    # The reference and two neighbours: 10, 10.05 and 10.09 -> 10.05 (the mean would be ~10.047).
    points, valid, _ = _fuse_plane([10.05, 10.09], median=True)
    assert valid[:, 4:-4].all()
    assert np.allclose(points[:, 4:-4, 2], 10.05, atol=1e-5)


def test_each_kept_pixel_names_the_neighbours_that_agreed():
    # Neighbours 0, 2 and 3 on the plane, neighbour 1 5 % behind it (outside the 1 % tolerance).
    _, valid, agreeing = _fuse_plane([10.0, 10.5, 10.0, 10.0], median=True)
    inside = valid[:, 5:-5]
    assert inside.all()
    assert (agreeing[:, 5:-5] == 0b1101).all()
    assert (agreeing[~valid] == 0).all()
    # Neighbours 1 and 2 only: their bits, not neighbour 0's.
    _, valid, agreeing = _fuse_plane([10.5, 10.0, 10.0], median=True)
    assert valid[:, 5:-5].all() and (agreeing[:, 5:-5] == 0b110).all()


def test_supporting_images_come_from_the_masks():
    counts, images = _supporting_images(
        np.array([0b101, 0b010, 0, 1 << 40], np.uint64), [7] + list(range(41))
    )
    assert counts.tolist() == [3, 2, 1, 2]
    assert images.tolist() == [7, 0, 2, 7, 1, 7, 7, 40]


def test_visibility_file_round_trip_in_colmap_layout(tmp_path):
    path = tmp_path / "fused.ply.vis"
    write_visibility(path, np.array([2, 3, 1]), np.array([0, 4, 1, 2, 3, 9]))
    data = path.read_bytes()
    # uint64 point count, then per point a uint32 count and the uint32 indices (little-endian).
    assert data == struct.pack("<QIIIIIIIII", 3, 2, 0, 4, 3, 1, 2, 3, 1, 9)
    assert [v.tolist() for v in read_visibility(path)] == [[0, 4], [1, 2, 3], [9]]
    write_visibility(path, np.zeros(0), np.zeros(0))
    assert path.read_bytes() == struct.pack("<Q", 0) and read_visibility(path) == []
    with pytest.raises(ValueError, match="add up to 3"):
        write_visibility(path, np.array([3]), np.array([1, 2]))
    path.write_bytes(struct.pack("<QII", 2, 1, 5))
    with pytest.raises(FusionError, match="truncated"):
        read_visibility(path)


def test_point_average_is_validated():
    assert FusionOptions().point_average == "median"
    FusionOptions(point_average="mean")
    with pytest.raises(ValueError, match="point_average"):
        FusionOptions(point_average="trimmed")


def _corridor_with_true_maps(root, views):
    """The corridor scene (views of 128x96, 4 sources each) with its ground-truth depth and normal
    maps as the geometric maps to fuse."""
    import shutil

    from dvpmvs.evaluation.synthetic import SynthOptions, generate
    from dvpmvs.maps import Pass, map_path
    from dvpmvs.workspace import Workspace, write_stereo_configs

    generate(root, SynthOptions(scene="corridor", views=views, width=128, priors=False))
    names = sorted(p.name for p in (root / "images").iterdir())
    write_stereo_configs(root / "stereo", {name: "__auto__, 4" for name in names})
    for name in names:
        for kind in ("depth", "normal"):
            target = map_path(root / "stereo", name, kind, Pass.GEOMETRIC)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(root / "ground_truth" / f"{kind}_maps" / f"{name}.bin", target)
    return Workspace.open(root)


@pytest.mark.slow
def test_streamed_fusion_writes_the_cloud_in_memory_fusion_makes_with_flat_peak_memory(tmp_path):
    import tracemalloc

    import open3d as o3d

    from dvpmvs.fusion import fuse, fuse_to_ply, visibility_path, write_fused_cloud

    options = FusionOptions(max_neighbours=4, cache_views=6)
    peaks, points = {}, {}
    for views in (12, 36):
        workspace = _corridor_with_true_maps(tmp_path / f"corridor{views}", views)
        # The corridor's views overlap only their neighbours along the walk.
        assert (
            max(
                abs(int(s[:4]) - int(v.name[:4]))
                for v in workspace.reference_views()
                for s in v.sources
            )
            <= 6
        )
        streamed = tmp_path / f"streamed{views}.ply"
        tracemalloc.start()
        per_view = fuse_to_ply(workspace, streamed, options)
        peaks[views] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        points[views] = sum(per_view.values())
        # The same bytes as the cloud fused in memory and written whole.
        whole = tmp_path / f"whole{views}.ply"
        cloud = fuse(workspace, options)
        write_fused_cloud(whole, cloud)
        assert streamed.read_bytes() == whole.read_bytes()
        assert visibility_path(streamed).read_bytes() == visibility_path(whole).read_bytes()
        assert len(read_visibility(visibility_path(streamed))) == points[views] == len(cloud)
        read = o3d.t.io.read_point_cloud(str(streamed))
        np.testing.assert_array_equal(read.point["positions"].numpy(), cloud.points)
        np.testing.assert_array_equal(read.point["colors"].numpy(), cloud.colors)
        assert not [p for p in tmp_path.glob(".*") if p.is_file()]  # no temporaries left
    # Three times the views and the points; the memory of a neighbourhood (measured: 19.6 and
    # 23.3 MB, the points 82k and 220k).
    assert points[36] > 2.5 * points[12]
    assert peaks[36] < 1.35 * peaks[12]
