"""The default, the presets and OpenMVS on clips of an RGB-D sequence, scored against its sensor.

Each clip is ``dvpmvs import`` of ``--views`` keyframes from frame ``start`` of the sequence (its
tracked poses, its sensor depth as ground truth: docs/cli.md, "import"). On each clip every
dvpmvs configuration runs once per estimator seed (``dvpmvs dense`` with ``out=`` beside the
clip, the run scoring its own cloud and maps: ETH3D F1 at 2 / 5 / 10 cm, the depth maps' RGB-D
errors); OpenMVS (``InterfaceCOLMAP``, then ``DensifyPointCloud`` with its defaults) runs once
on a copy of the clip, its cloud scored by ``dvpmvs eval`` and its own depth maps (``.dmap``,
after its filtering) by the same depth metrics. OpenMVS is not a dependency: build it outside
the repository as docs/benchmarks.md ("Reference tools") says, or leave ``--openmvs`` out.

    python -m dvpmvs.evaluation.experiments.rgbd_clips --source ../shared/data/7scenes-redkitchen \\
        --starts 0,60,120 --views 10 --seeds 0,1,2 --configs "" "quality=fast" \\
        --openmvs $PEERS/openMVS/make/bin --threads 2 --out kitchen_clips

(``""``: the default configuration). Prints markdown tables: per clip, and the clips' mean with
the spread over seeds (the lowest and highest of the seeds' clip means). ``--out`` keeps the
clips and runs: a rerun reuses a clip imported with the same options and a run whose manifest
names the same configuration, and recomputes the rest.
"""

from __future__ import annotations

import argparse
import functools
import json
import shutil
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

# (label, how a run's record holds it): F1 at three tolerances, then the depth maps' errors
# pooled over the clip's views (percent; RMSE in centimetres).
METRICS = (
    ("F1 2cm", "f1", 0),
    ("F1 5cm", "f1", 1),
    ("F1 10cm", "f1", 2),
    ("depth <2%", "within_2_percent", None),
    ("depth <5%", "within_5_percent", None),
    ("AbsRel %", "abs_rel", None),
    ("SqRel cm", "sq_rel", None),
    ("RMSE cm", "rmse", None),
    ("δ<1.05", "delta_1_05", None),
    ("δ<1.10", "delta_1_10", None),
    ("δ<1.25", "delta_1_25", None),
)
TOLERANCES = "[0.02,0.05,0.1]"
DVPMVS = [sys.executable, "-m", "dvpmvs.cli"]


def _run(command: list[str], log: Path, cwd: Path | None = None) -> float:
    """Wall seconds of ``command``, its output in ``log``."""
    start = time.perf_counter()
    with open(log, "w") as out:
        done = subprocess.run(command, cwd=cwd, stdout=out, stderr=subprocess.STDOUT)
    if done.returncode != 0:
        raise SystemExit(
            f"{command[2] if command[0] == sys.executable else command[0]} failed (see {log})"
        )
    return time.perf_counter() - start


@functools.cache  # the installed code does not change while the script runs
def _code() -> dict:
    """What made a clip or a run: the package's code as installed, the harness's included."""
    from dvpmvs.digests import sources_digest
    from dvpmvs.provenance import code_identity

    harness = Path(__file__).resolve().parents[1]  # dvpmvs/evaluation, as installed
    return {**code_identity(), "evaluation": sources_digest(harness)}


def _current(record: Path, made_by: dict) -> bool:
    """Whether the outputs ``record`` describes were made by ``made_by`` (command and code)."""
    return record.is_file() and json.loads(record.read_text()).get("made_by") == made_by


def import_clip(
    layout: str,
    source: Path,
    start: int,
    views: int,
    max_image_size: int,
    overrides: list[str],
    out: Path,
) -> Path:
    clip = out / f"clip_{start:03d}"
    command = DVPMVS + [
        "import",
        f"dataset={layout}",
        f"source={source}",
        f"out={clip}",
        f"rgbd.start={start}",
        f"rgbd.views={views}",
        f"max_image_size={max_image_size}",
        "overwrite=true",  # a clip this script imported before, with other code or options
        *overrides,
    ]
    made_by = {"command": command[2:], "code": _code()}
    record = out / f"clip_{start:03d}.json"
    if not _current(record, made_by):
        clip.parent.mkdir(parents=True, exist_ok=True)
        _run(command, out / f"import_{start:03d}.log")
        record.write_text(json.dumps({"made_by": made_by}))
    return clip


