"""How time and memory grow with the number of views: the long corridor scene, local and on a
Dask LocalCluster, and fusion's peak memory.

For each number of views: ``dvpmvs synth scene=corridor`` (once; reused when there), then
``dvpmvs dense`` without fusion with the local executor, then the same on a ``LocalCluster`` of
``--workers`` single-task workers this script starts (so that it can read their peak memory),
each in its own folder, then ``dvpmvs fuse`` on the local run's maps in a process of its own. It
prints one table row per number of views: wall seconds, peak resident memory of each process
(the dense driver, the busiest worker, fusion; and fusion's resident memory once the workspace
is open, before any map is read) and whether the two executors' maps are the same bytes;
``--json`` also writes the figures.

    python -m dvpmvs.evaluation.experiments.scale --views 50,100,200 --width 320 --out scale_runs

Every process runs with ``num_threads`` cores in all: the local run's kernels use them all, each
of the cluster's workers ``threads / workers``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import time
from pathlib import Path

from dvpmvs.run import peak_rss_mb


def _dvpmvs() -> str:
    return str(Path(sys.executable).with_name("dvpmvs"))


def _run(args: list[str]) -> float:
    start = time.perf_counter()
    done = subprocess.run(args, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(args)} failed:\n{done.stderr[-3000:]}")
    return time.perf_counter() - start


def _resident_mb() -> float:
    """This process's resident memory now (VmRSS); :func:`dvpmvs.run.peak_rss_mb` is its peak."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _maps_digest(stereo: Path) -> str:
    digest = hashlib.sha256()
    for path in sorted(stereo.glob("*_maps/*.bin")):
        digest.update(path.relative_to(stereo).as_posix().encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def _manifest(out: Path) -> dict:
    return json.loads((out / "dvpmvs_run.json").read_text())


def measure(views: int, width: int, out: Path, workers: int, threads: int) -> dict:
    from distributed import Client, LocalCluster

    scene = out / f"corridor_{views}v_{width}"
    if not (scene / "scene.json").is_file():
        _run(
            [
                _dvpmvs(),
                "synth",
                f"out={scene}",
                "scene=corridor",
                f"views={views}",
                f"width={width}",
            ]
        )
    common = [f"workspace={scene}", "fuse=false", "progress=false", "evaluate.depth_maps=false"]
    local = out / f"local_{views}"
    wall_local = _run(
        [_dvpmvs(), "dense", *common, f"out={local}", f"num_threads={threads}", "overwrite=true"]
    )
    per_worker = max(1, threads // workers)
    with (
        LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster,
        Client(cluster) as client,
    ):
        dask = out / f"dask_{views}"
        wall_dask = _run(
            [
                _dvpmvs(),
                "dense",
                *common,
                f"out={dask}",
                "executor=dask",
                f"executor.address={cluster.scheduler_address}",
                f"executor.threads_per_worker={per_worker}",
                "overwrite=true",
            ]
        )
        worker_peaks = client.run(peak_rss_mb)
    fusion_out = out / f"fusion_{views}.json"
    fuse_wall = _run(
        [
            sys.executable,
            "-m",
            "dvpmvs.evaluation.experiments.scale",
            "--fuse",
            str(local),
            "--threads",
            str(threads),
            "--json",
            str(fusion_out),
        ]
    )
    fusion = json.loads(fusion_out.read_text())
    return {
        "views": views,
        "width": width,
        "workers": workers,
        "threads": threads,
        "local": {
            "wall_seconds": wall_local,
            "dense_seconds": _manifest(local)["seconds"],
            "peak_rss_mb": _manifest(local)["peak_rss_mb"],
        },
        "dask": {
            "wall_seconds": wall_dask,
            "dense_seconds": _manifest(dask)["seconds"],
            "driver_peak_rss_mb": _manifest(dask)["peak_rss_mb"],
            "worker_peak_rss_mb": sorted(worker_peaks.values()),
        },
        "same_maps": _maps_digest(local / "stereo") == _maps_digest(dask / "stereo"),
        "fusion": {**fusion, "wall_seconds": fuse_wall},
    }


def fuse_only(folder: Path, threads: int) -> dict:
    """Fuse the geometric maps of a run's output folder in this process; seconds, points, peak MB."""
    from dvpmvs.dense import MaskStore, fuse_to_file
    from dvpmvs.fusion import FusionOptions
    from dvpmvs.workspace import Workspace

    workspace = Workspace.open(folder)
    opened = _resident_mb()  # the sparse model and the views' metadata, before any map is read
    start = time.perf_counter()
    stereo = workspace.stereo_dir
    points = fuse_to_file(
        workspace,
        FusionOptions(num_threads=threads),
        "dvpmvs",
        folder / "fused.ply",
        False,
        stereo,
        None,
        MaskStore.from_config(None, stereo, workspace.root),
        workspace.fusion_views(stereo),
    )
    return {
        "seconds": time.perf_counter() - start,
        "points": points,
        "peak_rss_mb": peak_rss_mb(),
        "opened_rss_mb": opened,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--views", default="50,100,200", help="numbers of views, comma-separated")
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--out", type=Path, default=Path("scale_runs"))
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument(
        "--threads", type=int, default=2, help="cores in all (local kernels; shared by workers)"
    )
    parser.add_argument("--json", type=Path, help="also write the figures here")
    parser.add_argument(
        "--fuse", type=Path, help=argparse.SUPPRESS
    )  # one fusion, in a process of its own
    args = parser.parse_args(argv)
    if args.fuse is not None:
        result = fuse_only(args.fuse, args.threads)
        args.json.write_text(json.dumps(result))
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    print(
        "| views | local s | local peak MB | 2 workers s | driver peak MB | worker peak MB | same maps "
        "| fusion s | fusion peak MB | fusion MB once open | points |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for views in (int(v) for v in args.views.split(",")):
        row = measure(views, args.width, args.out.resolve(), args.workers, args.threads)
        rows.append(row)
        local, dask, fusion = row["local"], row["dask"], row["fusion"]
        print(
            f"| {views} | {local['wall_seconds']:.0f} | {local['peak_rss_mb']:.0f} | {dask['wall_seconds']:.0f} "
            f"| {dask['driver_peak_rss_mb']:.0f} | {max(dask['worker_peak_rss_mb']):.0f} "
            f"| {'yes' if row['same_maps'] else 'no'} | {fusion['seconds']:.1f} | {fusion['peak_rss_mb']:.0f} "
            f"| {fusion['opened_rss_mb']:.0f} | {fusion['points']:,} |",
            flush=True,
        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
