"""Benchmark of the ETH3D metric: ``python -m dvpmvs.evaluation.bench_metric [points] [--width W]``.

Generates the synthetic room (8 views, 800x600 by default: ~3.8 M ground-truth scan points),
perturbs a sample of its ground truth into a reconstruction of the requested size (default one
million points) and times the evaluation at four tolerances.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from dvpmvs.evaluation.commands import eth3d_parameters_for
from dvpmvs.evaluation.eth3d_metric import evaluate_eth3d
from dvpmvs.evaluation.pointclouds import read_meshlab_project
from dvpmvs.evaluation.synthetic import SynthOptions, generate


def main(num_points: int = 1_000_000, width: int = 800) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        generate(tmp, SynthOptions(scene="room", views=8, width=width, priors=False))
        mlp = f"{tmp}/ground_truth/scan_alignment.mlp"
        scans = read_meshlab_project(mlp)
        params = eth3d_parameters_for(Path(mlp))
        gt = np.concatenate([s.global_points() for s in scans])
        rng = np.random.default_rng(0)
        rec = gt[rng.choice(len(gt), num_points)] + rng.normal(0, 0.01, (num_points, 3)).astype(
            np.float32
        )
        start = time.perf_counter()
        result = evaluate_eth3d(rec, scans, [0.01, 0.02, 0.05, 0.1], params)
        seconds = time.perf_counter() - start
    print(
        f"ground truth: {len(gt):,} scan points in {len(scans)} scans; reconstruction: {num_points:,} points"
    )
    print(f"ETH3D evaluation (4 tolerances): {seconds:.2f} s")
    print("F1:", ", ".join(f"{t:g} m: {100 * f:.2f}" for t, f in zip(result.tolerances, result.f1)))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "points", type=int, nargs="?", default=1_000_000, help="points of the reconstruction"
    )
    parser.add_argument(
        "--width", type=int, default=800, help="the scene's image width (its scans' density)"
    )
    args = parser.parse_args()
    main(args.points, args.width)
