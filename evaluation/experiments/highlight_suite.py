"""Highlight perception on the synthetic suite: the tables of docs/benchmarks.md from bench sweeps.

Reads the jobs of one or more ``dvpmvs bench`` sweep folders (``multirun/bench-*``), groups them
by their overrides other than the scene and the estimator's seed, and prints per configuration:

- F1 at 2 and 10 cm per scene and their mean (ETH3D metric), each a mean over the estimator's
  seeds with its spread (min-max of the seeds' figures) when the sweep ran several;
- the share of ground-truth highlight pixels whose final depth is within 1 % of the truth (a
  pixel without an estimate counts as a failure), the share with an estimate, the share within
  1 % of those, and the first share outside the highlights (pooled over the scenes' views and
  the seeds by pixel);
- the highlight masks' precision and recall against the ground truth (the masks the final maps
  used, and the provider's own), pooled by pixel;
- the highlight stage's share of the views' time: its seconds (provider and multi-view
  refinement, from the records) over those plus the maps' seconds of both passes.

    python -m dvpmvs.evaluation.experiments.highlight_suite multirun/bench-XXXX [multirun/bench-YYYY ...]

With ``--masks``, the arguments are synthetic scenes instead (``bench_scenes/room_8v_800_seed0``
...): the single-image providers (``--providers``, default dichromatic and threshold with their
defaults) are run on every view and their masks scored against the ground truth, per scene and
pooled, with the seconds per view.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np


def _job_rows(sweep: Path):
    for manifest in sorted(sweep.glob("*/dvpmvs_run.json")):
        data = json.loads(manifest.read_text())
        if data.get("status") not in (None, "ok", "completed", "done"):
            continue
        overrides = [
            o
            for o in data.get("overrides", [])
            if not o.startswith(("scene=", "seed=", "progress=", "num_threads="))
        ]
        scene = next(o.split("=", 1)[1] for o in data["overrides"] if o.startswith("scene="))
        seed = next((o.split("=", 1)[1] for o in data["overrides"] if o.startswith("seed=")), "")
        yield " ".join(overrides), scene, seed, data, manifest.parent


def _ground_truth(path: str | None, sweep: Path) -> Path | None:
    """The ground-truth folder of a job: its manifest's path, relative to where the sweep ran
    (the folder holding ``multirun/``) when it is not absolute."""
    if not path:
        return None
    path = Path(path)
    for base in (Path.cwd(), sweep.resolve().parent.parent):
        candidate = path if path.is_absolute() else base / path
        if candidate.is_file():
            return candidate.parent
    return None


def _seconds(stereo: Path) -> tuple[float, float]:
    """(highlight seconds, maps seconds) from the records of a job's maps folder."""
    highlight = maps = 0.0
    for record in (stereo / "provenance").glob("*.json"):
        stats = json.loads(record.read_text()).get("stats", {})
        if ".highlight" in record.name:
            highlight += float(stats.get("seconds", 0.0))
        elif record.name.endswith((".photometric.json", ".geometric.json")):
            maps += float(stats.get("seconds", 0.0))
    return highlight, maps


def summarise(sweeps: list[Path]) -> list[dict]:
    from dvpmvs.evaluation.depth_metrics import evaluate_depth_maps

    groups: dict[str, dict] = defaultdict(
        lambda: {
            "f1": defaultdict(dict),
            "in": [0.0, 0],
            "out": [0.0, 0],
            "estimated": 0.0,
            "final": [0, 0, 0],
            "single": [0, 0, 0],
            "seconds": [0.0, 0.0],
        }
    )
    for sweep in sweeps:
        for label, scene, seed, data, folder in _job_rows(sweep):
            group = groups[label]
            evaluation = data.get("evaluation") or {}
            eth3d = evaluation.get("eth3d")
            if eth3d:
                group["f1"][scene][seed] = [100 * f for f in eth3d["f1"]]
            truth = _ground_truth(evaluation.get("ground_truth"), sweep)
            if truth is not None and (truth / "highlights").is_dir():
                # Scored here, not read from the manifest: the same code for every sweep.
                views = evaluate_depth_maps(folder / "stereo" / "depth_maps", truth / "depth_maps")
                for v in views:
                    group["in"][0] += v.highlight_within_1_percent * v.highlight_pixels
                    group["in"][1] += v.highlight_pixels
                    group["estimated"] += v.highlight_estimated * v.highlight_pixels
                    outside = v.valid_pixels - v.highlight_pixels
                    group["out"][0] += v.outside_within_1_percent * outside
                    group["out"][1] += outside
            masks = evaluation.get("highlight_masks")
            if masks:
                for key, counts in (("final", masks), ("single", masks.get("single_view", {}))):
                    for i, name in enumerate(("true_positive", "false_positive", "false_negative")):
                        group[key][i] += int(counts.get(name, 0))
            highlight, maps = _seconds(folder / "stereo")
            group["seconds"][0] += highlight
            group["seconds"][1] += maps
    rows = []
    for label, group in groups.items():
        f1 = group["f1"]
        scenes = {scene: _over_seeds(list(by_seed.values())) for scene, by_seed in f1.items()}
        # The suite's mean per seed (over the scenes every seed ran), then over the seeds.
        seeds = sorted(set.intersection(*(set(by_seed) for by_seed in f1.values()))) if f1 else []
        mean = (
            _over_seeds(
                [list(np.mean([f1[scene][seed] for scene in f1], axis=0)) for seed in seeds]
            )
            if seeds
            else None
        )

        def ratio(a, b):
            return a / b if b else None

        tp, fp, fn = group["final"]
        stp, sfp, sfn = group["single"]
        highlight, maps = group["seconds"]
        rows.append(
            {
                "config": label or "(none)",
                "scenes": scenes,
                "mean": mean,
                "in_highlight": ratio(group["in"][0], group["in"][1]),
                "highlight_pixels": group["in"][1],
                "estimated": ratio(group["estimated"], group["in"][1]),
                "accuracy": ratio(group["in"][0], group["estimated"]),
                "outside": ratio(group["out"][0], group["out"][1]),
                "precision": ratio(tp, tp + fp),
                "recall": ratio(tp, tp + fn),
                "provider_precision": ratio(stp, stp + sfp),
                "provider_recall": ratio(stp, stp + sfn),
                "time_share": ratio(highlight, highlight + maps) if highlight else None,
            }
        )
    return rows


