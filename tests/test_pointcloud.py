"""Point clouds on disk: PLY files are read by their header, whatever order, type and encoding
they declare, and damaged ones are refused by name."""

import numpy as np
import pytest

from dvpmvs.pointcloud import PlyFormatError, read_cloud, read_ply, write_point_cloud

# Also run on the other Pythons `make test` checks (scripts/other_pythons.py).
pytestmark = pytest.mark.smoke


def _write_ply(path, columns, fmt="binary_little_endian"):
    """A PLY with the vertex properties ``columns`` [(name, ply type, numpy dtype, values)] in
    that order, written by hand (no library's writer decides the layout)."""
    n = len(columns[0][3])
    header = ["ply", f"format {fmt} 1.0", f"element vertex {n}"]
    header += [f"property {kind} {name}" for name, kind, _, _ in columns]
    header.append("end_header")
    body = b""
    if fmt == "ascii":
        rows = zip(*(values for _, _, _, values in columns))
        body = "".join(" ".join(repr(v.item()) for v in row) + "\n" for row in rows).encode()
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(name, np.dtype(dt).newbyteorder(order)) for name, _, dt, _ in columns])
        record = np.empty(n, dtype)
        for name, _, _, values in columns:
            record[name] = values
        body = record.tobytes()
    path.write_bytes(("\n".join(header) + "\n").encode() + body)
    return path


@pytest.fixture
def points():
    rng = np.random.default_rng(0)
    return rng.normal(size=(50, 3)).astype(np.float32) * 10


@pytest.mark.parametrize("fmt", ["binary_little_endian", "binary_big_endian", "ascii"])
@pytest.mark.parametrize("order", ["zyx", "red-first", "xyz"])
def test_read_ply_honours_property_order_types_and_encoding(tmp_path, points, fmt, order):
    colours = (np.arange(150).reshape(50, 3) % 256).astype(np.uint8)
    columns = {
        "x": ("x", "float", np.float32, points[:, 0]),
        "y": ("y", "double", np.float64, points[:, 1]),
        "z": ("z", "float", np.float32, points[:, 2]),
    }
    colour_columns = [
        (c, "uchar", np.uint8, colours[:, i]) for i, c in enumerate(("red", "green", "blue"))
    ]
    if order == "zyx":
        layout = [columns["z"], columns["y"], columns["x"]] + colour_columns
    elif order == "red-first":
        layout = (
            colour_columns[:1] + [columns["x"], columns["y"], columns["z"]] + colour_columns[1:]
        )
    else:
        layout = [columns["x"], columns["y"], columns["z"]] + colour_columns
    cloud = read_ply(_write_ply(tmp_path / "c.ply", layout, fmt))
    np.testing.assert_array_equal(cloud.points, points.astype(np.float64))
    np.testing.assert_allclose(cloud.colors, colours / 255.0)
    assert cloud.normals is None
    o3d_cloud = read_cloud(tmp_path / "c.ply")
    np.testing.assert_array_equal(np.asarray(o3d_cloud.points), points.astype(np.float64))


def test_read_ply_round_trips_our_own_clouds(tmp_path, points):
    normals = points / np.linalg.norm(points, axis=1, keepdims=True)
    path = write_point_cloud(
        tmp_path / "ours.ply", points, colors=np.full((50, 3), 0.5), normals=normals
    )
    cloud = read_ply(path)
    np.testing.assert_array_equal(cloud.points, points.astype(np.float64))
    np.testing.assert_allclose(cloud.normals, normals, rtol=1e-6)
    np.testing.assert_allclose(cloud.colors, 128 / 255.0)


@pytest.mark.parametrize("count", [0, 1, 50])
def test_written_clouds_are_the_bytes_open3ds_writer_makes(tmp_path, points, count):
    # The rendered scenes' ground truth is hashed by its bytes and was written by Open3D's tensor
    # writer: ours must give the same files, for each combination of colours and normals.
    import open3d as o3d

    rng = np.random.default_rng(count)
    points = points[:count]
    floats, normals = rng.random((count, 3)), rng.normal(size=(count, 3))
    for colors in (None, floats, (floats * 255).astype(np.uint8)):
        for with_normals in (False, True):
            ours = write_point_cloud(
                tmp_path / "ours.ply", points, colors, normals if with_normals else None
            )
            if not count:
                assert read_ply(ours).points.shape == (0, 3)
                continue
            cloud = o3d.t.geometry.PointCloud(o3d.core.Tensor(points.astype(np.float32)))
            if colors is not None:
                as_bytes = (
                    colors if colors.dtype == np.uint8 else np.round(colors * 255).astype(np.uint8)
                )
                cloud.point.colors = o3d.core.Tensor(as_bytes)
            if with_normals:
                cloud.point.normals = o3d.core.Tensor(normals.astype(np.float32))
            assert o3d.t.io.write_point_cloud(
                str(tmp_path / "open3d.ply"), cloud, write_ascii=False
            )
            assert ours.read_bytes() == (tmp_path / "open3d.ply").read_bytes(), (
                colors is not None,
                with_normals,
            )


def test_damaged_ply_files_are_refused_by_name(tmp_path, points):
    layout = [(a, "float", np.float32, points[:, i]) for i, a in enumerate("xyz")]
    good = _write_ply(tmp_path / "good.ply", layout).read_bytes()
    (tmp_path / "truncated.ply").write_bytes(good[:-20])
    (tmp_path / "header.ply").write_bytes(
        good.replace(b"element vertex 50", b"element vertex fifty")
    )
    _write_ply(tmp_path / "noz.ply", layout[:2])
    (tmp_path / "faces.ply").write_bytes(
        b"ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int v\nend_header\n"
    )
    # A header that declares fewer vertices than the file holds: read, it would be a part.
    (tmp_path / "fewer.ply").write_bytes(good.replace(b"element vertex 50", b"element vertex 40"))
    text = _write_ply(tmp_path / "t.ply", layout, "ascii").read_bytes()
    (tmp_path / "fewer_ascii.ply").write_bytes(
        text.replace(b"element vertex 50", b"element vertex 40")
    )
    for name, words in [
        ("fewer", r"holds 120 more byte\(s\) than its header declares \(40 vertex\)"),
        ("fewer_ascii", r"holds 10 more row\(s\) than its header declares"),
        ("truncated", "damaged"),
        ("header", "damaged"),
        ("noz", "no z property"),
        ("faces", "without a vertex element"),
    ]:
        with pytest.raises(PlyFormatError, match=words) as info:
            read_ply(tmp_path / f"{name}.ply")
        assert f"{name}.ply" in str(info.value)


def test_evaluation_reads_a_reordered_ply_as_the_original(tmp_path, points):
    """The metric's reader (eval, submit) gets the same points from a file whose properties are
    declared z y x as from x y z: Open3D's own reader returns garbage for the first."""
    from dvpmvs.evaluation.pointclouds import read_points

    xyz = [(a, "float", np.float32, points[:, i]) for i, a in enumerate("xyz")]
    ordered = read_points(_write_ply(tmp_path / "xyz.ply", xyz))
    reordered = read_points(_write_ply(tmp_path / "zyx.ply", xyz[::-1]))
    np.testing.assert_array_equal(ordered, points)
    np.testing.assert_array_equal(reordered, points)
