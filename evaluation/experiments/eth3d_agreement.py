"""Our ETH3D metric beside the official program, on the same clouds and ground truth.

For each case (a cloud and an ETH3D ground truth, ``scan_alignment.mlp``), this runs
``dvpmvs.evaluation.eth3d_metric.evaluate_eth3d`` with the parameters ``dvpmvs eval`` would use
(the official defaults, or ``eth3d_parameters.json`` beside the MLP), then the official
``ETH3DMultiViewEvaluation`` with the same parameters, and prints per case and tolerance
accuracy, completeness and F1 of both, their largest difference, and both times.

    python -m dvpmvs.evaluation.experiments.eth3d_agreement --official $PEERS/eth3d/build/ETH3DMultiViewEvaluation \\
        --case dvpmvs_demo/fused.ply dvpmvs_demo/ground_truth/scan_alignment.mlp \\
        --bench multirun/bench-*/*/         # every job folder of a bench sweep: its fused.ply and scene

The official program is built as docs/benchmarks.md ("Reference tools") says, outside this
repository; ``--json`` also writes the figures.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import time
from pathlib import Path


def _ours(cloud: Path, mlp: Path, tolerances: list[float]) -> tuple[dict, float]:
    from dvpmvs.evaluation.commands import eth3d_parameters_for
    from dvpmvs.evaluation.eth3d_metric import evaluate_eth3d
    from dvpmvs.evaluation.pointclouds import load_ground_truth, read_points

    params = eth3d_parameters_for(mlp)
    start = time.perf_counter()
    result = evaluate_eth3d(read_points(cloud), load_ground_truth(mlp), tolerances, params)
    seconds = time.perf_counter() - start
    return {
        "accuracy": list(result.accuracy),
        "completeness": list(result.completeness),
        "f1": list(result.f1),
        "parameters": params,
    }, seconds


def _official(
    program: Path, cloud: Path, mlp: Path, tolerances: list[float], params
) -> tuple[dict, float]:
    args = [
        str(program),
        "--reconstruction_ply_path",
        str(cloud.resolve()),
        "--ground_truth_mlp_path",
        str(mlp.resolve()),
        "--tolerances",
        ",".join(f"{t:g}" for t in tolerances),
        "--voxel_size",
        repr(params.voxel_size),
        "--beam_start_radius_meters",
        repr(params.beam_start_radius_meters),
        "--beam_divergence_halfangle_deg",
        repr(params.beam_divergence_halfangle_deg),
    ]
    start = time.perf_counter()
    # The program reads the scans named in the MLP relative to the current folder.
    done = subprocess.run(args, capture_output=True, text=True, cwd=mlp.resolve().parent)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(
            f"{' '.join(args)} failed ({done.returncode}):\n{done.stdout[-2000:]}{done.stderr[-2000:]}"
        )
    found = {}
    for key, label in (
        ("completeness", "Completenesses"),
        ("accuracy", "Accuracies"),
        ("f1", "F1-scores"),
    ):
        match = re.search(rf"^{label}: (.*)$", done.stdout, re.M)
        if match is None:
            raise SystemExit(
                f"no '{label}:' line in the official program's output:\n{done.stdout[-2000:]}"
            )
        found[key] = [float(v) for v in match.group(1).split()]
    return found, seconds


def _ground_truth(job: Path) -> Path:
    from dvpmvs.errors import DvpmvsError
    from dvpmvs.evaluation.runs import job_ground_truth

    try:
        return job_ground_truth(job)
    except DvpmvsError as exc:
        raise SystemExit(str(exc)) from None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--official", type=Path, required=True, help="the ETH3DMultiViewEvaluation program"
    )
    parser.add_argument("--case", nargs=2, action="append", default=[], metavar=("CLOUD", "MLP"))
    parser.add_argument("--bench", nargs="*", type=Path, default=[], help="bench job folders")
    parser.add_argument("--tolerances", default="0.01,0.02,0.05,0.1")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    if not args.official.is_file():
        raise SystemExit(
            f"--official {args.official}: no such program; build it as docs/benchmarks.md ('Reference tools') says"
        )
    tolerances = [float(t) for t in args.tolerances.split(",")]
    cases = [(Path(c), Path(m)) for c, m in args.case] + [
        (job / "fused.ply", _ground_truth(job)) for job in args.bench
    ]
    if not cases:
        raise SystemExit("give at least one --case CLOUD MLP or --bench JOB")
    rows = []
    print(
        "| cloud | tolerance | accuracy ours / official | completeness ours / official | F1 ours / official |"
    )
    print("|---|---|---|---|---|")
    for cloud, mlp in cases:
        ours, ours_s = _ours(cloud, mlp, tolerances)
        official, official_s = _official(args.official, cloud, mlp, tolerances, ours["parameters"])
        worst = max(
            abs(ours[k][i] - official[k][i])
            for k in ("accuracy", "completeness", "f1")
            for i in range(len(tolerances))
        )
        for i, t in enumerate(tolerances):
            print(
                f"| {cloud} | {t:g} | "
                + " | ".join(
                    f"{100 * ours[k][i]:.4f} / {100 * official[k][i]:.4f}"
                    for k in ("accuracy", "completeness", "f1")
                )
                + " |"
            )
        print(
            f"| {cloud}: largest difference {100 * worst:.4f} points; ours {ours_s:.1f} s, "
            f"official {official_s:.1f} s | | | | |"
        )
        rows.append(
            {
                "cloud": str(cloud),
                "ground_truth": str(mlp),
                "tolerances": tolerances,
                "ours": {k: ours[k] for k in ("accuracy", "completeness", "f1")},
                "official": official,
                "largest_difference": worst,
                "ours_seconds": ours_s,
                "official_seconds": official_s,
            }
        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
