"""Our fusion against COLMAP's, on the same maps: the cloud each gives and its ETH3D scores.

For each bench job folder of the sweeps given (their maps, their manifest's workspace and ground
truth), the job's own cloud (our fusion, ``fusion=dvpmvs``) is set beside two clouds that
COLMAP's ``stereo_fusion`` (through pycolmap) makes of the same maps: with COLMAP's defaults
(``colmap stereo_fusion`` as a COLMAP user runs it on our maps) and with our thresholds
(``fusion=colmap``). Each is scored by the ETH3D metric at the job's tolerances (kept in the job's
``evaluation/`` with their fingerprints: a rerun reads them back), then the means per scene over
the jobs (the estimator's seeds) are printed as a Markdown table.

    python -m dvpmvs.evaluation.experiments.fusion_parity multirun/bench-XXXX --threads 2
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

# The clouds compared: (label, file in the job folder, the fusion that makes it).
FUSIONS = (
    ("dvpmvs (`fusion=dvpmvs`, the default)", "fused.ply", None),
    ("COLMAP's `stereo_fusion`, its defaults", "fused_colmap_defaults.ply", "defaults"),
    ("COLMAP's `stereo_fusion`, our thresholds (`fusion=colmap`)", "fused_colmap_ours.ply", "ours"),
)


def colmap_defaults():
    """FusionOptions that hand COLMAP's fusion its own defaults (pycolmap's StereoFusionOptions):
    min_num_pixels, max_reproj_error, max_depth_error, max_normal_error."""
    import pycolmap

    from dvpmvs.options.fusion import FusionOptions

    colmap = pycolmap.StereoFusionOptions()
    return FusionOptions(
        min_consistent_views=colmap.min_num_pixels - 1,  # COLMAP counts the reference pixel
        max_depth_error=colmap.max_depth_error,
        max_normal_error=colmap.max_normal_error,
        colmap_max_reproj_error=colmap.max_reproj_error,
    )


def compare_job(job: Path, threads: int) -> dict[str, dict]:
    """The three clouds of a bench job and their scores, by label."""
    from dataclasses import replace

    from dvpmvs.evaluation.runs import job_ground_truth, score_cloud
    from dvpmvs.fusion import fuse_with_colmap
    from dvpmvs.options.fusion import FusionOptions
    from dvpmvs.run import MANIFEST_NAME
    from dvpmvs.workspace import Workspace

    manifest = json.loads((job / MANIFEST_NAME).read_text())
    tolerances = [float(t) for t in manifest["evaluation"]["eth3d"]["tolerances"]]
    truth = job_ground_truth(job)
    workspace = Workspace.open(Path(manifest["workspace"]))
    rows = {}
    for label, name, kind in FUSIONS:
        cloud = job / name
        # COLMAP's clouds are made again each time: one on disk may come from earlier maps.
        if kind is not None:
            options = colmap_defaults() if kind == "defaults" else FusionOptions()
            options = replace(options, num_threads=threads)
            fuse_with_colmap(workspace, cloud, options, root=job)
        scores = score_cloud(
            cloud, truth, tolerances, job / "evaluation" / f"eth3d_{cloud.stem}.json"
        )
        rows[label] = {**scores, "points": scores["reconstruction_points"]}
    return rows


def parity_table(jobs: list[Path], threads: int) -> str:
    """The Markdown table: per scene (over its jobs) and cloud, the mean points, accuracy,
    completeness and F1 at each tolerance."""
    from dvpmvs.run import MANIFEST_NAME

    by_scene: dict[str, dict[str, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for job in jobs:
        scene = (json.loads((job / MANIFEST_NAME).read_text()).get("scene") or {}).get("key", "?")
        for label, scores in compare_job(job, threads).items():
            by_scene[scene][label].append(scores)
    lines = [
        "| scene | fusion | points | Acc. 2 cm | Comp. 2 cm | F1 2 cm | F1 10 cm |",
        "|---|---|---|---|---|---|---|",
    ]
    for scene, clouds in sorted(by_scene.items()):
        for label, runs in clouds.items():

            def mean(key, index):
                return 100 * sum(r[key][index] for r in runs) / len(runs)

            points = sum(r["points"] for r in runs) / len(runs)
            lines.append(
                f"| {scene} ({len(runs)}) | {label} | {points:,.0f} | {mean('accuracy', 0):.2f} | "
                f"{mean('completeness', 0):.2f} | {mean('f1', 0):.2f} | {mean('f1', -1):.2f} |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sweeps", nargs="+", type=Path, help="bench sweep folders (or job folders)")
    parser.add_argument("--threads", type=int, default=0, help="COLMAP's fusion threads (0: all)")
    args = parser.parse_args(argv)
    import pycolmap

    from dvpmvs.run import MANIFEST_NAME

    pycolmap.logging.minloglevel = 3  # COLMAP's lines per fused image: only the table here

    jobs = []
    for sweep in args.sweeps:
        found = (
            [sweep]
            if (sweep / MANIFEST_NAME).is_file()
            else sorted(sweep.glob(f"*/{MANIFEST_NAME}"))
        )
        jobs += [p if p.is_dir() else p.parent for p in found]
    jobs = [job for job in jobs if (job / "fused.ply").is_file()]
    if not jobs:
        raise SystemExit("no bench job with a fused cloud in the folders given")
    print(parity_table(jobs, args.threads))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
