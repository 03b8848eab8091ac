"""Leaderboard submission files.

- ETH3D: ``<scene>.ply`` (float32 x, y, z) and ``<scene>.txt`` containing ``runtime <seconds>``.
- Tanks and Temples: ``<scene>.ply`` and ``<scene>.log``, the camera-to-world trajectory of the
  images (used by the server to align the reconstruction), in the workspace's image order.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap

from dvpmvs.errors import DvpmvsError
from dvpmvs.maps import atomic_path
from dvpmvs.evaluation.pointclouds import read_point_cloud, write_point_cloud
from dvpmvs.evaluation.tanks import write_log

__all__ = ["write_eth3d_submission", "write_tanks_submission"]


def _copy_cloud(cloud_path: str | Path, target: Path) -> None:
    cloud = read_point_cloud(cloud_path)
    colors = np.asarray(cloud.colors) if cloud.has_colors() else None
    normals = np.asarray(cloud.normals) if cloud.has_normals() else None
    write_point_cloud(target, np.asarray(cloud.points), colors, normals)


def write_eth3d_submission(out_dir: str | Path, scene: str, cloud_path: str | Path, runtime_seconds: float) -> list[Path]:
    if not runtime_seconds >= 0:
        raise DvpmvsError(f"runtime must be a non-negative number of seconds, got {runtime_seconds}")
    out_dir = Path(out_dir)
    ply, txt = out_dir / f"{scene}.ply", out_dir / f"{scene}.txt"
    _copy_cloud(cloud_path, ply)
    with atomic_path(txt) as tmp:
        tmp.write_text(f"runtime {runtime_seconds:.2f}\n")
    return [ply, txt]


def write_tanks_submission(out_dir: str | Path, scene: str, cloud_path: str | Path,
                           sparse_model: str | Path) -> list[Path]:
    """``sparse_model`` is the COLMAP model whose cameras the reconstruction was made from."""
    out_dir = Path(out_dir)
    try:
        recon = pycolmap.Reconstruction(str(sparse_model))
    except Exception as exc:  # pycolmap raises plain RuntimeErrors for unreadable models
        raise DvpmvsError(f"cannot read the COLMAP model {sparse_model}: {exc}") from None
    images = sorted(recon.images.values(), key=lambda im: im.name)
    if not images:
        raise DvpmvsError(f"the COLMAP model {sparse_model} has no images")
    poses = []
    for im in images:
        world_from_cam = np.eye(4)
        world_from_cam[:3, :] = im.cam_from_world().inverse().matrix()
        poses.append(world_from_cam)
    ply, log = out_dir / f"{scene}.ply", out_dir / f"{scene}.log"
    _copy_cloud(cloud_path, ply)
    write_log(log, poses)
    return [ply, log]
