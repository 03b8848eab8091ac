import numpy as np
import pycolmap
import pytest

from dvpmvs import maps
from dvpmvs.maps import MapFormatError, Pass

# Also run on the other Pythons `make test` checks (scripts/other_pythons.py).
pytestmark = pytest.mark.smoke


@pytest.fixture
def depth():
    rng = np.random.default_rng(1)
    d = rng.uniform(1.0, 5.0, (37, 53)).astype(np.float32)
    d[3:9, 4:7] = 0.0  # pixels without an estimate
    return d


@pytest.fixture
def normals():
    rng = np.random.default_rng(2)
    n = rng.normal(size=(37, 53, 3)).astype(np.float32)
    n[..., 2] = -np.abs(n[..., 2])
    return (n / np.linalg.norm(n, axis=2, keepdims=True)).astype(np.float32)


def test_paths_follow_colmap_naming(tmp_path):
    assert (
        maps.map_path(tmp_path, "a/b.jpg", "depth", Pass.GEOMETRIC)
        == tmp_path / "depth_maps" / "a/b.jpg.geometric.bin"
    )
    assert (
        maps.map_path(tmp_path, "x.png", "normal", "photometric")
        == tmp_path / "normal_maps" / "x.png.photometric.bin"
    )
    with pytest.raises(ValueError, match="unknown map kind"):
        maps.map_path(tmp_path, "x.png", "colour", "photometric")


def test_depth_written_by_dvpmvs_is_read_by_pycolmap(tmp_path, depth):
    path = maps.write_depth_map(tmp_path / "depth_maps" / "a.png.geometric.bin", depth)
    colmap_map = pycolmap.DepthMap()
    colmap_map.read(str(path))
    np.testing.assert_array_equal(colmap_map.to_array(), depth)
    np.testing.assert_array_equal(maps.read_depth_map(path), depth)


def test_depth_written_by_pycolmap_is_read_by_dvpmvs(tmp_path, depth):
    path = tmp_path / "d.bin"
    pycolmap.DepthMap.from_array(depth, 1.0, 5.0).write(str(path))
    np.testing.assert_array_equal(maps.read_depth_map(path), depth)


def test_normal_maps_have_colmaps_planar_layout(tmp_path):
    # COLMAP's C++ reads value (row, col, c) at c*W*H + row*W + col; NormalMap.to_bitmap goes
    # through that accessor, so a map of two constant halves must render as two flat halves.
    normals = np.zeros((4, 6, 3), np.float32)
    normals[:, :3] = (0, 0, -1)
    normals[:, 3:] = (1, 0, 0)
    path = maps.write_normal_map(tmp_path / "n.bin", normals)
    colmap_map = pycolmap.NormalMap()
    colmap_map.read(str(path))
    bitmap = np.asarray(colmap_map.to_bitmap().to_array())
    assert (bitmap[:, :3] == bitmap[0, 0]).all() and (bitmap[:, 3:] == bitmap[0, 3]).all()
    assert not (bitmap[0, 0] == bitmap[0, 3]).all()
    raw = np.frombuffer(path.read_bytes()[len(b"6&4&3&") :], "<f4").reshape(3, 4, 6)
    np.testing.assert_array_equal(raw.transpose(1, 2, 0), normals)
    np.testing.assert_array_equal(maps.read_normal_map(path), normals)


def test_normals_round_trip(tmp_path, normals):
    np.testing.assert_array_equal(
        maps.read_normal_map(maps.write_normal_map(tmp_path / "n.bin", normals)), normals
    )


def test_extra_maps_use_colmaps_container(tmp_path, depth, normals):
    cost = maps.write_extra_map(tmp_path / "cost.bin", depth)
    colmap_map = pycolmap.DepthMap()
    colmap_map.read(str(cost))  # one channel: COLMAP's own reader agrees with our layout
    np.testing.assert_array_equal(colmap_map.to_array(), depth)
    three = maps.write_extra_map(tmp_path / "three.bin", normals)
    assert three.read_bytes() == maps.write_normal_map(tmp_path / "n.bin", normals).read_bytes()
    visibility = np.random.default_rng(3).uniform(size=(37, 53, 6)).astype(np.float32)
    np.testing.assert_array_equal(
        maps.read_extra_map(maps.write_extra_map(tmp_path / "v.bin", visibility)), visibility
    )
    labels = np.arange(37 * 53, dtype=np.int32).reshape(37, 53)
    np.testing.assert_array_equal(
        maps.read_extra_map(maps.write_extra_map(tmp_path / "l.bin", labels)), labels
    )


def test_truncated_map_is_a_clear_error(tmp_path, depth):
    path = maps.write_depth_map(tmp_path / "d.bin", depth)
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(MapFormatError, match="truncated or corrupt"):
        maps.read_depth_map(path)


def test_garbage_file_is_a_clear_error(tmp_path):
    path = tmp_path / "d.bin"
    path.write_bytes(b"hello world, not a map")
    with pytest.raises(MapFormatError, match="not a COLMAP map"):
        maps.read_depth_map(path)
    with pytest.raises(MapFormatError, match="map file not found"):
        maps.read_depth_map(tmp_path / "missing.bin")


def test_wrong_channel_count(tmp_path, depth):
    path = maps.write_depth_map(tmp_path / "d.bin", depth)
    with pytest.raises(MapFormatError, match="a normal map has 3 channel"):
        maps.read_normal_map(path)


def test_nan_values_are_refused_on_write_and_detected_on_read(tmp_path, depth):
    bad = depth.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        maps.write_depth_map(tmp_path / "d.bin", bad)
    pycolmap.DepthMap.from_array(bad, 1.0, 5.0).write(str(tmp_path / "nan.bin"))
    with pytest.raises(MapFormatError, match="NaN"):
        maps.read_depth_map(tmp_path / "nan.bin")


def test_failed_write_leaves_the_previous_file_and_no_temporary(tmp_path, depth):
    path = maps.write_depth_map(tmp_path / "d.bin", depth)
    before = path.read_bytes()
    with pytest.raises(RuntimeError):
        with maps.atomic_path(path) as tmp:
            tmp.write_bytes(b"partial")
            raise RuntimeError("interrupted")
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d.bin"]
