"""Readers for benchmark layouts, turning each scene into a COLMAP dense workspace.

- ETH3D high-resolution multi-view: ``images/dslr_images_undistorted/*.JPG``,
  ``dslr_calibration_undistorted/{cameras,images,points3D}.txt`` (a COLMAP text model whose image
  names include the ``dslr_images_undistorted/`` prefix) and ``dslr_scan_eval/scan_alignment.mlp``.
- Tanks and Temples, COLMAP layout (``images/`` + ``sparse/``, or a ``dense/`` folder from
  ``colmap image_undistorter``) or MVSNet layout (``images/``, ``cams/<id>_cam.txt`` with
  extrinsic, intrinsic and depth range, ``pair.txt``), with the ground truth beside it.

ETH3D and COLMAP-layout workspaces link ``images`` to the scene's images (nothing is copied); an
MVSNet scene has no sparse points, so its images are copied and a sparse model is triangulated
with its cameras held fixed (as for Strecha).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from dvpmvs.errors import DvpmvsError
from dvpmvs.evaluation.strecha import StrechaCamera, import_with_known_poses
from dvpmvs.workspace import write_stereo_configs

__all__ = ["ETH3DScene", "prepare_eth3d", "prepare_tanks", "read_mvsnet_cam"]


@dataclass
class ETH3DScene:
    root: Path
    images: Path
    calibration: Path
    ground_truth: Path

    @classmethod
    def open(cls, root: str | Path) -> ETH3DScene:
        root = Path(root)
        scene = cls(
            root,
            root / "images",
            root / "dslr_calibration_undistorted",
            root / "dslr_scan_eval" / "scan_alignment.mlp",
        )
        if not (scene.images / "dslr_images_undistorted").is_dir():
            raise DvpmvsError(
                f"{root} is not an ETH3D scene: images/dslr_images_undistorted/ is missing"
            )
        if not (scene.calibration / "cameras.txt").is_file():
            raise DvpmvsError(
                f"{root} is not an ETH3D scene: dslr_calibration_undistorted/cameras.txt is missing"
            )
        return scene


def _link_images(source: Path, out: Path) -> None:
    target = out / "images"
    if target.is_symlink() or target.exists():
        if target.resolve() == source.resolve():
            return
        raise DvpmvsError(
            f"{target} exists and is not a link to {source}; choose an empty output folder"
        )
    os.symlink(source.resolve(), target, target_is_directory=True)


def _write_configs(out: Path, names: list[str], num_sources: int) -> None:
    n = min(num_sources, len(names) - 1)
    write_stereo_configs(out / "stereo", {name: f"__auto__, {n}" for name in names})


def _check_pinhole(recon: pycolmap.Reconstruction, where: Path) -> None:
    for cam in recon.cameras.values():
        if cam.model.name not in ("PINHOLE", "SIMPLE_PINHOLE"):
            raise DvpmvsError(
                f"{where}: camera {cam.camera_id} is {cam.model.name}; the undistorted "
                "calibration (PINHOLE) is needed"
            )


def prepare_eth3d(scene_dir: str | Path, out: str | Path, num_sources: int = 20) -> Path:
    """A COLMAP workspace for an ETH3D high-resolution scene; returns the ground-truth MLP path."""
    scene = ETH3DScene.open(scene_dir)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    recon = pycolmap.Reconstruction(str(scene.calibration))
    _check_pinhole(recon, scene.calibration)
    missing = [im.name for im in recon.images.values() if not (scene.images / im.name).is_file()]
    if missing:
        raise DvpmvsError(
            f"{len(missing)} calibrated images are missing under {scene.images}, e.g. {missing[0]}"
        )
    (out / "sparse").mkdir(exist_ok=True)
    recon.write(str(out / "sparse"))
    _link_images(scene.images, out)
    _write_configs(out, sorted(im.name for im in recon.images.values()), num_sources)
    return scene.ground_truth


def read_mvsnet_cam(path: str | Path) -> tuple[np.ndarray, np.ndarray, float, float]:
    """``(world_to_cam 4x4, K 3x3, depth_min, depth_interval)`` of an MVSNet ``*_cam.txt``."""
    path = Path(path)
    tokens = path.read_text().split()
    try:
        e = tokens.index("extrinsic")
        i = tokens.index("intrinsic")
        E = np.array(tokens[e + 1 : e + 17], float).reshape(4, 4)
        K = np.array(tokens[i + 1 : i + 10], float).reshape(3, 3)
        rest = [float(v) for v in tokens[i + 10 : i + 12]]
    except (ValueError, IndexError):
        raise DvpmvsError(
            f"{path} is not an MVSNet camera file (extrinsic 4x4, intrinsic 3x3, depth range)"
        ) from None
    depth_min, interval = (rest + [0.0, 0.0])[:2]
    return E, K, depth_min, interval


def prepare_tanks(
    scene_dir: str | Path,
    out: str | Path,
    num_sources: int = 10,
    max_image_size: int = 1600,
    num_threads: int = -1,
) -> Path:
    """A COLMAP workspace for a Tanks and Temples scene in COLMAP or MVSNet layout.

    Returns the workspace folder (the scene's own folder if it already is a COLMAP workspace).
    """
    scene_dir, out = Path(scene_dir), Path(out)
    for candidate in (scene_dir, scene_dir / "dense"):
        if (candidate / "images").is_dir() and (candidate / "sparse").is_dir():
            if not (candidate / "stereo" / "patch-match.cfg").is_file():
                recon = pycolmap.Reconstruction(str(candidate / "sparse"))
                out.mkdir(parents=True, exist_ok=True)
                _check_pinhole(recon, candidate / "sparse")
                (out / "sparse").mkdir(exist_ok=True)
                recon.write(str(out / "sparse"))
                _link_images(candidate / "images", out)
                _write_configs(out, sorted(im.name for im in recon.images.values()), num_sources)
                return out
            return candidate
    cams = sorted((scene_dir / "cams").glob("*_cam.txt"))
    if not cams:
        raise DvpmvsError(
            f"{scene_dir}: neither a COLMAP layout (images/ + sparse/) nor an MVSNet layout "
            "(images/ + cams/*_cam.txt)"
        )
    images = {
        p.stem: p
        for p in (scene_dir / "images").iterdir()
        if p.suffix.lower() in (".jpg", ".jpeg", ".png")
    }
    cameras, names = {}, []
    for cam_path in cams:
        stem = cam_path.name.removesuffix("_cam.txt")
        if stem not in images:
            raise DvpmvsError(
                f"{cam_path.name} has no image {stem}.jpg/.png in {scene_dir / 'images'}"
            )
        E, K, _, _ = read_mvsnet_cam(cam_path)
        height, width = cv2.imread(str(images[stem]), cv2.IMREAD_GRAYSCALE).shape
        R = E[:3, :3]
        cameras[images[stem].name] = StrechaCamera(K, R.T, -R.T @ E[:3, 3], width, height)
        names.append(images[stem].name)
    # MVSNet cameras come without sparse points: triangulate them with the poses held fixed, as
    # for Strecha, so that depth ranges and view selection work as for any COLMAP workspace.
    import_with_known_poses(
        scene_dir / "images", cameras, out, max_image_size, num_threads, num_sources
    )
    # MVSNet's pair.txt is its view selection: use it as explicit source lists when present.
    pair = scene_dir / "pair.txt"
    if pair.is_file():
        _write_pair_configs(out, pair, names, num_sources)
    else:
        _write_configs(out, names, num_sources)
    return out


def _write_pair_configs(out: Path, pair: Path, names: list[str], num_sources: int) -> None:
    tokens = pair.read_text().split()
    count, pos, sources = int(tokens[0]), 1, {}
    for _ in range(count):
        ref, n = int(tokens[pos]), int(tokens[pos + 1])
        listed = [int(tokens[pos + 2 + 2 * k]) for k in range(n)]
        pos += 2 + 2 * n
        chosen = [names[s] for s in listed if 0 <= s < len(names)][:num_sources]
        if 0 <= ref < len(names) and chosen:
            sources[names[ref]] = ", ".join(chosen)
    write_stereo_configs(out / "stereo", sources, fusion_images=names)