def score(cloud: Path, maps: Path, clip: Path, folder: Path) -> dict[str, float]:
    """The cloud's F1 and the depth maps' errors against the clip's sensor, by ``dvpmvs eval``
    (both tools alike, outside the timed runs)."""
    reports = {}
    for metric, reconstruction, truth in (
        ("eth3d", cloud, clip / "ground_truth" / "scan_alignment.mlp"),
        ("depth", maps, clip / "ground_truth"),
    ):
        reports[metric] = folder / f"{metric}.json"
        _run(
            DVPMVS
            + [
                "eval",
                f"metric={metric}",
                f"reconstruction={reconstruction}",
                f"ground_truth={truth}",
                f"tolerances={TOLERANCES}",
                f"report={reports[metric]}",
            ],
            folder / f"eval_{metric}.log",
        )
    eth3d = json.loads(reports["eth3d"].read_text())
    depth = json.loads(reports["depth"].read_text())["all"]
    row = {}
    for label, key, index in METRICS:
        if index is not None:
            row[label] = 100 * eth3d["f1"][index]
        else:  # shares and AbsRel in percent, SqRel and RMSE in centimetres
            row[label] = 100 * depth[key]
    return row


def run_dvpmvs(clip: Path, config: str, seed: int, threads: int, out: Path) -> dict[str, float]:
    name = config.replace(" ", "_").replace("=", "-") or "default"
    folder = out / "runs" / clip.name / f"{name}_seed{seed}"
    command = DVPMVS + [
        "dense",
        f"workspace={clip}",
        f"out={folder}",
        f"seed={seed}",
        f"num_threads={threads}",
        "previews=false",
        "report=false",
        "evaluate.ground_truth=none",  # scored below, outside the timed command
        *config.split(),
    ]
    # Beside the run folder: the folder is removed before a run.
    record = folder.parent / f"{folder.name}.json"
    made_by = {"command": command[2:], "code": _code(), "clip": clip_record(clip)}
    if not _current(record, made_by):
        shutil.rmtree(folder, ignore_errors=True)  # timed from scratch: no maps to resume from
        folder.mkdir(parents=True)
        seconds = _run(command, folder.parent / f"{folder.name}.log")
        record.write_text(json.dumps({"made_by": made_by, "seconds": seconds}))
    row = score(folder / "fused.ply", folder, clip, folder)
    row["s / view"] = json.loads(record.read_text())["seconds"] / _num_views(clip)
    return row


def clip_record(clip: Path) -> str:
    """The clip's import record (its keyframes and cameras), which a run's reuse depends on."""
    return (clip / "rgbd.json").read_text()


def _num_views(clip: Path) -> int:
    return len(json.loads((clip / "rgbd.json").read_text())["keyframes"])


def read_dmap(path: Path) -> tuple[str, np.ndarray]:
    """OpenMVS's raw depth-map file (``DepthMap.cpp``, ``ExportDepthDataRaw``): the image's file
    name and its depth map (z, float32, at the estimate's resolution; 0: none)."""
    data = path.read_bytes()
    name, kind, _, _, _, width, height, _, _ = struct.unpack_from("<HBBIIIIff", data, 0)
    if name != struct.unpack("<H", b"DR")[0] or not kind & 1:
        raise SystemExit(f"{path} is not an OpenMVS depth map")
    offset = struct.calcsize("<HBBIIIIff")
    (length,) = struct.unpack_from("<H", data, offset)
    image = data[offset + 2 : offset + 2 + length].decode()
    offset += 2 + length
    (ids,) = struct.unpack_from("<I", data, offset)
    offset += 4 + 4 * ids + 8 * (9 + 9 + 3)  # the view IDs, then K, R, C (float64)
    depth = np.frombuffer(data, np.float32, width * height, offset).reshape(height, width)
    return image, depth.copy()


