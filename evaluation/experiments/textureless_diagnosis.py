"""Where plain surfaces are gained and lost, stage by stage, from ground truth.

Runs the dense stage on a synthetic workspace (its ``ground_truth/textureless/`` masks: surfaces
of uniform albedo, such as the courtyard's wall) with the estimator's stages observed
(:func:`dvpmvs.patchmatch.estimator.observe_stages`), then fuses. For each pass, pyramid level and
stage (``start``: the state handed over from the level below; ``propagation``: after the plain
red-black iterations; ``prior``: after the planar-prior and deformable iterations; ``filtered``: the
map written), the share of the pixels on plain surfaces and on textured ones whose depth lies
within 1 % of the truth (the truth and masks resized to the level by nearest neighbour), pooled
over the views; then, for the fused cloud, the share of the ground-truth scan points on plain and
on textured surfaces that have a fused point within 2 cm, and the share of the cloud's points in
open sky.

    python -m dvpmvs.evaluation.experiments.textureless_diagnosis WORKSPACE OUT [overrides ...]

``overrides`` are `dvpmvs dense` options (``quality=fast``, ``patch_match.num_scales=2`` ...); OUT
receives the maps and the cloud (recomputed: every view's stages are observed). Prints a markdown
table; ``--json PATH`` writes the figures.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import cKDTree

TOLERANCE = 0.01  # relative depth error counted as right
CLOUD_TOLERANCE = 0.02  # metres: a scan point is complete with a fused point this near


def _mask(path: Path) -> np.ndarray:
    mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if mask is None:
        raise SystemExit(
            f"{path} is missing: render the workspace with this version of `dvpmvs synth`"
        )
    return mask > 127


def _resized(array: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    if array.shape[:2] == shape:
        return array
    return cv2.resize(
        array.astype(np.float32), (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST
    )


class StageShares:
    """The observer: per (pass, level, stage), pixels within 1 % and in all, plain and textured."""

    def __init__(self, truth: dict[str, np.ndarray], plain: dict[str, np.ndarray]):
        self.truth, self.plain = truth, plain
        self.counts: dict[tuple, np.ndarray] = defaultdict(lambda: np.zeros(4, np.int64))

    def __call__(self, stage, depth, K) -> None:
        truth = _resized(self.truth[stage.view], depth.shape)
        plain = _resized(self.plain[stage.view], depth.shape) > 0
        valid = truth > 0
        good = valid & (depth > 0) & (np.abs(depth - truth) <= TOLERANCE * truth)
        key = (stage.pass_.value, stage.level, depth.shape[::-1], stage.name)
        self.counts[key] += [
            np.sum(good & plain),
            np.sum(valid & plain),
            np.sum(good & ~plain),
            np.sum(valid & ~plain),
        ]

    def rows(self) -> list[dict]:
        order = {"start": 0, "propagation": 1, "prior": 2, "filtered": 3}
        rows = []
        for key in sorted(self.counts, key=lambda k: (k[0] != "photometric", k[1], order[k[3]])):
            good_plain, plain, good_textured, textured = (int(v) for v in self.counts[key])
            pass_value, level, size, stage = key
            rows.append(
                {
                    "pass": pass_value,
                    "level": level,
                    "size": "x".join(map(str, size)),
                    "stage": stage,
                    "plain_within_1_percent": good_plain / max(plain, 1),
                    "textured_within_1_percent": good_textured / max(textured, 1),
                }
            )
        return rows


def _scan_classes(
    ground_truth: Path, views: list, plain: dict[str, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """The ground-truth scan points (world frame) and whether each lies on a plain surface: scan
    ``i`` holds pixels of view ``i``, so each point projects onto its own pixel of that view."""
    from dvpmvs.evaluation.depth_scans import CAM_FROM_SCAN
    from dvpmvs.evaluation.pointclouds import read_meshlab_project

    points, on_plain = [], []
    by_stem = {Path(view.name).stem: view for view in views}
    for scan in read_meshlab_project(ground_truth / "scan_alignment.mlp"):
        view = by_stem[Path(scan.label).stem]
        camera = scan.points.astype(np.float64) @ CAM_FROM_SCAN.T
        pixel = camera @ view.K.T
        col = np.clip(np.round(pixel[:, 0] / pixel[:, 2]).astype(int), 0, view.width - 1)
        row = np.clip(np.round(pixel[:, 1] / pixel[:, 2]).astype(int), 0, view.height - 1)
        points.append(scan.global_points())
        on_plain.append(plain[view.name][row, col])
    return np.concatenate(points), np.concatenate(on_plain)


def diagnose(workspace: Path, out: Path, overrides: list[str]) -> dict:
    from dvpmvs import config
    from dvpmvs.dense import run_dense
    from dvpmvs.evaluation.depth_metrics import sky_point_share
    from dvpmvs.evaluation.pointclouds import read_points
    from dvpmvs.maps import read_depth_map
    from dvpmvs.patchmatch.estimator import observe_stages
    from dvpmvs.workspace import Workspace

    ground_truth = workspace / "ground_truth"
    views = Workspace.open(workspace).reference_views()
    truth = {v.name: read_depth_map(ground_truth / "depth_maps" / f"{v.name}.bin") for v in views}
    plain = {v.name: _mask(ground_truth / "textureless" / v.name) for v in views}
    if any(truth[v.name].shape != (v.height, v.width) for v in views):
        raise SystemExit(
            "the ground truth has another size than the views: run at the rendered size"
        )
    shares = StageShares(truth, plain)
    cfg = config.compose("dense", [f"workspace={workspace}", *overrides, "overwrite=true"])
    matched = Workspace.open(
        workspace, config.workspace_options(cfg)
    )  # at the size the options match at
    with observe_stages(shares):
        run_dense(matched, config.dense_options(cfg), out=out, progress=False)
    cloud = read_points(out / "fused.ply")
    scan, scan_plain = _scan_classes(ground_truth, views, plain)
    near = (
        cKDTree(cloud).query(scan, distance_upper_bound=CLOUD_TOLERANCE)[0] <= CLOUD_TOLERANCE
        if len(cloud)
        else np.zeros(len(scan), bool)
    )
    return {
        "workspace": str(workspace),
        "overrides": overrides,
        "stages": shares.rows(),
        "cloud": {
            "plain_complete_2cm": float(near[scan_plain].mean()) if scan_plain.any() else None,
            "textured_complete_2cm": float(near[~scan_plain].mean()),
            "points": int(len(cloud)),
            "sky_points": sky_point_share(
                cloud, [(v.K, v.R, v.t) for v in views], [truth[v.name] for v in views]
            ),
        },
    }


def table(result: dict) -> str:
    lines = [
        f"{result['workspace']} {' '.join(result['overrides'])}",
        "",
        "| pass | level | size | stage | plain < 1 % | textured < 1 % |",
        "|---|---|---|---|---|---|",
    ]
    for row in result["stages"]:
        lines.append(
            f"| {row['pass']} | {row['level']} | {row['size']} | {row['stage']} | "
            f"{100 * row['plain_within_1_percent']:.1f} | {100 * row['textured_within_1_percent']:.1f} |"
        )
    cloud = result["cloud"]
    plain = (
        "-" if cloud["plain_complete_2cm"] is None else f"{100 * cloud['plain_complete_2cm']:.1f}"
    )
    lines.append(
        f"| fused cloud | | {cloud['points']:,} pts | scan points within 2 cm | {plain} | "
        f"{100 * cloud['textured_complete_2cm']:.1f} |"
    )
    lines.append(f"\nsky points: {100 * cloud['sky_points']:.2f} % of the cloud")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("workspace", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("overrides", nargs="*")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    result = diagnose(args.workspace, args.out, args.overrides)
    print(table(result))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
