"""Small COLMAP workspaces made by the tests themselves, written with pycolmap.

The scene: ``num_views`` cameras on an arc looking at a slab of random points (z in [3.5, 4.5]); every
3D point is projected into the views that see it, so tracks, keypoints and depths are exact.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pycolmap

from dvpmvs.evaluation.geometry import look_at


def make_workspace(
    root: Path,
    num_views: int = 5,
    width: int = 64,
    height: int = 48,
    focal: float = 60.0,
    camera_model: str = "PINHOLE",
    num_points: int = 400,
    text: bool = False,
    layout_subdir: str = "",
    patch_match_cfg: str | None = "auto",
    num_auto: int = 2,
    seed: int = 0,
) -> dict:
    """Write a COLMAP dense workspace under ``root``; returns the ground truth used to build it."""
    rng = np.random.default_rng(seed)
    root = Path(root)
    (root / "images").mkdir(parents=True, exist_ok=True)
    model_dir = root / "sparse" / layout_subdir
    model_dir.mkdir(parents=True, exist_ok=True)
    (root / "stereo").mkdir(exist_ok=True)

    # A slab of points 3.5 to 4.5 units in front of the first camera.
    points = np.column_stack(
        [
            rng.uniform(-1.5, 1.5, num_points),
            rng.uniform(-1.0, 1.0, num_points),
            rng.uniform(3.5, 4.5, num_points),
        ]
    )
    cx, cy = width / 2.0, height / 2.0
    if camera_model == "PINHOLE":
        params = [focal, focal * 1.01, cx, cy]
    elif camera_model == "SIMPLE_PINHOLE":
        params = [focal, cx, cy]
    elif camera_model == "OPENCV":
        params = [focal, focal, cx, cy, 0.01, 0.0, 0.0, 0.0]
    else:
        raise ValueError(camera_model)
    camera = pycolmap.Camera(
        model=camera_model, width=width, height=height, params=params, camera_id=1
    )
    K = camera.calibration_matrix()

    reconstruction = pycolmap.Reconstruction()
    reconstruction.add_camera_with_trivial_rig(camera)
    names, poses = [], []
    observations: dict[int, list[tuple[int, np.ndarray]]] = {}
    for index in range(num_views):
        angle = np.deg2rad(-20 + 40 * index / max(1, num_views - 1))
        center = np.array([4.0 * np.sin(angle), 0.2 * index, 4.0 - 4.0 * np.cos(angle)])
        R, t = look_at(center, np.array([0.0, 0.0, 4.0]))
        cam = points @ R.T + t
        uv = cam @ K.T
        uv = uv[:, :2] / uv[:, 2:]
        visible = (
            (cam[:, 2] > 0)
            & (uv[:, 0] >= 0)
            & (uv[:, 0] < width)
            & (uv[:, 1] >= 0)
            & (uv[:, 1] < height)
        )
        name = f"view_{index:02d}.png"
        keypoints = uv[visible].astype(np.float64)
        image = pycolmap.Image(name=name, keypoints=keypoints, camera_id=1, image_id=index + 1)
        reconstruction.add_image_with_trivial_frame(
            image, pycolmap.Rigid3d(pycolmap.Rotation3d(R), t)
        )
        for point2d_idx, point_idx in enumerate(np.flatnonzero(visible)):
            observations.setdefault(int(point_idx), []).append((index + 1, point2d_idx))
        texture = (rng.uniform(0, 255, (height, width, 3))).astype(np.uint8)
        cv2.imwrite(str(root / "images" / name), texture)
        names.append(name)
        poses.append((R, t))

    for point_idx, obs in observations.items():
        if len(obs) < 2:
            continue
        track = pycolmap.Track()
        for image_id, point2d_idx in obs:
            track.add_element(image_id, point2d_idx)
        reconstruction.add_point3D(points[point_idx], track)

    if text:
        reconstruction.write_text(str(model_dir))
    else:
        reconstruction.write(str(model_dir))

    if patch_match_cfg == "auto":
        cfg = "".join(f"{name}\n__auto__, {num_auto}\n" for name in names)
    else:
        cfg = patch_match_cfg
    if cfg is not None:
        (root / "stereo" / "patch-match.cfg").write_text(cfg)
        (root / "stereo" / "fusion.cfg").write_text("".join(f"{name}\n" for name in names))
    return {
        "names": names,
        "poses": poses,
        "K": K,
        "points": points,
        "reconstruction": reconstruction,
    }
