"""A COLMAP dense workspace (as written by ``colmap image_undistorter``), read through pycolmap.

Layout::

    WS/images/            undistorted images, named as in the sparse model
    WS/sparse/            the model (binary or text; ``sparse/0/`` is accepted too)
    WS/stereo/            patch-match.cfg, fusion.cfg, and the maps dvpmvs writes

Conventions (those of COLMAP's dense stage, so that COLMAP's fusion reads our maps unchanged):
``K``, ``R``, ``t`` map a world point X to the pixel ``K (R X + t)``; the pixel at array index
``[row, col]`` is the image point ``(x, y) = (col, row)``; depth is z in the camera frame.
"""

from __future__ import annotations

import logging
import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Protocol

import numpy as np
import pycolmap

from dvpmvs import registry
from dvpmvs.errors import DvpmvsError
from dvpmvs.image import ImageReadError, check_image_file
from dvpmvs.maps import atomic_path
from dvpmvs.model import NoDepthRangeError, SparseModel
from dvpmvs.options.workspace import WorkspaceOptions
from dvpmvs.view import View

__all__ = [
    "WorkspaceError",
    "WorkspaceOptions",
    "View",
    "SourceSpec",
    "Workspace",
    "ViewSelector",
    "parse_patch_match_cfg",
    "UNDISTORTED_MODELS",
]

log = logging.getLogger(__name__)

UNDISTORTED_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")

_UNDISTORT_HINT = (
    "dvpmvs needs an undistorted workspace: run `colmap image_undistorter --image_path <images> "
    "--input_path <sparse model> --output_path <workspace>` (or pycolmap.undistort_images) and "
    "point dvpmvs at its output, or give undistort=true to `dvpmvs dense`, which does this into WS/dense "
    "(or out=DIR)"
)


class ViewSelector(Protocol):
    """A ``view_selector`` plugin (entry-point group ``dvpmvs.view_selectors``): ranks the source
    views of a reference view, for ``__auto__, N`` in ``stereo/patch-match.cfg``.

    Parameters
    ----------
    workspace : Workspace
        The workspace; ``workspace.covisibility`` gives, per pair of images, the triangulation
        angles (degrees) of the sparse points they share.
    reference : str
        The reference view's image name.
    max_sources : int
        How many sources to return at most.

    Returns
    -------
    list of (str, float)
        ``(source_name, score)`` pairs, best first.
    """

    def __call__(
        self, workspace: Workspace, reference: str, max_sources: int
    ) -> list[tuple[str, float]]: ...


class WorkspaceError(DvpmvsError, ValueError):
    """The workspace on disk is incomplete or inconsistent; the message names the file and the fix."""


@dataclass(frozen=True)
class SourceSpec:
    """One entry of ``patch-match.cfg``: explicit source names, ``__auto__, N`` or ``__all__``."""

    reference: str
    sources: tuple[str, ...] = ()
    auto: int | None = None
    all: bool = False
    line: int = 0  # line of the source spec in the file (0: not from a file)
    reference_line: int = 0


