"""Benchmark of the dense stage on the synthetic suite: ``python -m dvpmvs.evaluation.bench``.

For each scene family (room, facade, tabletop) it renders a workspace (``--views`` views of
``--width`` pixels, seed ``--seed``), runs ``dvpmvs dense`` in a fresh process with ``--threads``
OpenMP threads (so peak memory is that run's own), then scores the fused cloud with the ETH3D
metric (2 cm, 10 cm), the geometric depth maps with the depth-map metrics, and (``--colmap``)
COLMAP's stereo_fusion on the same maps. Prints a table and writes ``results.json`` (the rows,
and the environment: Python, numerical libraries and CPU, which the figures also depend on).

Example (the figures in docs/benchmarks.md)::

    python -m dvpmvs.evaluation.bench --out bench --views 8 --width 800 --threads 2 --colmap
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

SCENES = ("room", "facade", "tabletop")


def _write_json(path: Path, data: dict) -> None:
    """Write ``data`` as JSON atomically: an interrupted bench leaves the previous file whole."""
    from dvpmvs.maps import atomic_path

    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2))


def _peak_rss_mb() -> float:
    """Peak resident memory of this process. Linux's VmHWM belongs to the address space made by
    exec; ru_maxrss would also count the parent's peak before the exec (fork inherits it)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


_LIBRARIES = ("numpy", "scipy", "opencv-python-headless", "pycolmap", "open3d", "onnxruntime")


def environment() -> dict:
    """What the figures depend on besides the code and the seed: the Python, the numerical
    libraries (another OpenCV renders other scenes and gives other maps; see constraints.txt)
    and the CPU."""
    import platform
    from importlib import metadata

    versions = {}
    for name in _LIBRARIES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"python": platform.python_version(), "libraries": versions, "cpu": cpu, "cores": os.cpu_count()}


def _run_one(workspace: str, threads: int, out_json: str, overrides: list[str]) -> None:
    """Child process: the dense stage on one workspace; timings and peak RSS to ``out_json``."""
    from omegaconf import OmegaConf

    from dvpmvs.cli import dense_options
    from dvpmvs.pipeline import run_dense
    from dvpmvs.workspace import Workspace
    from hydra import compose, initialize_config_module

    with initialize_config_module(config_module="dvpmvs.conf", version_base=None):
        cfg = compose("dense", overrides=[f"workspace={workspace}", f"num_threads={threads}", *overrides])
    start = time.perf_counter()
    ws = Workspace.open(workspace)
    summary = run_dense(ws, dense_options(cfg), progress=False)
    total = time.perf_counter() - start
    reports = [r for r in summary.reports if not r.skipped]
    data = {
        "seconds_total": total,
        "views": len(ws.reference_views()),
        "pass_seconds": summary.pass_seconds,
        "fusion_seconds": summary.fusion_seconds,
        "estimator_seconds": sum(r.seconds for r in reports),
        "prior_seconds": sum(r.prior_seconds for r in reports),
        "hypothesis_evaluations": sum(r.evaluations for r in reports),
        "points": summary.num_points,
        "peak_rss_mb": _peak_rss_mb(),
        "config": OmegaConf.to_container(cfg.patch_match),
    }
    _write_json(Path(out_json), data)


def _score(workspace: Path, cloud: Path) -> dict:
    from dvpmvs.evaluation.commands import eth3d_parameters_for
    from dvpmvs.evaluation.eth3d_metric import evaluate_eth3d
    from dvpmvs.evaluation.pointclouds import read_meshlab_project, read_points

    mlp = workspace / "ground_truth" / "scan_alignment.mlp"
    result = evaluate_eth3d(read_points(cloud), read_meshlab_project(mlp), (0.02, 0.1), eth3d_parameters_for(mlp))
    return {"f1_2cm": 100 * result.f1[0], "f1_10cm": 100 * result.f1[1],
            "accuracy_2cm": 100 * result.accuracy[0], "completeness_2cm": 100 * result.completeness[0]}


