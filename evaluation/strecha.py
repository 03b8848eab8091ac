"""Import a Strecha scene (``images/`` + ``*.camera`` ground-truth cameras) as a COLMAP workspace.

A Strecha ``.camera`` file holds K (3 rows), the radial distortion (0 0 0), R (3 rows, camera to
world), the camera centre C and the image size; a world point X projects as
``x ~ K R^T (X - C)``, so COLMAP's world-to-camera pose is ``R^T, -R^T C``.

The sparse model comes from COLMAP itself (through pycolmap): SIFT features (extracted on images
downscaled to ``max_image_size``; COLMAP scales the keypoints back to full resolution), exhaustive
matching with geometric verification, and triangulation with the ground-truth poses and
intrinsics held fixed. The poses and the full-resolution images are kept exactly.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pycolmap

from dvpmvs.errors import DvpmvsError
from dvpmvs.maps import atomic_path
from dvpmvs.workspace import write_stereo_configs

__all__ = [
    "StrechaCamera",
    "read_strecha_camera",
    "write_strecha_camera",
    "import_strecha",
    "import_with_known_poses",
]


class StrechaCamera:
    def __init__(
        self, K: np.ndarray, R_cam_to_world: np.ndarray, center: np.ndarray, width: int, height: int
    ):
        self.K, self.width, self.height = K, width, height
        self.R = R_cam_to_world.T  # world -> camera (COLMAP)
        self.t = -self.R @ center
        self.center = center


def read_strecha_camera(path: str | Path) -> StrechaCamera:
    path = Path(path)
    try:
        values = [float(v) for v in path.read_text().split()]
    except (OSError, ValueError) as exc:
        raise DvpmvsError(f"cannot read the Strecha camera {path}: {exc}") from None
    if len(values) != 26:
        raise DvpmvsError(
            f"{path}: a Strecha camera file has 26 numbers (K, distortion, R, C, size); "
            f"found {len(values)}"
        )
    K = np.array(values[0:9]).reshape(3, 3)
    distortion = np.array(values[9:12])
    if np.any(distortion != 0):
        raise DvpmvsError(
            f"{path}: the camera has lens distortion {distortion.tolist()}; undistort the "
            "images first (the workspace needs PINHOLE cameras)"
        )
    R = np.array(values[12:21]).reshape(3, 3)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4):
        raise DvpmvsError(f"{path}: the rotation is not orthonormal")
    return StrechaCamera(K, R, np.array(values[21:24]), int(values[24]), int(values[25]))


def write_strecha_camera(
    path: str | Path,
    K: np.ndarray,
    R_world_to_cam: np.ndarray,
    t: np.ndarray,
    width: int,
    height: int,
) -> None:
    """Write a camera in Strecha's format from a COLMAP-convention pose."""
    R_c2w = np.asarray(R_world_to_cam).T
    center = -R_c2w @ np.asarray(t)
    rows = [*np.asarray(K).reshape(3, 3), np.zeros(3), *R_c2w, center]
    text = (
        "".join(" ".join(f"{v:.17g}" for v in row) + "\n" for row in rows) + f"{width} {height}\n"
    )
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def _find_camera_files(scene: Path) -> dict[str, Path]:
    for folder in (scene / "gt_dense_cameras", scene / "cameras", scene / "images", scene):
        files = sorted(folder.glob("*.camera")) if folder.is_dir() else []
        if files:
            return {f.name.removesuffix(".camera"): f for f in files}
    raise DvpmvsError(
        f"no *.camera files under {scene} (looked in gt_dense_cameras/, cameras/, images/)"
    )


def import_strecha(
    scene: str | Path,
    out: str | Path,
    max_image_size: int = 1600,
    num_threads: int = -1,
    num_sources: int = 10,
    progress=None,
) -> dict:
    """Build a COLMAP dense workspace in ``out`` from a Strecha scene; returns statistics.

    ``progress``, if given, is called with a description of each stage.
    """
    scene, out = Path(scene), Path(out)
    images_dir = scene / "images"
    if not images_dir.is_dir():
        raise DvpmvsError(f"{scene} has no images/ folder")
    cameras = {name: read_strecha_camera(path) for name, path in _find_camera_files(scene).items()}
    missing = [n for n in cameras if not (images_dir / n).is_file()]
    if missing:
        raise DvpmvsError(
            f"images listed by camera files are missing from {images_dir}: {', '.join(missing)}"
        )

    return import_with_known_poses(
        images_dir, cameras, out, max_image_size, num_threads, num_sources, progress
    )


