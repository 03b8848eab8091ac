"""OpenMVS's DensifyPointCloud beside ``dvpmvs dense`` on the synthetic suite, back to back.

For each scene, OpenMVS (``InterfaceCOLMAP`` then ``DensifyPointCloud`` with its defaults and
``--max-threads``) and then each dvpmvs configuration run on their own copy of the rendered
workspace, one after the other; each cloud is scored against the exact ground truth (ETH3D
metric at 2 and 10 cm) and each run's wall time and peak memory (of the process and its
children) are recorded. OpenMVS is not a dependency: build it outside the repository as
docs/benchmarks.md ("Reference tools") says and give its ``bin`` folder.

    python -m dvpmvs.evaluation.experiments.openmvs_suite --openmvs $PEERS/openMVS/make/bin \\
        --scenes room,facade,tabletop --width 800 --threads 2 --configs "quality=fast" ""

(``""``: the default configuration). Prints a markdown table; ``--out`` keeps the runs.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path


def timed(command: list[str], cwd: Path, log: Path) -> tuple[float, float]:
    """Wall seconds and peak resident memory (MB) of ``command`` and its children."""
    start = time.perf_counter()
    with open(log, "w") as out:
        process = subprocess.Popen(command, cwd=cwd, stdout=out, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(process.pid, 0)
    if status != 0:
        raise SystemExit(f"{command[0]} failed (see {log})")
    return time.perf_counter() - start, usage.ru_maxrss / 1024.0


def check_openmvs(folder: Path) -> None:
    """``folder`` holds OpenMVS's two programs the measurements run."""
    for tool in ("InterfaceCOLMAP", "DensifyPointCloud"):
        if not (folder / tool).is_file():
            raise SystemExit(
                f"no {tool} in {folder}: build OpenMVS as docs/benchmarks.md ('Reference tools') says"
            )


def densify(openmvs: Path, work: Path, threads: int, *options: str) -> tuple[float, float]:
    """OpenMVS on the COLMAP workspace ``work`` (``work/scene_dense.ply``, its depth maps
    ``work/depth*.dmap``): ``InterfaceCOLMAP``, then ``DensifyPointCloud`` with ``options``
    (none: its defaults); the densification's wall seconds and peak memory (MB)."""
    timed(
        [
            str(openmvs / "InterfaceCOLMAP"),
            "-i",
            ".",
            "-o",
            "scene.mvs",
            "--image-folder",
            "images",
        ],
        work,
        work / "interface.log",
    )
    return timed(
        [
            str(openmvs / "DensifyPointCloud"),
            "scene.mvs",
            "--max-threads",
            str(threads),
            *options,
            "-w",
            ".",
        ],
        work,
        work / "densify.log",
    )


def _score(cloud: Path, scene: Path) -> tuple[float, float]:
    """F1 at 2 and 10 cm (%) by ``dvpmvs eval``, in its own process: this one stays small, so
    that the processes it starts do not inherit its peak memory (a forked child's peak counts
    the parent's pages until it executes the measured program)."""
    report = cloud.with_name(cloud.name + ".eth3d.json")
    subprocess.run(
        [
            sys.executable,
            "-m",
            "dvpmvs.cli",
            "eval",
            f"reconstruction={cloud}",
            f"ground_truth={scene / 'ground_truth' / 'scan_alignment.mlp'}",
            "tolerances=[0.02,0.1]",
            f"report={report}",
        ],
        check=True,
        capture_output=True,
    )
    return tuple(100 * f for f in json.loads(report.read_text())["f1"])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--openmvs", type=Path, required=True, help="OpenMVS's bin folder")
    parser.add_argument("--scenes", default="room,facade,tabletop")
    parser.add_argument("--width", type=int, default=800)
    parser.add_argument("--views", type=int, default=8)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument(
        "--configs",
        nargs="*",
        default=["quality=fast"],
        help="dvpmvs overrides, one string each (none: OpenMVS alone)",
    )
    parser.add_argument("--scenes-dir", type=Path, default=Path("bench_scenes"))
    parser.add_argument("--out", type=Path, default=Path("openmvs_suite"))
    args = parser.parse_args(argv)
    check_openmvs(args.openmvs)

    from dvpmvs.evaluation.bench import render_scene
    from dvpmvs.evaluation.compare import copy_scene
    from dvpmvs.evaluation.scene_digest import scene_key

    dvpmvs = [sys.executable, "-m", "dvpmvs.cli"]
    rows = []
    for scene in args.scenes.split(","):
        rendered = render_scene(
            args.scenes_dir / scene_key(scene, args.views, args.width, 0),
            scene,
            args.views,
            args.width,
            0,
        )
        work = copy_scene(rendered, args.out.resolve() / scene / "openmvs")
        seconds, peak = densify(args.openmvs, work, args.threads)
        rows.append(
            (
                scene,
                "OpenMVS DensifyPointCloud (defaults)",
                *_score(work / "scene_dense.ply", rendered),
                seconds / args.views,
                peak,
            )
        )
        for index, config in enumerate(args.configs):
            work = copy_scene(rendered, args.out.resolve() / scene / f"dvpmvs{index}")
            command = dvpmvs + [
                "dense",
                f"workspace={work}",
                f"num_threads={args.threads}",
                "previews=false",
                *config.split(),
            ]
            seconds, peak = timed(command, work, work / "dense.log")
            rows.append(
                (
                    scene,
                    f"dvpmvs {config or '(default)'}",
                    *_score(work / "fused.ply", rendered),
                    seconds / args.views,
                    peak,
                )
            )
    print("| scene | tool | F1 2 cm | F1 10 cm | s / view | peak MB |\n|---|---|---|---|---|---|")
    for scene, tool, f2, f10, seconds, peak in rows:
        print(f"| {scene} | {tool} | {f2:.2f} | {f10:.2f} | {seconds:.1f} | {peak:.0f} |")
    tools = sorted({row[1] for row in rows}, key=[row[1] for row in rows].index)
    for tool in tools:
        mine = [row for row in rows if row[1] == tool]
        mean = [sum(row[k] for row in mine) / len(mine) for k in (2, 3, 4)]
        print(
            f"| mean | {tool} | {mean[0]:.2f} | {mean[1]:.2f} | {mean[2]:.1f} | {max(r[5] for r in mine):.0f} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