def _depth_scores(workspace: Path) -> dict:
    from dvpmvs.evaluation.depth_metrics import evaluate_depth_maps

    views = evaluate_depth_maps(workspace / "stereo" / "depth_maps", workspace / "ground_truth" / "depth_maps")
    return {"within_1pct": 100 * float(np.mean([v.within_1_percent for v in views])),
            "within_2cm": 100 * float(np.mean([v.within_2_cm for v in views])),
            "estimated": 100 * float(np.mean([v.estimated for v in views]))}


def bench(out: Path, scenes, views: int, width: int, threads: int, seed: int, colmap: bool,
          overrides: list[str]) -> list[dict]:
    from dvpmvs.evaluation.synthetic import SynthOptions, generate
    from dvpmvs.fusion import FusionOptions, fuse_with_colmap
    from dvpmvs.workspace import Workspace

    rows = []
    for scene in scenes:
        workspace = out / f"{scene}_{views}v_{width}"
        marker = workspace / ".bench-scene-complete"
        if not marker.is_file():
            generate(workspace, SynthOptions(scene=scene, views=views, width=width, seed=seed))
            marker.write_text("ok\n")
        run_json = workspace / "bench_run.json"
        subprocess.run([sys.executable, "-m", "dvpmvs.evaluation.bench", "--run-one", str(workspace),
                        "--threads", str(threads), "--json", str(run_json), "--", "overwrite=true", *overrides],
                       check=True)
        run = json.loads(run_json.read_text())
        row = {"scene": scene, "views": views, "size": f"{width}x{width * 3 // 4}", "threads": threads, **run}
        row["seconds_per_view"] = run["seconds_total"] / run["views"]
        row["evaluations_per_second"] = run["hypothesis_evaluations"] / max(run["estimator_seconds"], 1e-9)
        row.update(_score(workspace, workspace / "fused.ply"))
        row.update({f"depth_{k}": v for k, v in _depth_scores(workspace).items()})
        if colmap:
            colmap_ply = workspace / "fused_colmap.ply"
            fuse_with_colmap(Workspace.open(workspace), colmap_ply, FusionOptions(num_threads=threads))
            row.update({f"colmap_{k}": v for k, v in _score(workspace, colmap_ply).items()})
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "config"}), flush=True)
    return rows


def print_table(rows: list[dict]) -> None:
    header = ("scene", "size", "thr", "s/view", "M evals/s", "peak MB", "F1 2cm", "F1 10cm", "depth <1%",
              "COLMAP fusion F1 2cm")
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for r in rows:
        print(f"| {r['scene']} | {r['size']} | {r['threads']} | {r['seconds_per_view']:.1f} | "
              f"{r['evaluations_per_second'] / 1e6:.2f} | {r['peak_rss_mb']:.0f} | {r['f1_2cm']:.2f} | "
              f"{r['f1_10cm']:.2f} | {r['depth_within_1pct']:.1f} | "
              f"{r.get('colmap_f1_2cm', float('nan')):.2f} |")
    if len(rows) > 1:
        print(f"| mean | | | {np.mean([r['seconds_per_view'] for r in rows]):.1f} | | | "
              f"{np.mean([r['f1_2cm'] for r in rows]):.2f} | {np.mean([r['f1_10cm'] for r in rows]):.2f} | "
              f"{np.mean([r['depth_within_1pct'] for r in rows]):.1f} | "
              f"{np.mean([r.get('colmap_f1_2cm', np.nan) for r in rows]):.2f} |")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="bench")
    parser.add_argument("--scenes", default=",".join(SCENES))
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--width", type=int, default=800)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--colmap", action="store_true", help="also score COLMAP's stereo_fusion of our maps")
    parser.add_argument("--run-one", help=argparse.SUPPRESS)
    parser.add_argument("--json", help=argparse.SUPPRESS)
    parser.add_argument("overrides", nargs="*", help="dense config overrides, e.g. patch_match.num_iterations=4")
    args = parser.parse_args(argv)
    if args.run_one:
        _run_one(args.run_one, args.threads, args.json, args.overrides)
        return 0
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = bench(out, args.scenes.split(","), args.views, args.width, args.threads, args.seed, args.colmap,
                 args.overrides)
    env = environment()
    _write_json(out / "results.json", {"environment": env, "rows": rows})
    print_table(rows)
    print("environment: Python {python}, {cpu} ({cores} cores); ".format(**env)
          + ", ".join(f"{k} {v}" for k, v in env["libraries"].items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