def import_with_known_poses(
    images_dir: Path,
    cameras: dict,
    out: Path,
    max_image_size: int = 1600,
    num_threads: int = -1,
    num_sources: int = 10,
    progress=None,
) -> dict:
    """Copy the images into ``out/images`` and triangulate a sparse model with fixed poses.

    ``cameras`` maps image names to objects with ``K``, ``R``, ``t`` (world to camera),
    ``width`` and ``height`` (a ``StrechaCamera``).
    """
    names = sorted(cameras)
    Ks = {tuple(np.round(c.K.ravel(), 6)) for c in cameras.values()}
    sizes = {(c.width, c.height) for c in cameras.values()}
    images_dir, out = Path(images_dir), Path(out)
    out.mkdir(parents=True, exist_ok=True)
    ws_images = out / "images"
    ws_images.mkdir(exist_ok=True)
    for n in names:
        target = ws_images / n
        if not target.exists() or target.stat().st_size != (images_dir / n).stat().st_size:
            with atomic_path(target) as tmp:
                shutil.copyfile(images_dir / n, tmp)
    # COLMAP's own log lines show as the command's verbose= says (dvpmvs.config.configure_output).
    return _import(
        names,
        cameras,
        images_dir,
        out,
        max_image_size,
        num_threads,
        num_sources,
        Ks,
        sizes,
        progress,
    )


def _import(
    names, cameras, images_dir, out, max_image_size, num_threads, num_sources, Ks, sizes, progress
):
    work = out / "sparse_import"
    if work.exists():
        shutil.rmtree(work)  # a previous, interrupted import: start the database afresh
    work.mkdir()
    database = work / "database.db"

    if progress:
        progress("feature extraction")
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    # One camera per image: Strecha intrinsics may differ slightly between images.
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size = int(max_image_size)
    extraction.num_threads = int(num_threads)
    extraction.use_gpu = False
    for n in names:
        K = cameras[n].K
        reader.camera_params = f"{K[0, 0]},{K[1, 1]},{K[0, 2]},{K[1, 2]}"
        pycolmap.extract_features(
            database,
            images_dir,
            image_names=[n],
            camera_mode=pycolmap.CameraMode.PER_IMAGE,
            reader_options=reader,
            extraction_options=extraction,
            device=pycolmap.Device.cpu,
        )
    if progress:
        progress("exhaustive matching")
    matching = pycolmap.FeatureMatchingOptions()
    # One thread and a fixed RANSAC seed (as SfmOptions.reproducible): each verification thread
    # draws its samples from its own generator for whichever pairs it is handed, and COLMAP's
    # default seed (-1) is new each run, so the same scene gave other points and, through the
    # RGB-D import's calibration, another focal length and ground truth.
    matching.num_threads = 1
    matching.use_gpu = False
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = 0
    pycolmap.match_exhaustive(
        database,
        matching_options=matching,
        verification_options=verification,
        device=pycolmap.Device.cpu,
    )

    if progress:
        progress("triangulation with the ground-truth poses")
    # extract_features numbers images and cameras itself: build the posed model on its ids.
    db = pycolmap.Database.open(str(database))
    try:
        db_images = {im.name: im for im in db.read_all_images()}
        db_cameras = {cam.camera_id: cam for cam in db.read_all_cameras()}
    finally:
        db.close()
    recon = pycolmap.Reconstruction()
    for n in names:
        im = db_images[n]
        cam = db_cameras[im.camera_id]
        K, c = cameras[n].K, cameras[n]
        if (cam.width, cam.height) != (c.width, c.height):
            raise DvpmvsError(
                f"{n} is {cam.width}x{cam.height} but its camera file says {c.width}x{c.height}"
            )
        camera = pycolmap.Camera(
            model="PINHOLE",
            width=c.width,
            height=c.height,
            params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]],
            camera_id=im.camera_id,
        )
        recon.add_camera_with_trivial_rig(camera)
        image = pycolmap.Image(name=n, camera_id=im.camera_id, image_id=im.image_id)
        recon.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(c.R), c.t))
    triangulated_dir = work / "triangulated"
    triangulated_dir.mkdir()
    triangulation = pycolmap.IncrementalPipelineOptions()
    triangulation.num_threads = 1
    triangulation.random_seed = 0
    # Bundle adjustment on several threads sums the residuals in another order each run.
    triangulation.ba_min_num_residuals_for_cpu_multi_threading = 2**31 - 1
    recon = pycolmap.triangulate_points(
        recon, database, images_dir, triangulated_dir, options=triangulation
    )

    sparse = out / "sparse"
    sparse.mkdir(exist_ok=True)
    recon.write(str(sparse))
    n_src = min(num_sources, len(names) - 1)
    write_stereo_configs(out / "stereo", {n: f"__auto__, {n_src}" for n in names})

    errors = [p.error for p in recon.points3D.values()]
    pose_error = max(
        float(
            np.abs(
                recon.images[db_images[n].image_id].cam_from_world().matrix()
                - np.hstack([cameras[n].R, cameras[n].t[:, None]])
            ).max()
        )
        for n in names
    )
    return {
        "images": len(names),
        "distinct_intrinsics": len(Ks),
        "image_sizes": sorted(sizes),
        "points3D": recon.num_points3D(),
        "observations": int(sum(p.track.length() for p in recon.points3D.values())),
        "mean_reprojection_error_px": float(np.mean(errors)) if errors else float("nan"),
        "max_pose_deviation": pose_error,
    }
