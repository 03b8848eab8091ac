"""A synthetic scene's open sky as masks, and what masked runs made of it.

``write``: each view's sky (no surface along its ray: ground-truth depth 0) as a mask in COLMAP's
layout (``DIR/<image name>.png``, 0 masked, 255 kept), for ``mask=files mask.path=DIR``.

``check``: for a run made with those masks, per view, how many masked pixels have a depth in the
photometric and geometric maps (the mask's promise: none), and the run's figures from its
manifest (F1, sky points, dense seconds).

    python -m dvpmvs.evaluation.experiments.sky_masks write WORKSPACE DIR
    python -m dvpmvs.evaluation.experiments.sky_masks check WORKSPACE DIR [RUN.json ...]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from dvpmvs.maps import map_path, path_from_manifest, read_depth_map
from dvpmvs.run import MANIFEST_NAME

__all__ = ["write_sky_masks", "masked_depths", "windows_per_pixel"]


def _truth(workspace: Path, name: str) -> np.ndarray:
    return read_depth_map(workspace / "ground_truth" / "depth_maps" / f"{name}.bin")


def _names(workspace: Path) -> list[str]:
    return sorted(
        p.name[: -len(".bin")] for p in (workspace / "ground_truth" / "depth_maps").glob("*.bin")
    )


def write_sky_masks(workspace: str | Path, folder: str | Path) -> dict[str, float]:
    """Write each view's sky mask into ``folder``; returns the sky's share of each view."""
    workspace, folder = Path(workspace), Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    shares = {}
    for name in _names(workspace):
        sky = ~(_truth(workspace, name) > 0)
        if not cv2.imwrite(str(folder / f"{name}.png"), np.where(sky, 0, 255).astype(np.uint8)):
            raise OSError(f"cannot write {folder / (name + '.png')}")
        shares[name] = float(sky.mean())
    return shares


def masked_depths(stereo: str | Path, folder: str | Path) -> dict[str, dict[str, int]]:
    """Per view and pass: the masked pixels that have a depth in the maps under ``stereo``."""
    stereo, folder = Path(stereo), Path(folder)
    found = {}
    for mask in sorted(folder.glob("*.png")):
        name = mask.name[: -len(".png")]
        masked = cv2.imread(str(mask), cv2.IMREAD_GRAYSCALE) == 0
        found[name] = {}
        for pass_ in ("photometric", "geometric"):
            path = map_path(stereo, name, "depth", pass_)
            if path.is_file():
                depth = read_depth_map(path)
                found[name][pass_] = int((depth[masked] > 0).sum())
    return found


def windows_per_pixel(report: dict) -> float:
    """The matching windows a run's views scored, both passes and every level, per pixel of
    the views at full size (the work a run did, whatever else the machine was doing)."""
    windows = pixels = 0
    for pass_ in report["dense"]["passes"].values():
        for view in pass_["view_reports"]:
            if view["action"] != "computed":
                continue
            windows += sum(level["windows"] for level in view["work"])
            if pass_ is report["dense"]["passes"].get("photometric"):
                pixels += view["size"][0] * view["size"][1]
    return windows / max(pixels, 1)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("action", choices=("write", "check"))
    parser.add_argument("workspace", type=Path)
    parser.add_argument("folder", type=Path)
    parser.add_argument(
        "runs", nargs="*", type=Path, help="run manifests (report=...) to summarise"
    )
    args = parser.parse_args(argv)
    if args.action == "write":
        shares = write_sky_masks(args.workspace, args.folder)
        print(
            f"{len(shares)} masks in {args.folder}; sky {100 * np.mean(list(shares.values())):.1f} % of the pixels"
        )
        return 0
    for run in args.runs:
        report = json.loads(run.read_text())
        # A run folder's own manifest names its files relative to it; a report= copy elsewhere
        # relative to the run folder it records ("out").
        folder = run.parent if run.name == MANIFEST_NAME else Path(report.get("out", run.parent))
        stereo = path_from_manifest(report["dense"]["stereo_dir"], folder)
        found = masked_depths(stereo, args.folder)
        evaluation = report["evaluation"]
        f1 = evaluation["eth3d"]["f1"]
        print(
            f"{run}: F1 {100 * f1[0]:.2f} / {100 * f1[1]:.2f}, sky points "
            f"{100 * (evaluation.get('sky_points') or 0):.2f} %, dense {report['dense']['wall_seconds']:.0f} s, "
            f"{windows_per_pixel(report):.0f} windows per pixel, "
            f"masked pixels with a depth: {sum(sum(v.values()) for v in found.values())}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
