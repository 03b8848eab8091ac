"""From a folder of photos to a cloud and a mesh: COLMAP's structure from motion (pycolmap),
undistortion into a dense workspace, then dvpmvs's dense stage, fusion and meshing.

The project folder ``OUT`` holds what COLMAP's ``automatic_reconstructor`` would: ``database.db``
(features and matches), ``sparse/0`` (the largest model the mapper made), ``dense/`` (a COLMAP
dense workspace: ``images/``, ``sparse/``, ``stereo/``, then our maps, ``fused.ply`` with its
``.vis`` and ``meshed-<method>.ply``). Each stage records what made its output
(``OUT/stages/<stage>.provenance.json``: the photos' digests, the options, the upstream stage's
fingerprint, the code); a rerun skips every stage whose record matches and redoes the first that
does not and everything after it. The dense stage and meshing keep their own records (per view,
per cloud), so that changing a dense option recomputes maps, not the structure from motion.

Matching: ``exhaustive`` (every pair; what COLMAP recommends up to a few hundred photos),
``sequential`` (each photo with the next ``sequential_overlap``: video and walk-through
captures), ``spatial`` (pairs of nearby positions from the photos' GPS tags); ``auto`` takes
exhaustive up to ``exhaustive_max_images`` photos and sequential beyond.

Known intrinsics: ``camera_params`` in the order of ``camera_model``'s parameters (COLMAP's
``--ImageReader.camera_params``), held fixed by the bundle adjustment.

Masks (``mask=...``, given for the photos as they are in ``images``): made once per photo into
``OUT/masks/`` in COLMAP's layout (``<name>.png``, 0 masked), which feature extraction reads
(``ImageReader.mask_path``: no feature under a mask); undistorted with the photos into
``dense/masks/``, which the dense stage and fusion read, and which COLMAP's own
``stereo_fusion --StereoFusion.mask_path dense/masks`` reads the same way.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from dvpmvs.digests import file_digest
from dvpmvs.errors import DvpmvsError, Interrupted
from dvpmvs.options.sfm import MATCHING_METHODS, SfmOptions
from dvpmvs.provenance import CachedOutput, Status, library_versions
from dvpmvs.stage_progress import StepProgress, database_rows
from dvpmvs.validation import resolve_threads
from dvpmvs.writer_lock import writer_lock

__all__ = [
    "MATCHING_METHODS",
    "ReconstructionError",
    "ReconstructSummary",
    "SfmOptions",
    "StageReport",
    "print_reconstruct_summary",
    "reconstruct",
    "check_photos",
    "check_project_folders",
    "image_files",
    "photo_masks",
    "run_structure_from_motion",
    "undistort",
    "undistorted_workspace",
]

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".ppm", ".pgm")


class ReconstructionError(DvpmvsError, RuntimeError):
    """Structure from motion or undistortion cannot run or failed; the message says what to do."""


@dataclass
class StageReport:
    name: str
    reused: bool
    seconds: float
    summary: str = ""


@dataclass
class ReconstructSummary:
    """What :func:`dvpmvs.api.reconstruct` did: per stage whether it ran, its time and figures;
    the dense workspace, the cloud and the mesh."""

    stages: list[StageReport] = field(default_factory=list)
    workspace: Path | None = None
    cloud: Path | None = None
    mesh: Path | None = None
    dense: object | None = None  # the dense stage's DenseSummary


def image_files(folder: str | Path, recursive: bool = False) -> list[str]:
    """The photos in ``folder`` (with ``recursive``, also in its subfolders; COLMAP names them by
    their path relative to ``folder``), each checked to be complete (:func:`check_photos`)."""
    folder = Path(folder).expanduser()
    if not folder.is_dir():
        raise ReconstructionError(f"images={folder} is not a folder of photos")
    found = folder.rglob("*") if recursive else folder.iterdir()
    names = sorted(
        p.relative_to(folder).as_posix()
        for p in found
        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
    )
    if len(names) < 2:
        deeper = "" if recursive else "; photos in subfolders are read with recursive=true"
        raise ReconstructionError(
            f"{folder} holds {len(names)} photo(s) ({', '.join(IMAGE_SUFFIXES)}); structure "
            f"from motion needs at least 2 overlapping photos{deeper}"
        )
    check_photos(folder, names)
    return names


def check_photos(folder: Path, names: list[str]) -> None:
    """Every photo complete and in a format the readers know, before any stage runs: a truncated
    JPEG or PNG (cut off while copied) would otherwise be read with grey rows or not registered,
    and the cloud would silently lack its part. One error names every bad photo."""
    from dvpmvs.image import ImageReadError, check_image_file

    bad = []
    for name in names:
        path = folder / name
        try:
            check_image_file(path)
        except ImageReadError as exc:
            bad.append(str(exc))
    if bad:
        more = f" (and {len(bad) - 3} more)" if len(bad) > 3 else ""
        raise ReconstructionError(
            f"{len(bad)} of the {len(names)} photos cannot be used: {'; '.join(bad[:3])}{more} "
            f"(or move them out of {folder})"
        )


def check_project_folders(images: Path, out: Path) -> None:
    """The project folder must not lie inside the photos' folder (its undistorted copies would
    be read as photos by a later run), nor the photos inside the folder undistortion replaces."""
    photos, project = images.resolve(), out.resolve()
    if project == photos or photos in project.parents:
        beside = photos.parent / f"{photos.name}_project"
        raise ReconstructionError(
            f"out={out} {'is the folder' if project == photos else 'lies inside the folder'} images={images}: the "
            f"project's undistorted copies of the photos would be read as more photos by the next run. Give out= a "
            f"folder outside {images}, e.g. out={beside}"
        )
    dense = project / "dense"
    if photos == dense or dense in photos.parents:
        raise ReconstructionError(
            f"images={images} lies inside {dense}, which the undistortion stage replaces; "
            f"keep the photos outside it"
        )


# -- stages -------------------------------------------------------------------------------------


def _stage_record_path(out: Path, stage: str) -> Path:
    return out / "stages" / f"{stage}.provenance.json"


def _run_stage(
    out: Path,
    stage: str,
    inputs: dict,
    outputs: Callable[[], dict[str, Path]],
    run: Callable[[], str],
    reuse: bool,
    reports: list[StageReport],
) -> str:
    """Run ``stage`` unless its record matches ``inputs`` and its outputs are unchanged; returns
    the stage's fingerprint (the next stage's input). Once a stage has run, the stages after it
    run too (``reports`` tells them): their inputs may carry the same fingerprints while the
    files they read were made again."""
    cached = CachedOutput.check(_stage_record_path(out, stage), inputs, out)
    upstream_ran = any(not r.reused for r in reports)
    if reuse and not upstream_ran and cached.current is not None:
        log.info("%s: done by an earlier run with the same inputs: reused", stage)
        reports.append(
            StageReport(
                stage,
                True,
                float(cached.current.stats.get("seconds", 0.0)),
                str(cached.current.stats.get("summary", "")),
            )
        )
        return cached.fingerprint
    log.info("%s: computing (%s)", stage, _why_computed(cached.state, upstream_ran, reuse))
    start = time.perf_counter()
    try:
        with cached.making():
            summary = run()
    except Interrupted as stop:
        stop.progress = (
            stop.progress or f"in the {stage} stage, after {len(reports)} finished stage(s)"
        )
        raise
    seconds = time.perf_counter() - start
    log.info("%s: %s (%.1f s)", stage, summary, seconds)
    cached.complete(outputs(), {"seconds": seconds, "summary": summary})
    reports.append(StageReport(stage, False, seconds, summary))
    return cached.fingerprint


def _remove_database(database: Path) -> None:
    for suffix in ("", "-wal", "-shm", "-journal"):
        Path(str(database) + suffix).unlink(missing_ok=True)


@dataclass
class _Photo:
    """A photo as a mask provider sees a view (:class:`dvpmvs.masks.MaskView`), at its own size."""

    name: str
    path: Path
    height: int
    width: int

    def load_rgb(self):
        from dvpmvs.image import read_image

        return read_image(self.path)


# The masks undistorted with the photos: ``masks/`` of the undistorted workspace, COLMAP's layout.
UNDISTORTED_MASKS = {
    "name": "files",
    "path": "masks",
    "layout": "colmap",
    "ignore_label": 0,
    "allow_missing": False,
}


def photo_masks(
    images: Path, names: list[str], mask: dict, out: Path, reuse: bool, reports: list[StageReport]
) -> tuple[Path, str]:
    """The mask config ``mask`` made, for every photo, into ``out/masks/<name>.png`` (COLMAP's
    layout: 0 masked, 255 kept; the photo's size); returns the folder and the stage's fingerprint.
    Every mask is checked (missing, unreadable, another aspect ratio) before any is written."""
    import cv2

    from dvpmvs.image import check_image_file
    from dvpmvs.maps import atomic_path
    from dvpmvs.masks import ViewMasks

    masks = ViewMasks.from_config(mask)
    folder = out / "masks"
    photos = []
    for name in names:
        width, height = check_image_file(images / name)
        photos.append(_Photo(name, images / name, height, width))
    masks.check(photos)

    def run() -> str:
        kept = []
        for photo in photos:
            keep = masks.mask(photo)
            target = folder / f"{photo.name}.png"
            target.parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(target, suffix=".tmp.png") as tmp:
                if not cv2.imwrite(str(tmp), keep.astype("uint8") * 255):
                    raise ReconstructionError(f"cannot write the mask {target}")
            kept.append(keep.mean())
        return f"{len(photos)} masks, {100 * (1 - sum(kept) / max(len(kept), 1)):.1f} % of pixels masked"

    inputs = {
        "mask": mask,
        "photos": {p.name: masks.provenance(p.name) for p in photos},
        "pixels": {p.name: file_digest(p.path) for p in photos},
    }
    outputs = lambda: {f"{p.name}.png": folder / f"{p.name}.png" for p in photos}  # noqa: E731
    return folder, _run_stage(out, "masks", inputs, outputs, run, reuse, reports)


# Why a stage is computed, by the state of its stored outputs.
_STATE_REASONS = {
    Status.MISSING: "not computed yet",
    Status.INTERRUPTED: "an earlier run stopped during it",
    Status.STALE: "its inputs changed since it was computed",
    Status.MODIFIED: "its outputs were changed since it was computed",
    Status.FOREIGN: "its outputs are not dvpmvs's",
}


def _why_computed(state: Status, upstream_ran: bool, reuse: bool) -> str:
    if upstream_ran:
        return "the stage before it was computed again"
    if state.reusable and not reuse:
        return "overwrite=true"
    return _STATE_REASONS.get(state, state.value)


def run_structure_from_motion(
    images: Path,
    out: Path,
    options: SfmOptions,
    reuse: bool,
    reports: list[StageReport],
    recursive: bool = False,
    masks: tuple[Path, str] | None = None,
    progress: bool = False,
) -> tuple[Path, str, dict[str, str]]:
    """Features, matching and incremental mapping of the photos in ``images`` (``recursive``:
    and its subfolders) into ``out/database.db`` and ``out/sparse/0``; returns the model folder,
    the mapping stage's fingerprint and the photos' digests (name -> SHA-256). ``masks``: the
    folder of the photos' masks in COLMAP's layout and its stage's fingerprint (no feature is
    extracted under a mask). ``progress``: bars for the stages (else a log line every few
    seconds, :mod:`dvpmvs.stage_progress`)."""
    import pycolmap

    names = image_files(images, recursive)
    database = out / "database.db"
    threads = resolve_threads(options.num_threads)
    code = {"pycolmap": library_versions(["pycolmap"])["pycolmap"]}
    photos = {name: file_digest(images / name) for name in names}

    def extract() -> str:
        _remove_database(database)  # extraction skips photos already in a database
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = options.camera_model
        reader.camera_params = options.camera_params
        if masks is not None:
            reader.mask_path = str(masks[0])
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.max_image_size = options.feature_max_image_size
        # SIFT extraction on several threads numbers features differently from run to run,
        # and the model with them: one thread unless reproducibility is given up.
        extraction.num_threads = 1 if options.reproducible else threads
        extraction.sift.max_num_features = options.max_num_features
        mode = pycolmap.CameraMode.SINGLE if options.single_camera else pycolmap.CameraMode.AUTO
        watch = StepProgress(
            "features", "photos", len(names), database_rows(database, "keypoints"), progress
        )
        try:
            with watch:
                pycolmap.extract_features(
                    database,
                    images,
                    image_names=names,
                    camera_mode=mode,
                    reader_options=reader,
                    extraction_options=extraction,
                    device=pycolmap.Device.cpu,
                )
        except (RuntimeError, ValueError) as exc:
            raise ReconstructionError(f"feature extraction failed on {images}: {exc}") from None
        with pycolmap.Database.open(database) as db:
            return f"{db.num_images()} photos, {db.num_keypoints() / max(db.num_images(), 1):,.0f} features each"

    feature_options = {
        k: getattr(options, k)
        for k in (
            "camera_model",
            "single_camera",
            "camera_params",
            "max_num_features",
            "feature_max_image_size",
            "reproducible",
        )
    }
    features = _run_stage(
        out,
        "features",
        {
            "photos": photos,
            "options": feature_options,
            "code": code,
            "masks": None if masks is None else masks[1],
        },
        lambda: {},
        extract,
        reuse and database.is_file(),
        reports,
    )

    matcher = options.matcher(len(names))

    def match() -> str:
        with pycolmap.Database.open(database) as db:
            db.clear_matches()
            db.clear_two_view_geometries()
        matching = pycolmap.FeatureMatchingOptions()
        # Each verification thread draws RANSAC samples from its own seeded generator for
        # whichever pairs it is handed, so the inliers depend on the scheduling: one thread.
        matching.num_threads = 1 if options.reproducible else threads
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.random_seed = (
            options.seed
        )  # -1, COLMAP's default, draws a new seed each run
        watch = StepProgress(
            "matching",
            "pairs",
            _pairs(matcher, len(names), options.sequential_overlap),
            database_rows(database, "two_view_geometries"),
            progress,
        )
        try:
            with watch:
                _match(pycolmap, matcher, database, matching, verification, options)
        except (RuntimeError, ValueError) as exc:
            raise ReconstructionError(f"{matcher} matching failed: {exc}") from None
        with pycolmap.Database.open(database) as db:
            return f"{matcher}: {db.num_verified_image_pairs()} verified pairs of {db.num_matched_image_pairs()}"

    matches = _run_stage(
        out,
        "matching",
        {
            "features": features,
            "matcher": matcher,
            "seed": options.seed,
            "reproducible": options.reproducible,
            "sequential_overlap": options.sequential_overlap,
            "code": code,
        },
        lambda: {},
        match,
        reuse and database.is_file(),
        reports,
    )

    model_dir = out / "sparse" / "0"

    def mapping() -> str:
        mapper = pycolmap.IncrementalPipelineOptions()
        mapper.random_seed = options.seed
        mapper.num_threads = 1 if options.reproducible else threads
        mapper.min_num_matches = options.min_num_matches
        if options.reproducible:
            # Bundle adjustment on several threads sums residuals in another order each run.
            mapper.ba_min_num_residuals_for_cpu_multi_threading = 2**31 - 1
        if options.camera_params:
            mapper.ba_refine_focal_length = False
            mapper.ba_refine_principal_point = False
            mapper.ba_refine_extra_params = False
        scratch = out / ".sparse.partial"
        shutil.rmtree(scratch, ignore_errors=True)
        scratch.mkdir(parents=True)
        # The mapper calls back for each photo it tries to register next (some more than once,
        # some in vain): a count without a total.
        watch = StepProgress("mapping", "photos tried", progress=progress)
        try:
            with watch:
                models = pycolmap.incremental_mapping(
                    database, images, scratch, mapper, next_image_callback=watch.advance
                )
        except (RuntimeError, ValueError) as exc:
            raise ReconstructionError(f"incremental mapping failed: {exc}") from None
        finally:
            # The mapper's own folder; the model kept is written to sparse/0 from memory below.
            shutil.rmtree(scratch, ignore_errors=True)
        if not models:
            raise ReconstructionError(
                f"the mapper registered no pair of the {len(names)} photos: too little overlap or texture, or too "
                f"few matches (sfm.min_num_matches={options.min_num_matches}); more overlapping photos, "
                f"sfm.matching=exhaustive, or known intrinsics (sfm.camera_params) help"
            )
        best = max(models.values(), key=lambda m: (m.num_reg_images(), m.num_points3D()))
        if model_dir.exists():
            shutil.rmtree(model_dir)
        model_dir.mkdir(parents=True)
        best.write(model_dir)
        others = f"; {len(models) - 1} smaller model(s) left out" if len(models) > 1 else ""
        return (
            f"{best.num_reg_images()} of {len(names)} photos registered, {best.num_points3D():,} points, "
            f"reprojection error {best.compute_mean_reprojection_error():.2f} px{others}"
        )

    mapper_options = {
        "seed": options.seed,
        "min_num_matches": options.min_num_matches,
        "fixed_intrinsics": bool(options.camera_params),
        "reproducible": options.reproducible,
    }
    # The mapper writes to the database too: it is stamped with the model, after mapping.
    mapped = _run_stage(
        out,
        "mapping",
        {"matching": matches, "options": mapper_options, "code": code},
        lambda: {"database": database, **_model_files(model_dir)},
        mapping,
        reuse,
        reports,
    )
    return model_dir, mapped, photos


def _match(pycolmap, matcher: str, database: Path, matching, verification, options) -> None:
    """COLMAP's matcher of that name (exhaustive, sequential, spatial) on the database."""
    if matcher == "exhaustive":
        pycolmap.match_exhaustive(
            database,
            matching_options=matching,
            verification_options=verification,
            device=pycolmap.Device.cpu,
        )
    elif matcher == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = options.sequential_overlap
        pycolmap.match_sequential(
            database,
            matching_options=matching,
            pairing_options=pairing,
            verification_options=verification,
            device=pycolmap.Device.cpu,
        )
    else:
        pycolmap.match_spatial(
            database,
            matching_options=matching,
            verification_options=verification,
            device=pycolmap.Device.cpu,
        )


