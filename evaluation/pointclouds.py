"""Point clouds and ETH3D ground truth on disk: PLY files and MeshLab projects.

ETH3D ships its laser scans as a MeshLab project (``scan_alignment.mlp``): one ``MLMesh`` per
scan, each with a PLY file (relative to the project) and a 4x4 ``MLMatrix44`` that maps the
scan's points into the global frame (``global_T_mesh``, written row by row). The scanner sits at
the origin of each scan's own frame; the evaluation's beam model relies on that.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dvpmvs.errors import DvpmvsError
from dvpmvs.maps import atomic_path
from dvpmvs.pointcloud import (  # write re-exported: the harness writes clouds too
    PlyFormatError,
    read_ply,
    write_point_cloud,
)

if TYPE_CHECKING:
    import open3d as o3d

__all__ = [
    "GroundTruthError",
    "Scan",
    "read_points",
    "read_point_cloud",
    "write_point_cloud",
    "read_meshlab_project",
    "write_meshlab_project",
    "load_ground_truth",
]


class GroundTruthError(DvpmvsError, ValueError):
    """A ground-truth or reconstruction file is missing or unreadable."""


@dataclass(frozen=True)
class Scan:
    """One ground-truth scan: points in the scan frame, and the scan-to-global transform."""

    label: str
    path: Path
    global_T_scan: np.ndarray  # 4x4 float64
    points: np.ndarray | None = None  # (N, 3) float32 in the scan frame; None until loaded

    def global_points(self) -> np.ndarray:
        """The scan's points in the global frame, computed as the official program does (PCL's
        transformPointCloud with SSE: float32, m0 x + (m1 y + (m2 z + m3)) per row, no fused
        multiply-add; checked bit for bit against its completeness cloud).
        Synthetic scans lie on planes that coincide with voxel faces, where a last-bit difference
        moves a point into the next voxel of the completeness average."""
        T = self.global_T_scan.astype(np.float32)
        p = np.asarray(self.points, np.float32)
        x, y, z = p[:, 0], p[:, 1], p[:, 2]
        return np.stack(
            [T[r, 0] * x + (T[r, 1] * y + (T[r, 2] * z + T[r, 3])) for r in range(3)], axis=1
        )


def read_point_cloud(path: str | Path) -> o3d.geometry.PointCloud:
    """Read a PLY by its header (:func:`dvpmvs.pointcloud.read_ply`; other formats through
    Open3D); a clear error for a missing, empty, damaged or non-finite file."""
    _, cloud = _read(Path(path), as_open3d=True)
    return cloud


def read_points(path: str | Path) -> np.ndarray:
    """Positions of a point cloud file as an (N, 3) float32 array, checked as
    :func:`read_point_cloud` checks them (a PLY is read without loading Open3D)."""
    points, _ = _read(Path(path), as_open3d=False)
    return np.asarray(points, dtype=np.float32).reshape(-1, 3)


def _read(path: Path, as_open3d: bool):
    """(positions, Open3D cloud or None) of a point cloud file, after the checks."""
    if not path.is_file():
        raise GroundTruthError(f"point cloud {path} does not exist")
    declared = _check_ply_complete(path)
    cloud = None
    if declared is not None:
        try:
            ply = read_ply(path)
        except PlyFormatError as exc:
            raise GroundTruthError(str(exc)) from None
        points = ply.points
        if as_open3d:
            cloud = ply.to_open3d()
    else:
        import open3d as o3d  # the formats other than PLY

        cloud = o3d.io.read_point_cloud(str(path))
        points = np.asarray(cloud.points)
    count = len(points)
    if declared is not None and count != declared:
        raise GroundTruthError(
            f"{path} declares {declared:,} points in its header but {count:,} were read: the "
            f"file is corrupt; write or copy it again"
        )
    if not count and declared is None:
        raise GroundTruthError(
            f"{path} could not be read as a point cloud (corrupt or unsupported)"
        )
    finite = np.isfinite(np.asarray(points)).all(axis=1)
    if not finite.all():
        raise GroundTruthError(
            f"{path}: {int((~finite).sum()):,} of its {count:,} points have NaN or infinite "
            f"coordinates (e.g. point {int(np.flatnonzero(~finite)[0])}); remove them from the file"
        )
    return points, cloud


_PLY_TYPE_SIZES = {
    "char": 1,
    "uchar": 1,
    "int8": 1,
    "uint8": 1,
    "short": 2,
    "ushort": 2,
    "int16": 2,
    "uint16": 2,
    "int": 4,
    "uint": 4,
    "int32": 4,
    "uint32": 4,
    "float": 4,
    "float32": 4,
    "double": 8,
    "float64": 8,
}


def _check_ply_complete(path: Path) -> int | None:
    """The vertex count a PLY header declares, after checking that the file holds that many
    (None: not a PLY). Binary files must be as long as their header's elements need (elements
    with list properties, which vary in size, leave this to the count of vertices read); ASCII
    files need a non-empty line per declared record."""
    with open(path, "rb") as handle:
        data = handle.read(65536)
    if not data.startswith(b"ply"):
        return None
    end = data.find(b"end_header")
    if end < 0:
        raise GroundTruthError(
            f"{path}: a PLY header without end_header; the file is truncated or corrupt"
        )
    body = data.index(b"\n", end) + 1 if b"\n" in data[end:] else len(data)
    file_size = path.stat().st_size
    fmt, elements = None, []  # [name, count, record bytes or None (lists)]
    properties: dict[str, list[str]] = {}  # element name -> its property names
    for line in data[:end].decode("ascii", "replace").splitlines():
        parts = line.split()
        if parts[:1] == ["format"] and len(parts) >= 2:
            fmt = parts[1]
        elif parts[:1] == ["element"] and len(parts) == 3 and parts[2].isdigit():
            elements.append([parts[1], int(parts[2]), 0])
            properties.setdefault(parts[1], [])
        elif parts[:1] == ["property"] and elements:
            properties[elements[-1][0]].append(parts[-1])
            if elements[-1][2] is not None:
                size = (
                    _PLY_TYPE_SIZES.get(parts[1])
                    if len(parts) >= 3 and parts[1] != "list"
                    else None
                )
                elements[-1][2] = None if size is None else elements[-1][2] + size
    vertices = next((count for name, count, _ in elements if name == "vertex"), None)
    if vertices is None:
        raise GroundTruthError(
            f"{path}: a PLY without a vertex element (its elements: "
            f"{', '.join(name for name, _, _ in elements) or 'none'}); a point cloud has one"
        )
    lacking = [axis for axis in ("x", "y", "z") if axis not in properties["vertex"]]
    if lacking:
        what = "property" if len(lacking) == 1 else "properties"
        raise GroundTruthError(
            f"{path}: its vertices have no {', '.join(lacking)} {what} "
            f"(they have: {', '.join(properties['vertex']) or 'none'}); a point cloud needs x, y, z"
        )
    if fmt == "ascii":
        needed = sum(count for _, count, _ in elements)
        with open(path, "rb") as handle:
            handle.seek(body)
            records = sum(1 for line in handle if line.strip())
        if records < needed:
            raise GroundTruthError(
                f"{path} is truncated: its header declares {needed:,} records, the file holds "
                f"fewer; write or copy it again"
            )
    elif fmt is not None and all(size is not None for _, _, size in elements):
        needed = sum(count * size for _, count, size in elements)
        if file_size - body < needed:
            raise GroundTruthError(
                f"{path} is truncated: its header declares {vertices or 0:,} points ({needed:,} bytes of data), the "
                f"file holds {file_size - body:,} bytes after the header; write or copy it again"
            )
    return vertices


def read_meshlab_project(path: str | Path, load_points: bool = True) -> list[Scan]:
    """The scans of a MeshLab project (first ``MeshGroup``, as the ETH3D program reads it)."""
    path = Path(path)
    if not path.is_file():
        raise GroundTruthError(f"MeshLab project {path} does not exist")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise GroundTruthError(f"{path} is not a valid MeshLab project: {exc}") from None
    group = root.find("MeshGroup")
    if group is None:
        raise GroundTruthError(f"{path} has no <MeshGroup>: not a MeshLab project")
    scans = []
    for mesh in group.findall("MLMesh"):
        filename = mesh.get("filename")
        if not filename:
            raise GroundTruthError(f"{path}: an <MLMesh> has no filename")
        matrix = mesh.find("MLMatrix44")
        try:
            values = [float(v) for v in (matrix.text or "").split()] if matrix is not None else []
        except ValueError:
            values = []
        if len(values) != 16:
            raise GroundTruthError(f"{path}: the matrix of {filename} does not have 16 numbers")
        T = np.array(values, dtype=np.float64).reshape(4, 4)
        if not np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0]):
            raise GroundTruthError(
                f"{path}: the last row of the matrix of {filename} is not (0, 0, 0, 1)"
            )
        scan_path = Path(filename) if Path(filename).is_absolute() else path.parent / filename
        points = read_points(scan_path) if load_points else None
        scans.append(Scan(mesh.get("label") or filename, scan_path, T, points))
    if not scans:
        raise GroundTruthError(f"{path} lists no scans")
    return scans


def write_meshlab_project(path: str | Path, scans: list[tuple[str, np.ndarray]]) -> Path:
    """Write a MeshLab project listing ``(filename relative to the project, global_T_scan)``."""
    path = Path(path)
    lines = ["<!DOCTYPE MeshLabDocument>", "<MeshLabProject>", " <MeshGroup>"]
    for filename, T in scans:
        T = np.asarray(T, dtype=np.float64).reshape(4, 4)
        lines.append(f'  <MLMesh label="{filename}" filename="{filename}">')
        lines.append("   <MLMatrix44>")
        lines.extend(" ".join(repr(float(v)) for v in row) + " " for row in T)
        lines.append("</MLMatrix44>")
        lines.append("  </MLMesh>")
    lines += [" </MeshGroup>", " <RasterGroup/>", "</MeshLabProject>", ""]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines))
    return path


def load_ground_truth(path: str | Path) -> list[Scan] | np.ndarray:
    """Scans from an ``.mlp`` project, or the points of a plain point-cloud file."""
    path = Path(path)
    if path.suffix.lower() == ".mlp":
        return read_meshlab_project(path)
    return read_points(path)
