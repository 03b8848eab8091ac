"""Point clouds on disk: binary PLY through Open3D, written atomically."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d

from dvpmvs.errors import DvpmvsError
from dvpmvs.maps import atomic_path

__all__ = ["PointCloudError", "write_point_cloud"]


class PointCloudError(DvpmvsError, OSError):
    """A point cloud could not be written."""


def write_point_cloud(
    path: str | Path,
    points: np.ndarray,
    colors: np.ndarray | None = None,
    normals: np.ndarray | None = None,
) -> Path:
    """Write a binary PLY atomically: float32 positions (what the ETH3D program requires),
    float32 normals, uint8 colours (``colors`` as uint8 or floats in [0, 1])."""
    path = Path(path)
    tensor = o3d.core.Tensor
    cloud = o3d.t.geometry.PointCloud(tensor(np.ascontiguousarray(np.asarray(points, np.float32).reshape(-1, 3))))
    if colors is not None:
        colors = np.asarray(colors)
        if colors.dtype != np.uint8:
            colors = np.clip(np.round(colors.astype(np.float64) * 255), 0, 255).astype(np.uint8)
        cloud.point.colors = tensor(np.ascontiguousarray(colors.reshape(-1, 3)))
    if normals is not None:
        cloud.point.normals = tensor(np.ascontiguousarray(np.asarray(normals, np.float32).reshape(-1, 3)))
    if len(cloud.point.positions) == 0:
        return _write_empty_ply(path, colors is not None, normals is not None)
    # Open3D picks the writer from the suffix, so the temporary name keeps it.
    with atomic_path(path, suffix=".tmp.ply") as tmp:
        if not o3d.t.io.write_point_cloud(str(tmp), cloud, write_ascii=False):
            raise PointCloudError(f"could not write the point cloud {path}")
    return path


def _write_empty_ply(path: Path, colors: bool, normals: bool) -> Path:
    """A valid PLY with no vertices (Open3D refuses to write one), same properties as a full one."""
    lines = ["ply", "format binary_little_endian 1.0", "element vertex 0",
             "property float x", "property float y", "property float z"]
    if normals:
        lines += ["property float nx", "property float ny", "property float nz"]
    if colors:
        lines += ["property uchar red", "property uchar green", "property uchar blue"]
    lines.append("end_header")
    with atomic_path(path) as tmp:
        tmp.write_bytes(("\n".join(lines) + "\n").encode("ascii"))
    return path