def parse_patch_match_cfg(path: str | Path) -> list[SourceSpec]:
    """Parse COLMAP's ``stereo/patch-match.cfg``: pairs of lines (reference name, source spec).

    Blank lines and lines starting with ``#`` are ignored. A spec is ``__auto__, N``, ``__all__``
    or a comma-separated list of image names.
    """
    path = Path(path)
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise WorkspaceError(
            f"{path}:{line}: not UTF-8 text (byte 0x{raw[exc.start]:02x}); COLMAP reads image "
            f"names as UTF-8: save the file in that encoding"
        ) from None
    lines = [
        (number, text.strip())
        for number, text in enumerate(text.splitlines(), start=1)
        if text.strip() and not text.strip().startswith("#")
    ]
    if len(lines) % 2:
        number, text = lines[-1]
        raise WorkspaceError(
            f"{path}:{number}: reference image {text!r} has no line of source images after it; "
            f"each reference needs a second line with `__auto__, N`, `__all__` or source names"
        )
    specs = []
    for (ref_line, reference), (src_line, spec) in zip(lines[0::2], lines[1::2]):
        items = [item.strip() for item in spec.split(",") if item.strip()]
        lines_of = {"line": src_line, "reference_line": ref_line}
        if items and items[0] == "__auto__":
            if len(items) != 2 or not items[1].isdigit() or int(items[1]) < 1:
                raise WorkspaceError(
                    f"{path}:{src_line}: expected `__auto__, N` with N >= 1, got {spec!r}"
                )
            specs.append(SourceSpec(reference, auto=int(items[1]), **lines_of))
        elif items == ["__all__"]:
            specs.append(SourceSpec(reference, all=True, **lines_of))
        elif items:
            specs.append(SourceSpec(reference, sources=tuple(items), **lines_of))
        else:
            raise WorkspaceError(
                f"{path}:{src_line}: empty source list for reference image {reference!r}"
            )
    return specs


def parse_fusion_cfg(path: str | Path) -> list[tuple[int, str]]:
    """COLMAP's ``stereo/fusion.cfg``: the images to fuse, one name per line, as ``(line number,
    name)``; blank lines are skipped and surrounding spaces trimmed, as COLMAP reads it."""
    path = Path(path)
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise WorkspaceError(
            f"{path}:{line}: not UTF-8 text (byte 0x{raw[exc.start]:02x}); COLMAP reads image "
            f"names as UTF-8: save the file in that encoding"
        ) from None
    return [
        (number, line.strip())
        for number, line in enumerate(text.splitlines(), start=1)
        if line.strip()
    ]


def cfg_can_list(name: str) -> bool:
    """Whether an image name survives COLMAP's stereo cfg files: a source list is split at
    commas and each name trimmed of spaces, a line ends at a line break."""
    return "," not in name and name == name.strip() and "\n" not in name and "\r" not in name


def write_stereo_configs(
    stereo_dir: str | Path, sources: Mapping[str, str], fusion_images: Sequence[str] | None = None
) -> None:
    """Write ``patch-match.cfg`` (each reference, then its source spec: ``__auto__, N``, ``__all__``
    or comma-separated names) and ``fusion.cfg`` (``fusion_images``, by default the references),
    atomically; the writing twin of ``parse_patch_match_cfg``."""
    stereo_dir = Path(stereo_dir)
    with atomic_path(stereo_dir / "patch-match.cfg") as tmp:
        tmp.write_text("".join(f"{name}\n{spec}\n" for name, spec in sources.items()))
    names = list(sources) if fusion_images is None else list(fusion_images)
    with atomic_path(stereo_dir / "fusion.cfg") as tmp:
        tmp.write_text("".join(f"{name}\n" for name in names))


