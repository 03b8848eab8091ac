"""Our Tanks and Temples metric beside the official toolbox, on constructed clouds.

The official toolbox (github.com/isl-org/TanksAndTemples, ``python_toolbox/evaluation``, MIT
licence) is loaded from a checkout the user gives (``--toolbox``; nothing of it is kept here). It
was written for Open3D 0.9, whose ``o3d.registration`` is ``o3d.pipelines.registration`` today:
that name is mapped, nothing else (its arithmetic runs as written). Both sides start from the same
initial transform (the trajectory step is a RANSAC on camera centres, compared by the tests) and
run their three ICP rounds, crop, downsampling and distances.

Cases (:func:`cases`): a ground-truth surface (a room corner and a box, sampled every 5 mm), and
reconstructions of it with noise and a hole, plus 3 % outliers, plus geometry outside the crop
volume; and the cloud with outliers from an initial transform 1.5 degrees and 3 cm off, and also
2 % off in scale; at several thresholds.

    python -m dvpmvs.evaluation.experiments.tanks_agreement --toolbox PATH/TanksAndTemples [--json out.json]

Prints per case and threshold the precision, recall and F of both, and the largest difference.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import open3d as o3d


def _surface(step: float = 0.005) -> np.ndarray:
    """A room corner (floor and two walls, 2 m) and a box on the floor, sampled every ``step``."""
    g = np.arange(0.0, 2.0, step)
    a, b = np.meshgrid(g, g)
    floor = np.stack([a.ravel(), b.ravel(), np.zeros(a.size)], 1)
    wall_x = np.stack([np.zeros(a.size), a.ravel(), b.ravel()], 1)
    wall_y = np.stack([a.ravel(), np.zeros(a.size), b.ravel()], 1)
    h = np.arange(0.0, 0.4, step)
    c, d = np.meshgrid(h, h)
    box = [np.stack([0.8 + c.ravel(), 0.8 + d.ravel(), np.full(c.size, 0.4)], 1)]  # top
    for x in (0.8, 1.2):
        box.append(np.stack([np.full(c.size, x), 0.8 + c.ravel(), d.ravel()], 1))
    for y in (0.8, 1.2):
        box.append(np.stack([0.8 + c.ravel(), np.full(c.size, y), d.ravel()], 1))
    return np.concatenate([floor, wall_x, wall_y, *box])


def _rotation(degrees: float, axis=(0.3, 1.0, 0.2)) -> np.ndarray:
    import cv2

    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return cv2.Rodrigues(axis * np.deg2rad(degrees))[0]


def crop_volume_json(
    path: Path, lo: tuple[float, float, float], hi: tuple[float, float, float]
) -> Path:
    """An Open3D selection polygon volume (the format of a scene's ``<scene>.json``): the box
    ``lo``-``hi`` as a polygon in x, y and a z interval."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    path.write_text(
        json.dumps(
            {
                "axis_max": z1,
                "axis_min": z0,
                "class_name": "SelectionPolygonVolume",
                "orthogonal_axis": "Z",
                "version_major": 1,
                "version_minor": 0,
                "bounding_polygon": [[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]],
            }
        )
    )
    return path


def cases(
    seed: int = 0, step: float = 0.005
) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """name -> (reconstruction, ground truth, reconstruction-to-ground-truth initial transform);
    ``step``: the ground truth's sampling."""
    rng = np.random.default_rng(seed)
    gt = _surface(step)
    noisy = gt + rng.normal(0, 0.003, gt.shape)
    hole = np.linalg.norm(noisy[:, :2] - [1.5, 1.5], axis=1) > 0.25  # a hole in the floor
    base = noisy[hole & (rng.random(len(noisy)) < 0.6)]
    lo, hi = gt.min(axis=0), gt.max(axis=0)
    outliers = rng.uniform(lo - 0.3, hi + 0.3, (int(0.03 * len(base)), 3))
    dirty = np.concatenate([base, outliers])
    outside = np.concatenate(
        [dirty, rng.uniform([2.6, 0, 0], [3.4, 2, 1], (20000, 3))]
    )  # beyond the crop
    # Initial transforms as an imperfect trajectory step gives them: 1.5 degrees and 3 cm off, and
    # the same with 2 % of scale.
    rigid = np.eye(4)
    rigid[:3, :3], rigid[:3, 3] = _rotation(1.5), [0.03, -0.02, 0.01]
    similar = rigid @ np.diag([1.02, 1.02, 1.02, 1.0])
    return {
        "noise": (base, gt, np.eye(4)),
        "outliers": (dirty, gt, np.eye(4)),
        "outside the crop": (outside, gt, np.eye(4)),
        "rigid offset": (dirty, gt, rigid),
        "similarity offset": (dirty, gt, similar),
    }