def _pairs(matcher: str, photos: int, overlap: int) -> int | None:
    """The image pairs ``matcher`` matches (None where it depends on the photos' positions)."""
    if matcher == "exhaustive":
        return photos * (photos - 1) // 2
    if matcher == "sequential":
        return sum(min(overlap, photos - 1 - i) for i in range(photos))
    return None


def _model_files(model_dir: Path) -> dict[str, Path]:
    return {p.name: p for p in sorted(model_dir.glob("*.bin")) + sorted(model_dir.glob("*.txt"))}


def _undistort_masks(masks: Path, model_dir: Path, options, target: Path) -> None:
    """Each photo's mask (COLMAP's layout) undistorted as its photo is, into ``target``: the
    masks of the dense workspace's images, pixel for pixel."""
    import cv2
    import numpy as np
    import pycolmap

    model = pycolmap.Reconstruction(str(model_dir))
    for image in model.images.values():
        keep = cv2.imread(str(masks / f"{image.name}.png"), cv2.IMREAD_GRAYSCALE)
        if keep is None:
            raise ReconstructionError(f"the mask {masks / (image.name + '.png')} cannot be read")
        camera = model.cameras[image.camera_id]
        bitmap, _ = pycolmap.undistort_image(options, pycolmap.Bitmap.from_array(keep), camera)
        values = np.asarray(bitmap.to_array())
        values = values[..., 0] if values.ndim == 3 else values
        # Interpolated across a mask's edge: a pixel is kept when it is mostly kept.
        path = target / f"{image.name}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        if not cv2.imwrite(str(path), np.where(values >= 128, 255, 0).astype(np.uint8)):
            raise ReconstructionError(f"cannot write the mask {path}")