def run_openmvs(clip: Path, openmvs: Path, threads: int, out: Path) -> dict[str, float]:
    from dvpmvs.evaluation.compare import copy_scene
    from dvpmvs.evaluation.experiments.openmvs_suite import densify
    from dvpmvs.maps import write_depth_map

    work = out / "runs" / clip.name / "openmvs"
    cloud = work / "scene_dense.ply"
    record = work.parent / "openmvs.json"
    made_by = {"openmvs": str(openmvs.resolve()), "threads": threads, "clip": clip_record(clip)}
    if not _current(record, made_by):
        copy_scene(clip, work)
        seconds, _ = densify(openmvs, work, threads)
        record.write_text(json.dumps({"made_by": made_by, "seconds": seconds}))
    maps = work / "dmaps_as_colmap" / "stereo" / "depth_maps"
    for dmap in sorted(work.glob("depth*.dmap")):
        image, depth = read_dmap(dmap)
        write_depth_map(maps / f"{Path(image).name}.geometric.bin", depth)
    row = score(cloud, maps.parent.parent, clip, work)
    row["s / view"] = json.loads(record.read_text())["seconds"] / _num_views(clip)
    return row


def _table(rows: dict[str, dict[str, float]], spreads: dict | None = None) -> str:
    labels = [label for label, _, _ in METRICS] + ["s / view"]
    lines = [
        "| configuration | " + " | ".join(labels) + " |",
        "|---|" + "---|" * len(labels),
    ]
    for name, row in rows.items():
        cells = []
        for label in labels:
            cell = f"{row[label]:.2f}" if label != "s / view" else f"{row[label]:.1f}"
            if spreads and name in spreads and label.startswith("F1"):
                low, high = spreads[name][label]
                cell += f" ({low:.2f}-{high:.2f})"
            cells.append(cell)
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", type=Path, required=True, help="an RGB-D sequence's folder")
    parser.add_argument("--layout", default="7scenes", help="7scenes | tum | scannet | rgbd")
    parser.add_argument(
        "--import-overrides", nargs="*", default=[], help="more rgbd.* keys of dvpmvs import"
    )
    parser.add_argument("--starts", default="0,60,120", help="each clip's first frame (index)")
    parser.add_argument("--views", type=int, default=10)
    parser.add_argument("--max-image-size", type=int, default=640)
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--configs", nargs="*", default=["", "quality=fast"])
    parser.add_argument("--openmvs", type=Path, help="OpenMVS's bin folder (else without it)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("rgbd_clips"))
    args = parser.parse_args(argv)
    if args.openmvs is not None:
        from dvpmvs.evaluation.experiments.openmvs_suite import check_openmvs

        check_openmvs(args.openmvs)
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    seeds = [int(s) for s in args.seeds.split(",")]
    names = {config: f"`{config}`" if config else "default" for config in args.configs}
    per_seed: dict[str, dict[int, list[dict]]] = {}  # configuration -> seed -> clips' rows
    for start in (int(s) for s in args.starts.split(",")):
        clip = import_clip(
            args.layout,
            args.source.resolve(),
            start,
            args.views,
            args.max_image_size,
            args.import_overrides,
            out,
        )
        rows = {}
        for config in args.configs:
            runs = [run_dvpmvs(clip, config, seed, args.threads, out) for seed in seeds]
            for seed, row in zip(seeds, runs):
                per_seed.setdefault(names[config], {}).setdefault(seed, []).append(row)
            rows[names[config]] = {k: float(np.mean([r[k] for r in runs])) for k in runs[0]}
        if args.openmvs is not None:
            row = run_openmvs(clip, args.openmvs, args.threads, out)
            per_seed.setdefault("OpenMVS", {}).setdefault(0, []).append(row)
            rows["OpenMVS"] = row
        frames = [k["frame"] for k in json.loads((clip / "rgbd.json").read_text())["keyframes"]]
        print(
            f"\nclip {clip.name} (frames {frames[0]}-{frames[-1]}), mean over seeds {args.seeds}:"
        )
        print(_table(rows))
    means, spreads = {}, {}
    for name, by_seed in per_seed.items():
        seed_means = [
            {k: float(np.mean([r[k] for r in clips])) for k in clips[0]}
            for clips in by_seed.values()
        ]
        means[name] = {k: float(np.mean([m[k] for m in seed_means])) for k in seed_means[0]}
        spreads[name] = {
            k: (min(m[k] for m in seed_means), max(m[k] for m in seed_means)) for k in seed_means[0]
        }
    print("\nmean of the clips (seed spread in brackets; OpenMVS: one run):")
    print(_table(means, spreads))
    return 0


if __name__ == "__main__":
    sys.exit(main())