def _cloud(points: np.ndarray) -> o3d.geometry.PointCloud:
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))


def ours(recon, gt, initial, crop_file: Path, tau: float) -> tuple[float, float, float]:
    from dvpmvs.evaluation.tanks import evaluate_tanks

    volume = o3d.visualization.read_selection_polygon_volume(str(crop_file))
    result = evaluate_tanks(_cloud(recon), _cloud(gt), tau, initial, volume)
    return result.precision, result.recall, result.fscore


def load_toolbox(folder: Path):
    """The toolbox's ``registration`` and ``evaluation`` modules, with Open3D's renamed API mapped."""
    source = folder / "python_toolbox" / "evaluation"
    if not (source / "registration.py").is_file():
        raise SystemExit(
            f"{source / 'registration.py'} not found: give --toolbox the root of a TanksAndTemples "
            f"checkout"
        )
    if not hasattr(o3d, "registration"):
        o3d.registration = o3d.pipelines.registration  # the one renamed module it uses
    sys.path.insert(0, str(source))
    import registration  # noqa: E402

    import evaluation  # noqa: E402  (the toolbox's modules, by their own names)

    return registration, evaluation


def official(
    toolbox, recon, gt, initial, crop_file: Path, tau: float
) -> tuple[float, float, float]:
    """The toolbox's run_evaluation steps after the trajectory alignment, as its run.py calls them."""
    registration, evaluation = toolbox
    pcd, gt_pcd = _cloud(recon), _cloud(gt)
    vol = o3d.visualization.read_selection_polygon_volume(str(crop_file))
    with tempfile.TemporaryDirectory() as out, contextlib.redirect_stdout(io.StringIO()):
        r2 = registration.registration_vol_ds(
            pcd, gt_pcd, initial, vol, tau, tau * 80, 20, verbose=False
        )
        r3 = registration.registration_vol_ds(
            pcd, gt_pcd, r2.transformation, vol, tau / 2.0, tau * 20, 20, verbose=False
        )
        r = registration.registration_unif(
            pcd, gt_pcd, r3.transformation, vol, 2 * tau, 20, verbose=False
        )
        precision, recall, fscore, *_ = evaluation.EvaluateHisto(
            pcd, gt_pcd, r.transformation, vol, tau / 2.0, tau, out, 5, "case", verbose=False
        )
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Warning)
    return precision, recall, fscore


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--toolbox", type=Path, required=True, help="root of a TanksAndTemples checkout"
    )
    parser.add_argument("--thresholds", default="0.01,0.02,0.05")
    parser.add_argument(
        "--step", type=float, default=0.005, help="the ground truth's sampling (metres)"
    )
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    toolbox = load_toolbox(args.toolbox)
    rows, worst = [], 0.0
    with tempfile.TemporaryDirectory() as folder:
        crop = crop_volume_json(
            Path(folder) / "crop.json", (-0.05, -0.05, -0.05), (2.05, 2.05, 2.05)
        )
        for name, (recon, gt, initial) in cases(step=args.step).items():
            for tau in (float(v) for v in args.thresholds.split(",")):
                a = ours(recon, gt, initial, crop, tau)
                b = official(toolbox, recon, gt, initial, crop, tau)
                diff = 100 * max(abs(x - y) for x, y in zip(a, b))
                worst = max(worst, diff)
                rows.append(
                    {
                        "case": name,
                        "tau": tau,
                        "ours": a,
                        "official": b,
                        "max_difference_points": diff,
                    }
                )
                print(
                    f"| {name} | {100 * tau:g} cm | "
                    + " / ".join(f"{100 * v:.2f}" for v in b)
                    + " | "
                    + " / ".join(f"{100 * v:.2f}" for v in a)
                    + f" | {diff:.4f} |",
                    flush=True,
                )
    print(f"largest difference: {worst:.4f} F-points")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