def undistort(
    images: Path,
    model_dir: Path,
    dense: Path,
    max_image_size: int,
    upstream: str,
    reuse: bool,
    reports: list[StageReport],
    out: Path,
    photos: dict[str, str] | None = None,
    masks: tuple[Path, str] | None = None,
) -> Path:
    """The photos undistorted into the COLMAP dense workspace ``dense`` (pinhole cameras, at
    most ``max_image_size`` pixels long; -1 keeps the size), as ``colmap image_undistorter``.
    ``photos``: digests the caller has already computed (the others are computed here).
    ``masks``: the photos' masks in COLMAP's layout (and their stage's fingerprint), undistorted
    with them into ``dense/masks``."""
    import pycolmap

    model = pycolmap.Reconstruction(str(model_dir))
    names = sorted(image.name for image in model.images.values())
    if photos is None:
        check_photos(images, names)

    def run() -> str:
        scratch = dense.with_name(dense.name + ".partial")
        shutil.rmtree(scratch, ignore_errors=True)
        options = pycolmap.UndistortCameraOptions()
        options.max_image_size = max_image_size
        try:
            pycolmap.undistort_images(
                scratch, model_dir, images, output_type="COLMAP", undistort_options=options
            )
            if masks is not None:
                _undistort_masks(masks[0], model_dir, options, scratch / "masks")
        except BaseException as exc:  # failed or stopped: nothing of it is kept
            shutil.rmtree(scratch, ignore_errors=True)
            if isinstance(exc, (RuntimeError, ValueError)):
                raise ReconstructionError(f"undistortion of {model_dir} failed: {exc}") from None
            raise
        # The maps of another undistortion would not fit these images: the workspace is replaced.
        if dense.exists():
            shutil.rmtree(dense)
        os.replace(scratch, dense)
        size = max(
            max(c.width, c.height)
            for c in pycolmap.Reconstruction(str(dense / "sparse")).cameras.values()
        )
        return f"{len(names)} photos, longest side {size} px"

    inputs = {
        "model": {name: file_digest(path) for name, path in _model_files(model_dir).items()},
        "photos": {name: (photos or {}).get(name) or file_digest(images / name) for name in names},
        "upstream": upstream,
        "max_image_size": max_image_size,
        "code": {"pycolmap": library_versions(["pycolmap"])["pycolmap"]},
        "masks": None if masks is None else masks[1],
    }
    _run_stage(
        out,
        "undistortion",
        inputs,
        lambda: _model_files(dense / "sparse"),
        run,
        reuse and (dense / "images").is_dir(),
        reports,
    )
    return dense


