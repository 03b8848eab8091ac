"""ETH3D-format ground truth made of depth maps: one scan per view.

A view's scan holds its depth map's surface points (one per pixel) that at least one other
view's depth map confirms: seen from that view at the depth it measures there, within a relative
``tolerance``. The scanner sits at the camera centre. A scan frame has the camera's optical axis
as x and "up" (the image's -y) as z, because ETH3D's beam search uses spherical coordinates
around the scan's z axis, like a tripod-mounted laser scanner. The beams of a pixel-grid scan
are ~1/f rad apart, far wider than a laser scanner's 0.011 degree divergence, so
:func:`beam_parameters` gives a divergence of 0.75 px that makes neighbouring beams overlap;
pass it to the official program as ``--beam_divergence_halfangle_deg``.

``dvpmvs synth`` writes its exact depth this way, ``dvpmvs import`` of an RGB-D sequence its
sensor's depth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dvpmvs.evaluation.pointclouds import write_meshlab_project, write_point_cloud
from dvpmvs.evaluation.portable import matmul, transposed_matvec

# Scan frame -> camera frame: scan x = optical axis, scan y = image left, scan z = image up.
CAM_FROM_SCAN = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


def backproject(
    depth: np.ndarray,
    K: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    rows: np.ndarray,
    cols: np.ndarray,
) -> np.ndarray:
    """The world points of the pixels (``rows``, ``cols``) of a depth map, in the dense stage's
    convention: the pixel (row, col) is the image point (col, row)."""
    z = depth[rows, cols].astype(np.float64)
    x = (cols - K[0, 2]) / K[0, 0] * z
    y = (rows - K[1, 2]) / K[1, 1] * z
    pc = np.stack([x, y, z], axis=1)
    return matmul(pc - t, R)


def visible_in(points, R, t, K, depth, tolerance: float = 0.01) -> np.ndarray:
    """Which world ``points`` the view (``R``, ``t``, ``K``) sees at the depth its map ``depth``
    holds there, within ``tolerance`` of the depth (the neighbouring pixel's surface, not an
    occluder)."""
    h, w = depth.shape
    pc = matmul(points, R.T) + t
    z = pc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = K[0, 0] * pc[:, 0] / z + K[0, 2]
        y = K[1, 1] * pc[:, 1] / z + K[1, 2]
    col = np.round(x)
    row = np.round(y)
    inside = (z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    visible = np.zeros(len(points), bool)
    idx = np.flatnonzero(inside)
    d = depth[row[idx].astype(np.int64), col[idx].astype(np.int64)]
    visible[idx] = (d > 0) & (np.abs(d - z[idx]) <= tolerance * z[idx])
    return visible


def covisible(
    points: np.ndarray, cams: list, depths: list, skip: int, K: np.ndarray, tolerance: float = 0.01
) -> np.ndarray:
    """How many views other than ``skip`` see each world point (:func:`visible_in`)."""
    count = np.zeros(len(points), np.int32)
    for j, ((R, t), depth) in enumerate(zip(cams, depths)):
        if j == skip:
            continue
        count += visible_in(points, R, t, K, depth, tolerance)
    return count


def beam_parameters(focal: float) -> dict:
    """The ETH3D program's parameters for scans of a pixel grid of focal length ``focal`` px."""
    return {
        "voxel_size": 0.01,
        "beam_start_radius_meters": 0.0,
        "beam_divergence_halfangle_deg": float(np.rad2deg(0.75 / focal)),
    }


def write_scans(
    ground_truth: Path,
    stems: list[str],
    depths: list[np.ndarray],
    cams: list[tuple[np.ndarray, np.ndarray]],
    K: np.ndarray,
    tolerance: float = 0.01,
    progress=None,
) -> int:
    """Write ``ground_truth/scans/<stem>.ply`` per view and ``scan_alignment.mlp`` listing them;
    ``cams``: each view's world-to-camera (``R``, ``t``). Returns the number of scan points."""
    entries, total = [], 0
    for i, (R, t) in enumerate(cams):
        if progress:
            progress(f"ground-truth scan {stems[i]}")
        rows, cols = np.nonzero(depths[i] > 0)
        world = backproject(depths[i], K, R, t, rows, cols)
        seen = covisible(world, cams, depths, i, K, tolerance) >= 1
        cam_points = matmul(world[seen], R.T) + t
        scan_points = matmul(cam_points, CAM_FROM_SCAN)  # rows: p_scan = CAM_FROM_SCAN^T p_cam
        total += len(scan_points)
        write_point_cloud(
            ground_truth / "scans" / f"{stems[i]}.ply", scan_points.astype(np.float32)
        )
        global_T_scan = np.eye(4)
        global_T_scan[:3, :3] = matmul(R.T, CAM_FROM_SCAN)
        global_T_scan[:3, 3] = transposed_matvec(-R, t)
        entries.append((f"scans/{stems[i]}.ply", global_T_scan))
    write_meshlab_project(ground_truth / "scan_alignment.mlp", entries)
    return total
