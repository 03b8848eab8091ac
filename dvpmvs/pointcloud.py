"""Point clouds on disk: PLY read by its header (plyfile), binary PLY written atomically.

Open3D's PLY reader assumes the vertex properties in the order x, y, z, ...: a valid file that
declares them in another order (``z y x``, or a property before x) is read as garbage, with a
warning and the points returned. Every cloud dvpmvs reads (evaluation, submission, meshing) goes
through :func:`read_ply`, which honours the header (property order and types, endianness, ASCII)
or refuses the file naming what is wrong."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import plyfile

from dvpmvs.errors import DvpmvsError
from dvpmvs.maps import atomic_path

if TYPE_CHECKING:
    import open3d as o3d

__all__ = [
    "PlyFormatError",
    "PlyCloud",
    "is_ply",
    "ply_element_counts",
    "ply_header",
    "read_ply",
    "read_cloud",
    "write_point_cloud",
]


class PlyFormatError(DvpmvsError, ValueError):
    """A PLY file cannot be read as a point cloud (damaged, or no x, y, z vertices)."""


_COLOUR_NAMES = (
    ("red", "green", "blue"),
    ("r", "g", "b"),
    ("diffuse_red", "diffuse_green", "diffuse_blue"),
)


class PlyCloud:
    """The vertices of a PLY file: ``points`` (N, 3) float64, ``colors`` (N, 3) float64 in [0, 1]
    or None, ``normals`` (N, 3) float64 or None."""

    __slots__ = ("path", "points", "colors", "normals")

    def __init__(
        self, path: Path, points: np.ndarray, colors: np.ndarray | None, normals: np.ndarray | None
    ):
        self.path, self.points, self.colors, self.normals = path, points, colors, normals

    def __len__(self) -> int:
        return len(self.points)

    def to_open3d(self) -> o3d.geometry.PointCloud:
        # Open3D is imported where it is used: reading a PLY (a report, an evaluation's input
        # check) needs none of it, and it is among the slowest imports of a command.
        import open3d as o3d

        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(self.points))
        if self.colors is not None:
            cloud.colors = o3d.utility.Vector3dVector(self.colors)
        if self.normals is not None:
            cloud.normals = o3d.utility.Vector3dVector(self.normals)
        return cloud


def is_ply(path: str | Path) -> bool:
    """Whether the file starts as a PLY does (``ply`` then a line end)."""
    with open(path, "rb") as handle:
        return handle.read(4) in (b"ply\n", b"ply\r")


def ply_element_counts(path: Path) -> tuple[int, int]:
    """The vertex and face counts a PLY header declares (without reading the data)."""
    counts = {"vertex": 0, "face": 0}
    with open(path, "rb") as f:
        for raw in f:
            line = raw.decode("ascii", "replace").strip()
            if line.startswith("element "):
                _, name, count = line.split()
                counts[name] = int(count)
            if line == "end_header":
                break
    return counts["vertex"], counts["face"]


def _columns(vertex: np.ndarray, names: tuple[str, ...]) -> np.ndarray:
    return np.stack([np.asarray(vertex[name], np.float64) for name in names], axis=1)


def read_ply(path: str | Path) -> PlyCloud:
    """The vertices of a PLY file, by its header: properties in any order and of any scalar type,
    ASCII or binary of either endianness. Colours (``red green blue``, integer types scaled by
    their maximum, floats as they are) and normals (``nx ny nz``) where the file has them.
    Raises :class:`PlyFormatError` naming the file for a damaged file (truncated data, a broken
    header) or one without ``vertex`` x, y, z; ``FileNotFoundError`` when it does not exist."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"point cloud {path} does not exist")
    try:
        # Memory-mapped: plyfile's plain reader goes row by row (seconds for a fused cloud,
        # against a millisecond); the columns are copied out below, so no mapping outlives the call.
        data = plyfile.PlyData.read(str(path), mmap="c")
    except (
        plyfile.PlyParseError,
        plyfile.PlyHeaderParseError,
        plyfile.PlyElementParseError,
        ValueError,
        EOFError,
        IndexError,
        UnicodeDecodeError,
    ) as exc:
        raise PlyFormatError(
            f"{path} cannot be read as a PLY file ({exc}); the file is damaged or truncated: "
            f"write or copy it again"
        ) from None
    _check_no_data_beyond_header(path, data)
    try:
        vertex = data["vertex"].data
    except KeyError:
        names = ", ".join(element.name for element in data.elements) or "none"
        raise PlyFormatError(
            f"{path}: a PLY without a vertex element (its elements: {names}); a point cloud has one"
        ) from None
    present = vertex.dtype.names or ()
    lacking = [axis for axis in ("x", "y", "z") if axis not in present]
    if lacking:
        what = "property" if len(lacking) == 1 else "properties"
        raise PlyFormatError(
            f"{path}: its vertices have no {', '.join(lacking)} {what} (they have: "
            f"{', '.join(present) or 'none'}); a point cloud needs x, y, z"
        )
    points = _columns(vertex, ("x", "y", "z"))
    colors = None
    for names in _COLOUR_NAMES:
        if all(name in present for name in names):
            kind = vertex.dtype[names[0]]
            colors = _columns(vertex, names)
            if kind.kind in "iu":
                colors /= float(np.iinfo(kind).max)
            break
    normals = (
        _columns(vertex, ("nx", "ny", "nz"))
        if all(n in present for n in ("nx", "ny", "nz"))
        else None
    )
    return PlyCloud(path, points, colors, normals)