def undistorted_workspace(
    root: str | Path, target: str | Path | None = None, mask: dict | None = None
) -> tuple[Path, dict | None]:
    """A COLMAP project (``images/`` and a sparse model in ``sparse/`` or ``sparse/0``) whose
    cameras are not all pinhole, undistorted into ``target`` (default ``ROOT/dense``, COLMAP's
    layout) as ``colmap image_undistorter`` would, once: a rerun with the same model and images
    reuses it. A project whose cameras are all pinhole is returned as it is. ``mask``: a mask
    config for the project's photos (a relative ``path`` is the project's), made for every photo
    and undistorted with them into ``target/masks``. Returns the workspace and the mask config
    its views take (the undistorted masks; ``mask`` itself where nothing was undistorted)."""
    import pycolmap

    from dvpmvs.workspace import UNDISTORTED_MODELS, _find_model_dir

    root = Path(root).expanduser()
    model_dir = _find_model_dir(root / "sparse")
    cameras = pycolmap.Reconstruction(str(model_dir)).cameras.values()
    if all(camera.model.name in UNDISTORTED_MODELS for camera in cameras):
        return root, mask
    target = root / "dense" if target is None else Path(target).expanduser()
    if target.resolve() == root.resolve():
        raise ReconstructionError(
            f"undistort=true writes a new workspace: give out=DIR other than the workspace "
            f"{root} (default {root / 'dense'})"
        )
    reports: list[StageReport] = []
    masks = None
    if mask is not None:
        # The user's masks are of the distorted photos: made for each, then undistorted with it.
        mask = dict(mask)
        if mask.get("path") and not Path(str(mask["path"])).expanduser().is_absolute():
            mask["path"] = str(root / str(mask["path"]))
        names = [v.name for v in pycolmap.Reconstruction(str(model_dir)).images.values()]
        masks = photo_masks(
            root / "images", sorted(names), mask, target / "distorted", True, reports
        )
    undistort(
        root / "images", model_dir, target, -1, "given model", True, reports, target, masks=masks
    )
    return target, None if masks is None else dict(UNDISTORTED_MASKS)


