"""Recovered cameras against given ones (:func:`dvpmvs.evaluation.poses.pose_errors`).

The reference is a COLMAP model (``--model``) or a Strecha scene's camera files (``--strecha``,
the ``*.camera`` files under ``gt_dense_cameras/``); intrinsics are compared too where both
models have them (focal length, principal point, in pixels of the reference's image size).

    python -m dvpmvs.evaluation.experiments.camera_errors OUT/sparse/0 --strecha fountain-P11

Prints a markdown table.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from dvpmvs.evaluation.poses import pose_errors
from dvpmvs.evaluation.strecha import _find_camera_files, read_strecha_camera


def strecha_cameras(scene: Path) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, int]]:
    """image name -> (R world-to-camera, centre, K, width)."""
    cameras = {}
    for name, path in _find_camera_files(scene).items():
        camera = read_strecha_camera(path)
        cameras[name] = (camera.R, camera.center, camera.K, camera.width)
    return cameras


def intrinsics_table(model, reference: dict) -> str:
    """Per camera of ``model``: focal length(s) and principal point against the reference's,
    scaled to the reference's width."""
    lines = [
        "| camera | images | model | focal (px) | given focal | principal point | given |",
        "|---|---:|---|---|---|---|---|",
    ]
    for camera_id, camera in sorted(model.cameras.items()):
        names = [
            im.name
            for im in model.images.values()
            if im.camera_id == camera_id and im.name in reference
        ]
        if not names:
            continue
        _, _, K, width = reference[names[0]]
        scale = width / camera.width
        focal = f"{scale * camera.focal_length_x:.1f}"
        if camera.focal_length_x != camera.focal_length_y:
            focal += f", {scale * camera.focal_length_y:.1f}"
        lines.append(
            f"| {camera_id} | {len(names)} | {camera.model.name} | {focal} | {K[0, 0]:.1f}, {K[1, 1]:.1f} | "
            f"{scale * camera.principal_point_x:.1f}, {scale * camera.principal_point_y:.1f} | "
            f"{K[0, 2]:.1f}, {K[1, 2]:.1f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    import pycolmap

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("model", type=Path, help="the recovered COLMAP model")
    given = parser.add_mutually_exclusive_group(required=True)
    given.add_argument(
        "--model", dest="reference_model", type=Path, help="a COLMAP model with the given poses"
    )
    given.add_argument("--strecha", type=Path, help="a Strecha scene folder (its *.camera files)")
    args = parser.parse_args(argv)
    model = pycolmap.Reconstruction(str(args.model))
    if args.strecha is not None:
        cameras = strecha_cameras(args.strecha)
        errors = pose_errors(model, {name: (R, c) for name, (R, c, _, _) in cameras.items()})
    else:
        errors = pose_errors(model, pycolmap.Reconstruction(str(args.reference_model)))
    print(errors.table())
    print(
        f"\ncentre errors in the reference's units; camera extent {errors.extent:.3f}, similarity scale "
        f"{errors.scale:.4f}"
    )
    if args.strecha is not None:
        print()
        print(intrinsics_table(model, cameras))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
