"""Time opening a large COLMAP workspace (model parsing, depth ranges, view selection).

    python -m dvpmvs.evaluation.bench_workspace [--views 150] [--points 60000] [--out DIR]

Builds a synthetic sparse model (cameras on a line facing a slab of points, each point seen by
a random 15 % of the views that frame it), then reports the seconds ``Workspace.open`` takes
with ``__auto__, 10`` sources chosen by the default ``colmap_cfg`` selector.
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from dvpmvs.evaluation.geometry import look_at
from dvpmvs.workspace import Workspace, WorkspaceOptions


def build_model(
    root: Path, num_views: int, num_points: int, seed: int = 0
) -> pycolmap.Reconstruction:
    rng = np.random.default_rng(seed)
    width, height = 800, 600
    (root / "sparse").mkdir(parents=True, exist_ok=True)
    (root / "images").mkdir(exist_ok=True)
    camera = pycolmap.Camera(
        model="PINHOLE", width=width, height=height, params=[500, 500, 400, 300], camera_id=1
    )
    reconstruction = pycolmap.Reconstruction()
    reconstruction.add_camera_with_trivial_rig(camera)
    points = np.column_stack(
        [
            rng.uniform(-10, 10, num_points),
            rng.uniform(-3, 3, num_points),
            rng.uniform(8, 12, num_points),
        ]
    )
    K = camera.calibration_matrix()
    blank_png = cv2.imencode(".png", np.zeros((height, width), np.uint8))[1].tobytes()
    observations: dict[int, list[tuple[int, int]]] = {}
    for index in range(num_views):
        centre = np.array([rng.uniform(-8, 8), rng.uniform(-1, 1), 0.0])
        R, t = look_at(centre, centre + np.array([0.0, 0.0, 10.0]))
        cam = points @ R.T + t
        uv = cam @ K.T
        uv = uv[:, :2] / uv[:, 2:]
        seen = (
            (cam[:, 2] > 0)
            & (uv[:, 0] >= 0)
            & (uv[:, 0] < width)
            & (uv[:, 1] >= 0)
            & (uv[:, 1] < height)
        )
        seen &= rng.uniform(size=num_points) < 0.15
        name = f"{index:04d}.png"
        image = pycolmap.Image(name=name, keypoints=uv[seen], camera_id=1, image_id=index + 1)
        reconstruction.add_image_with_trivial_frame(
            image, pycolmap.Rigid3d(pycolmap.Rotation3d(R), t)
        )
        for point2d, point in enumerate(np.flatnonzero(seen)):
            observations.setdefault(int(point), []).append((index + 1, point2d))
        (root / "images" / name).write_bytes(blank_png)  # Workspace.open reads each image's header
    for point, obs in observations.items():
        if len(obs) >= 2:
            track = pycolmap.Track()
            for image_id, point2d in obs:
                track.add_element(image_id, point2d)
            reconstruction.add_point3D(points[point], track)
    reconstruction.write(str(root / "sparse"))
    return reconstruction


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=150)
    parser.add_argument("--points", type=int, default=60000)
    parser.add_argument(
        "--out", type=Path, default=None, help="where to build the model (default: a temp dir)"
    )
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)
    with tempfile.TemporaryDirectory() as tmp:
        root = args.out or Path(tmp) / "ws"
        reconstruction = build_model(root, args.views, args.points)
        observations = reconstruction.compute_num_observations()
        start = time.perf_counter()
        workspace = Workspace.open(root, WorkspaceOptions(default_num_sources=10))
        seconds = time.perf_counter() - start
    print(
        f"views {len(workspace)}  points {reconstruction.num_points3D()}  observations {observations}  "
        f"Workspace.open {seconds:.2f} s"
    )


if __name__ == "__main__":
    main()