# -- the whole chain -----------------------------------------------------------------------------


def reconstruct(
    images: str | Path,
    out: str | Path,
    sfm: SfmOptions | None = None,
    workspace_options=None,
    dense_options=None,
    meshing_options=None,
    sparse: str | Path | None = None,
    max_image_size: int = 2000,
    progress: bool = True,
    overwrite: bool = False,
    recursive: bool = False,
) -> ReconstructSummary:
    """Photos in ``images`` (``recursive``: and its subfolders; the project folder ``out`` may not
    lie inside it) -> ``out/database.db``, ``out/sparse/0`` (or the given ``sparse``
    model), ``out/dense`` (undistorted, at most ``max_image_size`` pixels long), its maps, cloud
    ``out/dense/fused.ply`` and, unless ``meshing_options`` is None, mesh
    ``out/dense/meshed-<method>.ply``. Finished stages are reused (module doc); ``overwrite``
    redoes every stage. The run holds ``out``'s writer lock (:mod:`dvpmvs.writer_lock`)."""
    images = Path(images).expanduser()
    out = Path(out).expanduser()
    if not images.is_dir():
        raise ReconstructionError(f"images={images} is not a folder of photos")
    check_project_folders(images, out)
    out.mkdir(parents=True, exist_ok=True)
    # One reconstruct at a time per project folder (the database and the model are shared).
    with writer_lock(out):
        return _reconstruct_locked(
            images,
            out,
            sfm or SfmOptions(),
            workspace_options,
            dense_options,
            meshing_options,
            sparse,
            max_image_size,
            progress,
            overwrite,
            recursive,
        )


