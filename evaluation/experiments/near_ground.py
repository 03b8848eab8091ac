"""Where a view's depth is lost, band by band of image rows, and why it may be, from ground truth.

For each view of a synthetic workspace that ``dvpmvs dense`` has run on (``stereo/depth_maps``
beside ``ground_truth/``): the share of ground-truth pixels whose estimated depth lies within
1 % of the truth, per band of image rows (fifths by default, top to bottom), and for the pixels
lost, the conditions that can explain it, each measured on its own (a pixel can meet several):

- ``range``: the true depth lies outside the view's depth range (the sparse points' quantiles,
  stretched: where random hypotheses are drawn; propagation and refinement are not bounded by it);
- ``sources<2``: fewer than 2 of the view's sources see the true point (inside the source image,
  in front of it, not occluded: the source's true depth there within 1 %);
- ``grazing``: the angle between the viewing ray and the true surface normal exceeds 75 degrees.

Beside the share of all ground-truth pixels, the share of those that at least 2 sources see
(the pixels two-view matching can reach), and both for the rows above the bottom band together.

    python -m dvpmvs.evaluation.experiments.near_ground WORKSPACE [--pass geometric] [--bands 5]

WORKSPACE is a scene made by ``dvpmvs synth`` that ``dvpmvs dense`` ran on, or a ``dvpmvs bench``
job's folder (whose images link into its scene, where the ground truth is).

Prints a markdown table per workspace; ``--json`` writes the figures.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from dvpmvs.evaluation.depth_scans import backproject, visible_in
from dvpmvs.maps import read_depth_map, read_normal_map
from dvpmvs.workspace import Workspace

GRAZING_DEGREES = 75.0
TOLERANCE = 0.01


def _sources_seeing(
    ws: Workspace, view, truth: np.ndarray, truths: dict[str, np.ndarray]
) -> np.ndarray:
    """Per pixel of ``view``, how many of its sources see the true point (see the module doc)."""
    rows, cols = np.nonzero(truth > 0)
    world = backproject(truth, view.K, view.R, view.t, rows, cols)
    count = np.zeros(truth.shape, np.int32)
    for name in view.sources:
        source = ws[name]
        count[rows, cols] += visible_in(world, source.R, source.t, source.K, truths[name])
    return count


def _grazing(view, normal: np.ndarray, truth: np.ndarray) -> np.ndarray:
    h, w = truth.shape
    rows, cols = np.mgrid[0:h, 0:w]
    rays = np.stack(
        [
            (cols - view.K[0, 2]) / view.K[0, 0],
            (rows - view.K[1, 2]) / view.K[1, 1],
            np.ones((h, w)),
        ],
        -1,
    )
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    cos = np.abs(np.sum(rays * normal, axis=-1))
    return (truth > 0) & (cos < np.cos(np.deg2rad(GRAZING_DEGREES)))


def analyse(root: Path, pass_name: str = "geometric", bands: int = 5) -> dict:
    gt = root / "ground_truth"
    if not gt.is_dir() and (root / "images").is_symlink():
        # a `dvpmvs bench` job's folder: its images link into the scene, which holds the ground truth
        gt = (root / "images").resolve().parent / "ground_truth"
    if not (gt / "depth_maps").is_dir() or not (gt / "normal_maps").is_dir():
        raise SystemExit(
            f"{root}: no ground_truth/depth_maps and normal_maps; give a workspace made by "
            f"`dvpmvs synth` (after `dvpmvs dense` has run on it) or a `dvpmvs bench` job's folder"
        )
    ws = Workspace.open(root)
    if not any(
        (root / "stereo" / "depth_maps" / f"{name}.{pass_name}.bin").exists() for name in ws.views
    ):
        raise SystemExit(
            f"{root}: no {pass_name} depth map in stereo/depth_maps; run `dvpmvs dense` on it, or "
            f"give the folder of a `dvpmvs bench` job"
        )
    truths = {name: read_depth_map(gt / "depth_maps" / f"{name}.bin") for name in ws.views}
    # pixels, within 1 %, lost, range, sources<2, grazing; seen by >= 2 sources, of them within 1 %
    per_band = np.zeros((bands, 8))
    for name in sorted(ws.views):
        view = ws[name]
        truth = truths[name]
        estimate_path = root / "stereo" / "depth_maps" / f"{name}.{pass_name}.bin"
        if not estimate_path.exists():
            continue
        depth = read_depth_map(estimate_path)
        if depth.shape != truth.shape:
            raise SystemExit(
                f"{estimate_path}: {depth.shape} against the ground truth's {truth.shape}; "
                f"run dense at the images' own size"
            )
        normal = read_normal_map(gt / "normal_maps" / f"{name}.bin")
        valid = truth > 0
        good = valid & (np.abs(depth - truth) <= TOLERANCE * truth)
        lost = valid & ~good
        lo, hi = view.depth_range
        out_range = valid & ((truth < lo) | (truth > hi))
        few = valid & (_sources_seeing(ws, view, truth, truths) < 2)
        grazing = _grazing(view, normal, truth)
        edges = np.linspace(0, truth.shape[0], bands + 1).round().astype(int)
        for b in range(bands):
            rows = slice(edges[b], edges[b + 1])
            per_band[b] += [
                valid[rows].sum(),
                good[rows].sum(),
                lost[rows].sum(),
                (lost & out_range)[rows].sum(),
                (lost & few)[rows].sum(),
                (lost & grazing)[rows].sum(),
                (valid & ~few)[rows].sum(),
                (good & ~few)[rows].sum(),
            ]
    rows = []
    for b in range(bands):
        pixels, good, lost, *why, seen, seen_good = per_band[b]
        rows.append(
            {
                "band": b,
                "within_1pct": 100 * good / max(pixels, 1),
                "seen_within_1pct": 100 * seen_good / max(seen, 1),
                **{
                    key: 100 * v / max(lost, 1)
                    for key, v in zip(("range", "sources<2", "grazing"), why)
                },
            }
        )
    # The image above the bottom band, for the comparison "near ground against the rest".
    pixels, good, *_, seen, seen_good = per_band[:-1].sum(axis=0)
    rest = {
        "within_1pct": 100 * good / max(pixels, 1),
        "seen_within_1pct": 100 * seen_good / max(seen, 1),
    }
    return {"workspace": str(root), "pass": pass_name, "bands": rows, "above_bottom": rest}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("workspaces", nargs="+", type=Path)
    parser.add_argument(
        "--pass", dest="pass_name", default="geometric", choices=("photometric", "geometric")
    )
    parser.add_argument("--bands", type=int, default=5)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    results = [analyse(root, args.pass_name, args.bands) for root in args.workspaces]
    for result in results:
        print(
            f"\n{result['workspace']} ({result['pass']} maps); of the lost pixels, the share that ...\n"
        )
        print(
            "| rows | depth within 1 % | ... of the pixels >= 2 sources see | lost: outside range | "
            "< 2 sources see it | grazing > 75 deg |"
        )
        print("|---|---|---|---|---|---|")
        for row in result["bands"]:
            print(
                f"| {row['band'] + 1} / {args.bands} | {row['within_1pct']:.1f} % | {row['seen_within_1pct']:.1f} % | "
                f"{row['range']:.1f} % | {row['sources<2']:.1f} % | {row['grazing']:.1f} % |"
            )
        rest = result["above_bottom"]
        print(
            f"| 1-{args.bands - 1} / {args.bands} | {rest['within_1pct']:.1f} % | {rest['seen_within_1pct']:.1f} % "
            f"| | | |"
        )
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