def _over_seeds(values: list[list[float]]) -> list[tuple[float, float, float]]:
    """Per tolerance, the mean of the seeds' F1 and their minimum and maximum."""
    columns = np.asarray(values, dtype=float).T
    return [(float(c.mean()), float(c.min()), float(c.max())) for c in columns]


def _f1_cell(figures: list[tuple[float, float, float]]) -> str:
    """``mean (min-max) / ...``; the spread left out when one seed ran."""
    return " / ".join(
        f"{m:.2f}" + (f" ({lo:.2f}-{hi:.2f})" if hi > lo else "") for m, lo, hi in figures
    )


def _pct(value) -> str:
    return "-" if value is None else f"{100 * value:.1f}"


def provider_masks(scenes: list[Path], providers: list[str]) -> None:
    """Print the single-image providers' mask precision and recall per scene and pooled."""
    import time

    import cv2

    from dvpmvs import registry
    from dvpmvs.evaluation.highlight_metrics import mask_metrics, pooled_mask_metrics
    from dvpmvs.priors import PriorContext
    from dvpmvs.workspace import Workspace

    print(
        "| provider | "
        + " | ".join(f"{s.name}: P / R (true px)" for s in scenes)
        + " | all: P / R | s / view |"
    )
    print("|---" * (len(scenes) + 3) + "|")
    for name in providers:
        provider = registry.create("highlight", {"name": name})
        cells, everything, seconds, views = [], [], 0.0, 0
        for scene in scenes:
            workspace = Workspace.open(scene)
            results = []
            for view in workspace.reference_views():
                ctx = PriorContext(
                    view.name, view.load_grey(), view.K, view.depth_range, rgb_loader=view.load_rgb
                )
                start = time.perf_counter()
                _, mask = provider(ctx)
                seconds += time.perf_counter() - start
                views += 1
                truth = (
                    cv2.imread(
                        str(scene / "ground_truth" / "highlights" / view.name), cv2.IMREAD_GRAYSCALE
                    )
                    > 127
                )
                results.append(mask_metrics(view.name, mask, truth))
            pooled = pooled_mask_metrics(results)
            everything += results
            cells.append(
                f"{_pct(pooled.precision)} / {_pct(pooled.recall)} "
                f"({pooled.true_positive + pooled.false_negative:,})"
            )
        pooled = pooled_mask_metrics(everything)
        print(
            f"| `{name}` | "
            + " | ".join(cells)
            + f" | {_pct(pooled.precision)} / {_pct(pooled.recall)} | "
            f"{seconds / max(views, 1):.3f} |"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "folders",
        nargs="+",
        type=Path,
        help="dvpmvs bench sweep folders (multirun/bench-*), or with --masks synthetic scenes",
    )
    parser.add_argument(
        "--masks", action="store_true", help="score the single-image providers' masks on scenes"
    )
    parser.add_argument("--providers", nargs="+", default=["dichromatic", "threshold"])
    args = parser.parse_args()
    if args.masks:
        provider_masks(args.folders, args.providers)
        return
    rows = summarise(args.folders)
    names = sorted({s for row in rows for s in row["scenes"]})
    print(
        "| config | "
        + " | ".join(f"{s} F1 2 / 10 cm" for s in names)
        + " | mean F1 2 / 10 cm | highlight px: "
        "depth < 1 % | estimated | < 1 % of estimated | outside: < 1 % | mask P / R (used) | "
        "mask P / R (provider) | highlight time share |"
    )
    print("|---" * (len(names) + 9) + "|")
    for row in rows:
        cells = [_f1_cell(row["scenes"][s]) if s in row["scenes"] else "-" for s in names]
        mean = _f1_cell(row["mean"]) if row["mean"] else "-"
        print(
            f"| `{row['config']}` | "
            + " | ".join(cells)
            + f" | {mean} | {_pct(row['in_highlight'])} % of "
            f"{row['highlight_pixels']:,} | {_pct(row['estimated'])} % | {_pct(row['accuracy'])} % | "
            f"{_pct(row['outside'])} % | {_pct(row['precision'])} / "
            f"{_pct(row['recall'])} | {_pct(row['provider_precision'])} / {_pct(row['provider_recall'])} | "
            f"{_pct(row['time_share'])} % |"
        )


if __name__ == "__main__":
    main()