def _reconstruct_locked(
    images: Path,
    out: Path,
    sfm: SfmOptions,
    workspace_options,
    dense_options,
    meshing_options,
    sparse,
    max_image_size: int,
    progress: bool,
    overwrite: bool,
    recursive: bool,
) -> ReconstructSummary:
    from dataclasses import replace

    from dvpmvs.dense import DenseOptions, run_dense
    from dvpmvs.meshing import default_mesh_path, mesh_cloud
    from dvpmvs.workspace import Workspace, WorkspaceOptions

    reports: list[StageReport] = []
    dense_options = dense_options or DenseOptions()
    masks = None
    if dense_options.mask is not None:
        # The user's masks are the photos'; the dense stage reads them undistorted (dense/masks).
        masks = photo_masks(
            images, image_files(images, recursive), dense_options.mask, out, not overwrite, reports
        )
        undistorted = dict(UNDISTORTED_MASKS)
        dense_options = replace(
            dense_options, mask=undistorted, fusion=replace(dense_options.fusion, mask=undistorted)
        )
    if sparse is None:
        model_dir, upstream, photos = run_structure_from_motion(
            images, out, sfm, not overwrite, reports, recursive, masks, progress
        )
    else:
        photos = None
        model_dir = Path(sparse).expanduser()
        if not model_dir.is_dir():
            raise ReconstructionError(f"sparse={model_dir} is not a folder holding a COLMAP model")
        upstream = "given model"
    dense_dir = undistort(
        images,
        model_dir,
        out / "dense",
        max_image_size,
        upstream,
        not overwrite,
        reports,
        out,
        photos,
        masks,
    )

    workspace_options = workspace_options or WorkspaceOptions()
    workspace = Workspace.open(dense_dir, replace(workspace_options, max_image_size=-1))
    if overwrite:
        dense_options = replace(dense_options, overwrite=True)
    start = time.perf_counter()
    dense = run_dense(workspace, dense_options, progress=progress)
    computed = sum(1 for r in dense.reports if not r.skipped)
    reports.append(
        StageReport(
            "dense",
            computed == 0 and (dense.output is None or dense.fusion_reused),
            time.perf_counter() - start,
            f"{computed} of {len(dense.reports)} maps computed, "
            f"{dense.num_points or 0:,} fused points",
        )
    )
    summary = ReconstructSummary(reports, dense_dir, dense.output, None, dense)
    if meshing_options is not None and dense.output is not None:
        output = default_mesh_path(dense_dir, meshing_options.method)
        with StepProgress("meshing", "", progress=progress):
            mesh = mesh_cloud(
                dense.output,
                output,
                meshing_options,
                model_dir=workspace.model_dir,
                reuse=not overwrite,
            )
        reports.append(
            StageReport(
                "mesh",
                mesh.reused,
                mesh.seconds,
                f"{mesh.vertices:,} vertices, {mesh.triangles:,} triangles",
            )
        )
        summary.mesh = mesh.output
    return summary


def print_reconstruct_summary(summary: ReconstructSummary, console=None) -> None:
    """The closing table: per stage whether it ran, its time and what it made."""
    from rich.console import Console
    from rich.table import Table

    console = console or Console(stderr=True)
    table = Table(title="dvpmvs reconstruct", title_justify="left")
    for column, justify in (("stage", "left"), ("", "left"), ("s", "right"), ("result", "left")):
        table.add_column(column, justify=justify)
    for report in summary.stages:
        table.add_row(
            report.name,
            "reused" if report.reused else "ran",
            f"{report.seconds:.1f}",
            report.summary,
        )
    console.print(table)
    console.print(
        f"workspace: {summary.workspace}\ncloud: {summary.cloud}"
        + (f"\nmesh: {summary.mesh}" if summary.mesh else "")
    )