def _check_no_data_beyond_header(path: Path, data: plyfile.PlyData) -> None:
    """A file holding more data than its header declares (a header's vertex count left from a
    smaller cloud) is damaged: reading the declared part alone would score a part of the cloud.
    Checked where the size is known from the header: binary elements without lists, and ASCII."""
    with path.open("rb") as handle:
        head = handle.read(1 << 16)
    end = head.find(b"end_header")
    newline = head.find(b"\n", end) if end >= 0 else -1
    if newline < 0:
        return
    declared = sum(element.count for element in data.elements)
    if data.text:
        with path.open("rb") as handle:
            handle.seek(newline + 1)
            rows = sum(1 for line in handle if line.strip())
        extra = f"{rows - declared} more row(s)" if rows > declared else None
    else:
        if any(isinstance(p, plyfile.PlyListProperty) for e in data.elements for p in e.properties):
            return
        size = newline + 1 + sum(e.count * e.dtype().itemsize for e in data.elements)
        actual = path.stat().st_size
        extra = f"{actual - size} more byte(s)" if actual > size else None
    if extra is not None:
        counts = ", ".join(f"{e.count:,} {e.name}" for e in data.elements)
        raise PlyFormatError(
            f"{path} holds {extra} than its header declares ({counts}): the header does not "
            f"describe the file (a count left from another cloud?); write it again"
        )


def read_cloud(path: str | Path) -> o3d.geometry.PointCloud:
    """A point cloud file as an Open3D cloud: a PLY through :func:`read_ply` (by its header),
    other formats (PCD, XYZ, PTS) through Open3D."""
    import open3d as o3d

    path = Path(path)
    if path.is_file() and is_ply(path):
        return read_ply(path).to_open3d()
    return o3d.io.read_point_cloud(str(path))


def write_point_cloud(
    path: str | Path,
    points: np.ndarray,
    colors: np.ndarray | None = None,
    normals: np.ndarray | None = None,
) -> Path:
    """Write a binary little-endian PLY atomically: float32 positions (what the ETH3D program
    requires), float32 normals, uint8 colours (``colors`` as uint8 or floats in [0, 1]).

    The file is byte for byte the one Open3D's tensor writer (``o3d.t.io.write_point_cloud``)
    makes of the same arrays, header comment included: the ground truth of the rendered scenes is
    hashed by its bytes (:mod:`dvpmvs.evaluation.scene_digest`) and was written that way. Writing
    it with numpy spares the commands that write a cloud Open3D's import (about a second)."""
    path = Path(path)
    points = np.asarray(points, np.float32).reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    columns = [points]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
        columns.append(np.asarray(normals, np.float32).reshape(-1, 3))
    if colors is not None:
        colors = np.asarray(colors)
        if colors.dtype != np.uint8:
            colors = np.clip(np.round(colors.astype(np.float64) * 255), 0, 255).astype(np.uint8)
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        columns.append(colors.reshape(-1, 3))
    if any(len(column) != len(points) for column in columns):
        raise ValueError(
            f"{path}: the colours or normals are not one per point ({len(points):,} points)"
        )
    vertices = np.empty(len(points), np.dtype(fields))
    names = iter(name for name, _ in fields)
    for column in columns:
        for k in range(3):
            vertices[next(names)] = column[:, k]
    # Open3D refuses to write an empty cloud: those files were written without its comment.
    header = ply_header(
        vertices.dtype, len(points), comment="Created by Open3D" if len(points) else None
    )
    with atomic_path(path) as tmp, open(tmp, "wb") as out:  # a full disk: atomic_path names it
        out.write(header)
        out.write(vertices.tobytes())
    return path


_PLY_TYPES = {"<f4": "float", "|u1": "uchar"}


def ply_header(vertex: np.dtype, count: int, comment: str | None = None) -> bytes:
    """The header of a binary little-endian PLY of ``count`` vertices laid out as ``vertex`` (a
    structured dtype of little-endian float32 and uint8 fields)."""
    lines = [
        "ply",
        "format binary_little_endian 1.0",
        *([f"comment {comment}"] if comment else []),
        f"element vertex {count}",
    ]
    lines += [f"property {_PLY_TYPES[vertex[name].str]} {name}" for name in vertex.names]
    return ("\n".join([*lines, "end_header"]) + "\n").encode("ascii")