def _find_model_dir(sparse: Path) -> Path:
    for candidate in (sparse, sparse / "0"):
        if any((candidate / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
            return candidate
    raise WorkspaceError(
        f"no COLMAP model in {sparse}: expected cameras/images/points3D .bin or .txt files there "
        f"(or in {sparse / '0'}). " + _UNDISTORT_HINT
    )


class _Truncated(Exception):
    pass


class _BinaryReader:
    """Walks a COLMAP binary model file, checking that every record it declares is there."""

    def __init__(self, path: Path):
        self.data = path.read_bytes()
        self.offset = 0

    def take(self, fmt: str) -> tuple:
        size = struct.calcsize(fmt)
        if self.offset + size > len(self.data):
            raise _Truncated
        values = struct.unpack_from(fmt, self.data, self.offset)
        self.offset += size
        return values

    def skip(self, size: int) -> None:
        if size < 0 or self.offset + size > len(self.data):
            raise _Truncated
        self.offset += size

    def string(self) -> None:
        end = self.data.find(b"\0", self.offset)
        if end < 0:
            raise _Truncated
        self.offset = end + 1


def _walk_cameras(reader: _BinaryReader) -> int:
    (count,) = reader.take("<Q")
    for _ in range(count):
        _, model_id, _, _ = reader.take("<IiQQ")
        try:
            camera = pycolmap.Camera.create_from_model_id(
                1, pycolmap.CameraModelId(model_id), 1.0, 1, 1
            )
            num_params = len(camera.params)
        except (ValueError, TypeError, RuntimeError):
            raise ValueError(f"unknown camera model id {model_id}") from None
        reader.skip(8 * num_params)
    return count


def _walk_images(reader: _BinaryReader) -> int:
    (count,) = reader.take("<Q")
    for _ in range(count):
        reader.skip(4 + 8 * 7 + 4)  # image id, quaternion, translation, camera id
        reader.string()
        (num_points,) = reader.take("<Q")
        reader.skip(24 * num_points)
    return count


def _walk_points(reader: _BinaryReader) -> int:
    (count,) = reader.take("<Q")
    for _ in range(count):
        reader.skip(8 + 24 + 3 + 8)  # id, xyz, rgb, error
        (track_length,) = reader.take("<Q")
        reader.skip(8 * track_length)
    return count


def check_model_files(model_dir: str | Path) -> None:
    """Check that the binary model files in ``model_dir`` hold every record their counts declare
    and nothing after them (pycolmap reads a truncated file as garbage or fails with an opaque
    message); raises :class:`WorkspaceError` naming the file. Text models are left to pycolmap."""
    model_dir = Path(model_dir)
    for name, walk, what in (
        ("cameras.bin", _walk_cameras, "camera"),
        ("images.bin", _walk_images, "image"),
        ("points3D.bin", _walk_points, "point"),
    ):
        path = model_dir / name
        if not path.is_file():
            continue
        reader = _BinaryReader(path)
        try:
            count = walk(reader)
        except _Truncated:
            raise WorkspaceError(
                f"{path} is truncated: it ends ({len(reader.data)} bytes) before the {what} records its header "
                f"declares; the model was cut off while written or copied: write or copy it again"
            ) from None
        except ValueError as exc:
            raise WorkspaceError(
                f"{path} is not a COLMAP model file ({exc}); write it again"
            ) from None
        if reader.offset != len(reader.data):
            raise WorkspaceError(
                f"{path} has {len(reader.data) - reader.offset} bytes after its {count} {what} records; the file "
                f"is corrupt or of another format: write it again"
            )


def _read_reconstruction(model_dir: Path) -> pycolmap.Reconstruction:
    check_model_files(model_dir)
    try:
        return pycolmap.Reconstruction(str(model_dir))
    except Exception as exc:  # pycolmap raises various types for unreadable models
        files = ", ".join(
            sorted(p.name for p in model_dir.iterdir() if p.suffix in (".bin", ".txt"))
        )
        raise WorkspaceError(
            f"cannot read the COLMAP model in {model_dir} ({files}): {exc}; a file is "
            f"truncated or corrupt: write the model again"
        ) from exc


def _cam_from_world(image: pycolmap.Image) -> pycolmap.Rigid3d:
    pose = image.cam_from_world
    return pose() if callable(pose) else pose


def _check_finite_camera(image: pycolmap.Image, camera: pycolmap.Camera, model_dir: Path) -> None:
    """An image's pose and its camera's intrinsics must be finite, its rotation a rotation and its
    focal lengths positive: a NaN or infinite pose gives a view no source and a depth range of
    inf, and its maps would be garbage that fusion takes."""
    pose = _cam_from_world(image)
    quat = np.asarray(pose.rotation.quat, np.float64)
    translation = np.asarray(pose.translation, np.float64)
    where = f"image {image.name!r} (id {image.image_id}) in the sparse model {model_dir}"
    if not (np.isfinite(quat).all() and np.isfinite(translation).all()):
        raise WorkspaceError(
            f"{where} has a pose that is not finite (quaternion xyzw {quat.tolist()}, translation "
            f"{translation.tolist()}); fix or remove that image in the model (e.g. register it "
            f"again)"
        )
    if not 0.5 < float(np.linalg.norm(quat)) < 2.0:
        raise WorkspaceError(
            f"{where} has a rotation quaternion of norm {np.linalg.norm(quat):.3g} "
            f"({quat.tolist()}), not a rotation; fix or remove that image in the model"
        )
    params = np.asarray(camera.params, np.float64)
    focal = np.asarray([camera.focal_length_x, camera.focal_length_y], np.float64)
    if not np.isfinite(params).all() or not (focal > 0).all():
        raise WorkspaceError(
            f"{where}: its camera {image.camera_id} ({camera.model_name}) has parameters "
            f"{params.tolist()}; they must be finite with positive focal lengths: fix the camera "
            f"in the model"
        )


class Workspace:
    """A COLMAP dense workspace: the views, their calibration, depth ranges and source views.

    Use :meth:`Workspace.open`; ``views`` holds every registered image (any can be a source),
    ``references`` the images to compute maps for (those listed in ``patch-match.cfg``).
    """

    def __init__(
        self, root: Path, reconstruction: pycolmap.Reconstruction, options: WorkspaceOptions
    ):
        self.root = root
        self.options = options
        self.reconstruction = reconstruction
        self.views: dict[str, View] = {}
        self.references: list[str] = []

    # -- construction -------------------------------------------------------------------------

    @classmethod
    def open(cls, root: str | Path, options: WorkspaceOptions | None = None) -> Workspace:
        """Read the workspace at ``root``; raises :class:`WorkspaceError` naming what is wrong."""
        options = options or WorkspaceOptions()
        root = Path(root).expanduser()
        if not root.is_dir():
            raise WorkspaceError(f"workspace folder not found: {root}")
        for folder in ("images", "sparse"):
            if not (root / folder).is_dir():
                raise WorkspaceError(
                    f"workspace {root} has no {folder}/ folder; a COLMAP dense workspace holds "
                    f"images/, sparse/ and stereo/. " + _UNDISTORT_HINT
                )
        model_dir = _find_model_dir(root / "sparse")
        workspace = cls(root, _read_reconstruction(model_dir), options)
        workspace._build_views()
        try:
            ranges = workspace.model.depth_ranges(
                options.depth_quantiles,
                options.depth_margin,
                options.min_points_for_range,
                options.depth_range,
                root,
            )
        except NoDepthRangeError as exc:
            raise WorkspaceError(str(exc)) from None
        for view in workspace.views.values():
            found = ranges[view.name]
            view.depth_range, view.num_sparse_points = found.range, found.num_points
            view.depth_range_is_fallback = found.fallback
        workspace._assign_sources()
        return workspace

    def link_output(self, out: str | Path) -> Path:
        """Make ``out`` a COLMAP dense workspace over this one's images and model, for maps and
        a cloud computed elsewhere than in the workspace itself (which is then only read):
        ``out/images`` and ``out/sparse`` are symbolic links to them, ``out/stereo/patch-match.cfg``
        lists each reference's resolved sources by name and ``fusion.cfg`` the references, so
        that ``colmap stereo_fusion`` and ``dvpmvs fuse`` run on ``out`` as on a workspace."""
        out = Path(out).expanduser()
        if out.exists() and not out.is_dir():
            raise WorkspaceError(
                f"out={out} is a file; out= names the folder for the maps, the cloud and the manifest"
            )
        references = self.reference_views()
        listed = {name for v in references for name in (v.name, *v.sources)}
        unfit = sorted(name for name in listed if not cfg_can_list(name))
        if unfit:
            raise WorkspaceError(
                f"image {unfit[0]!r}{f' (and {len(unfit) - 1} more)' if len(unfit) > 1 else ''} cannot be listed in "
                f"COLMAP's stereo/patch-match.cfg, which out={out} needs (COLMAP and dvpmvs split source lists at "
                f"commas and trim spaces): rename the image (file and sparse model), or run in the workspace itself "
                f"(without out=), whose own cfg it keeps"
            )
        out.mkdir(parents=True, exist_ok=True)
        for name, target in (("images", self.images_dir), ("sparse", self.model_dir)):
            link = out / name
            target = target.resolve()
            if link.is_symlink():
                if link.resolve() == target:
                    continue
                link.unlink()
            elif link.exists():
                raise WorkspaceError(
                    f"the output folder {out} holds a {name}/ of its own; out= must be a new folder or an "
                    f"earlier output folder (whose {name} is a link to the workspace's)"
                )
            link.symlink_to(target, target_is_directory=True)
        write_stereo_configs(
            out / "stereo",
            {v.name: ", ".join(v.sources) for v in references if v.sources},
            fusion_images=[v.name for v in self.fusion_views()],
        )
        return out

    @property
    def model_dir(self) -> Path:
        """The folder holding the sparse model: ``sparse/`` or ``sparse/0/``."""
        return _find_model_dir(self.root / "sparse")

    @property
    def images_dir(self) -> Path:
        return self.root / "images"

    @property
    def colmap_image_indices(self) -> dict[str, int]:
        """Image name -> its index among the model's registered images in the order COLMAP reads
        them (``Reconstruction::RegImageIds``): the index a fused cloud's ``.vis`` file names
        an image by, in COLMAP's fusion and meshers."""
        names = [self.reconstruction.image(i).name for i in self.reconstruction.reg_image_ids()]
        return {name: index for index, name in enumerate(names)}

    @property
    def stereo_dir(self) -> Path:
        return self.root / "stereo"

    def _build_views(self) -> None:
        images = sorted(self.reconstruction.images.values(), key=lambda image: image.name)
        names = [image.name for image in images]
        repeated = (
            sorted({name for name in names if names.count(name) > 1})
            if len(set(names)) < len(names)
            else []
        )
        if repeated:
            raise WorkspaceError(
                f"the sparse model in {self.model_dir} names {len(repeated)} image(s) more than once (e.g. "
                f"{repeated[0]!r}, image ids {sorted(i.image_id for i in images if i.name == repeated[0])}); "
                f"maps are named after images, so each name must be unique: fix the model's images"
            )
        registered = [image for image in images if image.has_pose]
        if not registered:
            raise WorkspaceError(
                f"the sparse model in {self.root / 'sparse'} has no registered images"
            )
        missing = [
            image.name for image in registered if not (self.images_dir / image.name).is_file()
        ]
        if missing:
            shown = ", ".join(missing[:5]) + (
                f" and {len(missing) - 5} more" if len(missing) > 5 else ""
            )
            raise WorkspaceError(
                f"{len(missing)} image(s) of the sparse model are missing from {self.images_dir}: "
                f"{shown}. Copy them there or rerun image_undistorter"
            )
        for image in registered:
            camera = self.reconstruction.camera(image.camera_id)
            # Every image complete and of its camera's size before any compute, not when first read.
            size = check_image_file(self.images_dir / image.name)
            if size != (int(camera.width), int(camera.height)):
                raise ImageReadError(
                    f"image {self.images_dir / image.name} is {size[0]}x{size[1]} but its camera in the sparse "
                    f"model is {camera.width}x{camera.height}; the workspace images do not match the model "
                    f"(was image_undistorter run with another max_image_size?)"
                )
            if camera.model_name not in UNDISTORTED_MODELS:
                raise WorkspaceError(
                    f"image {image.name} uses camera {image.camera_id} with model {camera.model_name}; "
                    f"only {' or '.join(UNDISTORTED_MODELS)} cameras are supported. "
                    + _UNDISTORT_HINT
                )
            _check_finite_camera(image, camera, self.model_dir)
            width, height = int(camera.width), int(camera.height)
            new_width, new_height = self._scaled_size(width, height)
            K = np.asarray(camera.calibration_matrix(), dtype=np.float64).copy()
            K[0, :] *= new_width / width
            K[1, :] *= new_height / height
            pose = _cam_from_world(image)
            matrix = np.asarray(pose.matrix(), dtype=np.float64)
            self.views[image.name] = View(
                image_id=int(image.image_id),
                name=image.name,
                path=self.images_dir / image.name,
                K=K,
                R=matrix[:, :3].copy(),
                t=matrix[:, 3].copy(),
                width=new_width,
                height=new_height,
                original_size=(width, height),
            )

    @cached_property
    def max_image_size(self) -> int:
        """The longest image side the views are matched at (-1: their own size): the options'
        ``max_image_size``, or lower with a ``resolution_level`` (see ``WorkspaceOptions``)."""
        limit = self.options.max_image_size
        if self.options.resolution_level > 0:
            longest = max(
                max(int(camera.width), int(camera.height))
                for camera in self.reconstruction.cameras.values()
            )
            level = max(
                self.options.min_resolution, int(round(longest / 2**self.options.resolution_level))
            )
            if level < longest:
                limit = level if limit <= 0 else min(limit, level)
        return limit

    def resolution_scale(self, view: View) -> float:
        """How much smaller ``view`` is matched than without a ``resolution_level`` (1.0 without
        one): sizes in pixels that options give for the images at level 0 are scaled by it."""
        own = self._scaled_size(*view.original_size, limit=self.options.max_image_size)
        return max(view.width, view.height) / max(own)

    def _scaled_size(self, width: int, height: int, limit: int | None = None) -> tuple[int, int]:
        limit = self.max_image_size if limit is None else limit
        if limit <= 0 or max(width, height) <= limit:
            return width, height
        factor = limit / max(width, height)
        return max(1, round(width * factor)), max(1, round(height * factor))

    # -- the sparse model ---------------------------------------------------------------------

    @cached_property
    def model(self) -> SparseModel:
        """The sparse model's queries over these views (depth ranges, shared points)."""
        return SparseModel(self.reconstruction, self.views)

    def observed_points(self, name: str) -> np.ndarray:
        """(N, 3) world coordinates of the sparse points image ``name`` observes."""
        return self.model.observed_points(name)

    def sparse_points(self, name: str) -> np.ndarray:
        """(N, 3) ``[col, row, depth]`` of the sparse points image ``name`` observes (in front of
        it), in the pixel convention of the (possibly downscaled) view."""
        view = self.views[name]
        X = self.observed_points(name) @ view.R.T + view.t
        X = X[X[:, 2] > 0]
        uv = X @ view.K.T
        return np.stack([uv[:, 0] / uv[:, 2], uv[:, 1] / uv[:, 2], X[:, 2]], axis=1)

    @property
    def covisibility(self) -> Mapping[str, dict[str, np.ndarray]]:
        """name -> other name -> triangulation angles (degrees) of the sparse points both observe
        (:attr:`dvpmvs.model.SparseModel.covisibility`). View selectors rank on this."""
        return self.model.covisibility

    # -- source views -------------------------------------------------------------------------

    # -- source views -------------------------------------------------------------------------

    def _assign_sources(self) -> None:
        cfg = self.stereo_dir / "patch-match.cfg"
        if cfg.is_file():
            specs = parse_patch_match_cfg(cfg)
            if not specs:
                raise WorkspaceError(
                    f"{cfg} lists no reference image: write a line with an image name, then a line with its "
                    f"sources (`__auto__, N`, `__all__` or names), for each image to compute; or delete the "
                    f"file to compute every image with `__auto__, {self.options.default_num_sources}`"
                )
        else:
            log.warning(
                "%s not found; computing every image with `__auto__, %d` source views",
                cfg,
                self.options.default_num_sources,
            )
            specs = [SourceSpec(name, auto=self.options.default_num_sources) for name in self.views]
        selector: ViewSelector | None = None
        seen = set()
        for spec in specs:
            where = f"{cfg}:{spec.line}" if spec.line else str(cfg)
            where_reference = f"{cfg}:{spec.reference_line}" if spec.reference_line else str(cfg)
            if spec.reference not in self.views:
                raise WorkspaceError(
                    f"{where_reference}: reference image {spec.reference!r} is not a registered image of the "
                    f"sparse model ({len(self.views)} images, e.g. {next(iter(self.views))!r})"
                )
            if spec.reference in seen:
                raise WorkspaceError(
                    f"{where_reference}: reference image {spec.reference!r} is listed twice"
                )
            seen.add(spec.reference)
            view = self.views[spec.reference]
            if spec.all:
                view.sources = tuple(name for name in self.views if name != spec.reference)
                view.source_scores = tuple(math.nan for _ in view.sources)
            elif spec.auto is not None:
                if selector is None:
                    selector = registry.create("view_selector", self.options.view_selector)
                ranked = list(selector(self, spec.reference, spec.auto))[: spec.auto]
                for name, _ in ranked:
                    if name not in self.views or name == spec.reference:
                        raise WorkspaceError(
                            f"view selector {self.options.view_selector.get('name')!r} returned "
                            f"{name!r} as a source of {spec.reference!r}, which is not another view"
                        )
                view.sources = tuple(name for name, _ in ranked)
                view.source_scores = tuple(float(score) for _, score in ranked)
            else:
                for name in spec.sources:
                    if name not in self.views:
                        raise WorkspaceError(
                            f"{where}: source image {name!r} of {spec.reference!r} does not exist "
                            f"in the sparse model; fix the name or use `__auto__, N`"
                        )
                    if name == spec.reference:
                        raise WorkspaceError(f"{where}: image {name!r} is listed as its own source")
                view.sources = tuple(spec.sources)
                view.source_scores = tuple(math.nan for _ in spec.sources)
            if view.sources and not self.model.overlaps(view):
                log.warning(
                    "image %s shares no sparse point with any of its %d source view(s); it will get no "
                    "depth map",
                    spec.reference,
                    len(view.sources),
                )
                view.sources, view.source_scores = (), ()
            elif not view.sources:
                log.warning(
                    "image %s has no source views; it will get no depth map", spec.reference
                )
            self.references.append(spec.reference)

    # -- access -------------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self.views)

    def __getitem__(self, name: str) -> View:
        try:
            return self.views[name]
        except KeyError:
            raise KeyError(f"no image named {name!r} in the workspace {self.root}") from None

    def reference_views(self) -> Sequence[View]:
        """The views to compute maps for, in ``patch-match.cfg`` order."""
        return [self.views[name] for name in self.references]

    def fusion_views(self, stereo_dir: str | Path | None = None) -> list[View]:
        """The views to fuse, in order: those ``fusion.cfg`` in ``stereo_dir`` (default the
        workspace's ``stereo/``) lists, as COLMAP's fusion reads them, or without that file the
        reference views. A listed name that is no registered image of the model is an error
        naming the file and line (COLMAP's fusion stops on a failed check there)."""
        path = (self.stereo_dir if stereo_dir is None else Path(stereo_dir)) / "fusion.cfg"
        if not path.is_file():
            return list(self.reference_views())
        views: list[View] = []
        for line, name in parse_fusion_cfg(path):
            if name not in self.views:
                raise WorkspaceError(
                    f"{path}:{line}: image {name!r} is not a registered image of the sparse model "
                    f"in {self.model_dir}; fix the name or remove the line (fusion.cfg lists the "
                    f"images to fuse)"
                )
            if self.views[name] not in views:
                views.append(self.views[name])
        if not views:
            raise WorkspaceError(
                f"{path} lists no image: nothing to fuse; list the images to fuse, one per line (or "
                f"remove the file to fuse every view of patch-match.cfg)"
            )
        return views
