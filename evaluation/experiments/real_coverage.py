"""Coverage of real views by fused clouds, band by band of image rows: dvpmvs beside OpenMVS.

For a workspace of real images without a ground-truth cloud (``dvpmvs import dataset=strecha``
of ``../shared/data/strecha/fountain-P11``), each dvpmvs configuration and OpenMVS's
``DensifyPointCloud`` run on their own copy of the workspace at the same image size, one after
the other; then every cloud is projected into every view at that size. A view's pixel is
*covered* when a point of the cloud in front of the camera projects into it, after a
morphological closing of one pixel (a 3x3 kernel) that closes the gaps between neighbouring
splats. The share of covered pixels is given per band of image rows (fifths by default, top to
bottom) and for the whole view, averaged over the views. Occlusion is not modelled (a point
behind a nearer surface covers the pixel too): on a scene that is mostly one facade it matters
little, and it is the same rule for every cloud.

``--renders DIR`` also writes, for the views of ``--render-views``, the photo beside each
cloud's points splatted into that view with a depth test (the nearest point wins), as one JPEG
strip per view (at most 1536 px wide).

    python -m dvpmvs.evaluation.experiments.real_coverage --workspace fountain_ws \\
        --openmvs $PEERS/openMVS/make/bin --size 768 --threads 2 --configs "" \\
        --renders docs/images --render-views 0000.jpg,0005.jpg

(``""``: the default configuration; a config is a string of dense overrides.) OpenMVS works at
the same size through ``--resolution-level`` (the power-of-two reduction that gives it) and
``--max-resolution``. Prints a markdown table; ``--out`` keeps the runs and a ``coverage.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np

from dvpmvs.evaluation.experiments.openmvs_suite import check_openmvs, densify, timed
from dvpmvs.workspace import Workspace, WorkspaceOptions

RENDER_MAX_WIDTH = 1536  # a render strip wider than this is scaled down (the files go into docs/)


def _copy_workspace(workspace: Path, target: Path) -> Path:
    """A fresh copy: images and the sparse model linked (read only), ``stereo/*.cfg`` copied."""
    if target.exists():
        shutil.rmtree(target)
    (target / "stereo").mkdir(parents=True)
    for name in ("images", "sparse"):
        (target / name).symlink_to((workspace / name).resolve(), target_is_directory=True)
    for cfg in (workspace / "stereo").glob("*.cfg"):
        shutil.copy2(cfg, target / "stereo" / cfg.name)
    return target


def _read_cloud(path: Path) -> tuple[np.ndarray, np.ndarray]:
    from dvpmvs.pointcloud import read_cloud

    cloud = read_cloud(path)
    points = np.asarray(cloud.points, np.float64)
    if len(points) == 0:
        raise SystemExit(f"{path}: no points")
    colours = (
        np.asarray(cloud.colors, np.float64) if cloud.has_colors() else np.full_like(points, 0.7)
    )
    return points, colours


def _project(points: np.ndarray, view) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel columns, rows (rounded) and depths of the points in front of ``view`` inside it."""
    X = points @ view.R.T + view.t
    front = X[:, 2] > 0
    X = X[front]
    uv = X @ view.K.T
    col = np.floor(uv[:, 0] / uv[:, 2] + 0.5).astype(np.int64)
    row = np.floor(uv[:, 1] / uv[:, 2] + 0.5).astype(np.int64)
    inside = (col >= 0) & (col < view.width) & (row >= 0) & (row < view.height)
    return col[inside], row[inside], np.flatnonzero(front)[inside]


def coverage(points: np.ndarray, view, bands: int = 5) -> np.ndarray:
    """(bands + 1,) shares (%) of ``view``'s pixels covered by ``points``, per band of rows and
    for the whole view (see the module doc)."""
    col, row, _ = _project(points, view)
    covered = np.zeros((view.height, view.width), np.uint8)
    covered[row, col] = 1
    covered = cv2.morphologyEx(covered, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))
    edges = np.linspace(0, view.height, bands + 1).round().astype(int)
    shares = [covered[edges[b] : edges[b + 1]].mean() for b in range(bands)]
    return 100 * np.array(shares + [covered.mean()])


def render(points: np.ndarray, colours: np.ndarray, view) -> np.ndarray:
    """The points splatted into ``view`` (one pixel each, the nearest wins), BGR uint8, black
    where no point falls."""
    col, row, index = _project(points, view)
    depth = (points[index] @ view.R[2]) + view.t[2]
    order = np.argsort(-depth)  # far first: the nearest is written last
    image = np.zeros((view.height, view.width, 3), np.uint8)
    rgb = np.clip(colours[index[order]] * 255 + 0.5, 0, 255).astype(np.uint8)
    image[row[order], col[order]] = rgb[:, ::-1]
    return image


def _label(image: np.ndarray, text: str) -> np.ndarray:
    image = image.copy()
    cv2.putText(
        image, text, (10, 30), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 255, 255), 2, cv2.LINE_AA
    )
    return image


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--workspace", type=Path, required=True, help="a COLMAP workspace of real images"
    )
    parser.add_argument("--openmvs", type=Path, help="OpenMVS's bin folder (none: dvpmvs alone)")
    parser.add_argument(
        "--size", type=int, default=768, help="the longer image side the tools work at"
    )
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument(
        "--configs", nargs="*", default=[""], help="dvpmvs overrides, one string each"
    )
    parser.add_argument("--bands", type=int, default=5)
    parser.add_argument("--renders", type=Path, help="folder for the renders (photo | each cloud)")
    parser.add_argument("--render-views", default="", help="comma-separated image names to render")
    parser.add_argument("--out", type=Path, default=Path("real_coverage"))
    args = parser.parse_args(argv)
    workspace = args.workspace.resolve()
    base = Workspace.open(workspace)
    full = max(max(view.width, view.height) for view in base.views.values())
    if args.openmvs is not None:
        check_openmvs(args.openmvs)
        level = math.log2(full / args.size)
        if abs(level - round(level)) > 1e-6:
            raise SystemExit(
                f"--size {args.size}: OpenMVS reduces the images {full} px long by powers of two; "
                f"give {full // 2}, {full // 4}, ..."
            )

    dvpmvs = [sys.executable, "-m", "dvpmvs.cli"]
    runs = []  # (tool, cloud, seconds per view, peak MB)
    out = args.out.resolve()
    if args.openmvs is not None:
        work = _copy_workspace(workspace, out / "openmvs")
        seconds, peak = densify(
            args.openmvs,
            work,
            args.threads,
            "--resolution-level",
            str(round(level)),
            "--max-resolution",
            str(args.size),
        )
        runs.append(
            ("OpenMVS DensifyPointCloud", work / "scene_dense.ply", seconds / len(base.views), peak)
        )
    for index, config in enumerate(args.configs):
        work = _copy_workspace(workspace, out / f"dvpmvs{index}")
        command = dvpmvs + [
            "dense",
            f"workspace={work}",
            f"num_threads={args.threads}",
            f"max_image_size={args.size}",
            *config.split(),
        ]
        seconds, peak = timed(command, work, work / "dense.log")
        runs.append(
            (f"dvpmvs {config or '(default)'}", work / "fused.ply", seconds / len(base.views), peak)
        )

    views = Workspace.open(workspace, WorkspaceOptions(max_image_size=args.size)).views
    clouds = {tool: _read_cloud(cloud) for tool, cloud, _, _ in runs}
    table = {}
    for tool, seconds, peak in ((r[0], r[2], r[3]) for r in runs):
        per_view = {
            name: coverage(clouds[tool][0], view, args.bands).tolist()
            for name, view in views.items()
        }
        table[tool] = {
            "per_view": per_view,
            "mean": np.mean(list(per_view.values()), axis=0).tolist(),
            "points": len(clouds[tool][0]),
            "seconds_per_view": seconds,
            "peak_mb": peak,
        }
    (out / "coverage.json").write_text(json.dumps(table, indent=2))

    size = next(iter(views.values()))
    bands = " | ".join(f"rows {b + 1} / {args.bands}" for b in range(args.bands))
    print(
        f"{workspace.name}, {len(views)} views at {size.width}x{size.height}: share of pixels covered "
        f"(mean over views)\n"
    )
    print(f"| tool | {bands} | whole view | points | s / view | peak MB |")
    print("|---|" + "---|" * (args.bands + 4))
    for tool, row in table.items():
        shares = " | ".join(f"{v:.1f} %" for v in row["mean"])
        print(
            f"| {tool} | {shares} | {row['points']:,} | {row['seconds_per_view']:.1f} | {row['peak_mb']:.0f} |"
        )

    if args.renders is not None and args.render_views:
        args.renders.mkdir(parents=True, exist_ok=True)
        for name in args.render_views.split(","):
            view = views[name]
            photo = cv2.resize(
                cv2.imread(str(workspace / "images" / name)),
                (view.width, view.height),
                interpolation=cv2.INTER_AREA,
            )
            panels = [_label(photo, "photo")] + [
                _label(render(*clouds[tool], view), tool.split(" (")[0]) for tool in clouds
            ]
            strip = np.hstack(panels)
            if strip.shape[1] > RENDER_MAX_WIDTH:
                scale = RENDER_MAX_WIDTH / strip.shape[1]
                strip = cv2.resize(
                    strip,
                    (RENDER_MAX_WIDTH, round(strip.shape[0] * scale)),
                    interpolation=cv2.INTER_AREA,
                )
            target = (
                args.renders / f"coverage_{Path(workspace).name}_{Path(name).stem}_{view.width}.jpg"
            )
            cv2.imwrite(str(target), strip, [cv2.IMWRITE_JPEG_QUALITY, 85])
            print(f"render: {target}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
