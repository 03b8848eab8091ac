"""Depth-map fusion: ours (streaming, kernel in ``_fusion.pyx``) and COLMAP's through pycolmap.

Ours visits the reference views in order; a pixel's point is kept when at least
``min_consistent_views`` of its neighbour views agree within ``max_reproj_error`` pixels
(forward-backward), ``max_depth_error`` relative depth and ``max_normal_error`` degrees. The
agreeing points are averaged (position: per-coordinate median by default, normal and colour:
mean) and the neighbours' agreeing pixels are marked used, so each surface point is emitted
once.

Memory follows the views in a neighbourhood, not the scene: the maps of at most
``max(cache_views, max_neighbours + 1)`` views (an LRU cache; 19 bytes per pixel: depth,
normal, colour), the used-pixel masks (1 byte per pixel) of the views a later reference still
reads (a view's mask is dropped after the last reference that has it as itself or among its
first ``max_neighbours`` sources: with the references in walking order, those within a
neighbourhood), and one reference's outputs (about 60 bytes per pixel). :func:`fuse_to_ply`
writes each view's points to the cloud's file as they are made; :func:`fuse` returns the whole
cloud in memory.

Every fused point also records the views that support it (the reference and its agreeing
neighbours), written beside the cloud as COLMAP's ``<cloud>.vis`` (:func:`write_visibility`), so
that ``colmap delaunay_mesher`` and other COLMAP tools that read a fused cloud read ours.
"""

from __future__ import annotations

import errno
import logging
import os
import shutil
import tempfile
from collections import OrderedDict
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

import dvpmvs._fusion as _fusion
from dvpmvs._kernel_sources import require_current
from dvpmvs.errors import DvpmvsError
from dvpmvs.maps import (
    DiskFullError,
    atomic_path,
    disk_full_message,
    map_path,
    read_depth_map,
    read_normal_map,
)
from dvpmvs.options.fusion import FusionOptions
from dvpmvs.passes import Pass
from dvpmvs.pointcloud import ply_header
from dvpmvs.validation import resolve_threads
from dvpmvs.view import View
from dvpmvs.workspace import Workspace

require_current(_fusion)

__all__ = [
    "FusionOptions",
    "FusedCloud",
    "FusionError",
    "check_maps",
    "empty_cloud_message",
    "fuse",
    "fuse_to_ply",
    "fuse_with_colmap",
    "read_visibility",
    "visibility_path",
    "write_fused_cloud",
    "write_visibility",
]

log = logging.getLogger(__name__)


class FusionError(DvpmvsError, RuntimeError):
    """Fusion cannot run: maps are missing or inconsistent with the workspace."""


@dataclass
class FusedCloud:
    """points (N, 3) float32, world frame; normals (N, 3) float32; colors (N, 3) uint8.
    visibility_counts (N,) uint32 and visibility_images (sum of the counts,) uint32: point i is
    supported by the next ``visibility_counts[i]`` entries of ``visibility_images``, indices of
    images in the order COLMAP reads the workspace's model (:attr:`Workspace.colmap_image_indices`)."""

    points: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    points_per_view: dict[str, int]
    visibility_counts: np.ndarray
    visibility_images: np.ndarray

    def __len__(self) -> int:
        return len(self.points)


@dataclass
class _ViewMaps:
    depth: np.ndarray
    normal: np.ndarray
    rgb: np.ndarray


class _MapCache:
    """Maps and colours of the most recently used views (bounded memory)."""

    def __init__(
        self,
        workspace: Workspace,
        pass_: Pass,
        capacity: int,
        stereo_dir: Path,
        masks=None,
    ):
        self.workspace = workspace
        self.masks = masks
        self.stereo_dir = stereo_dir
        self.pass_ = pass_
        self.capacity = capacity
        self.entries: OrderedDict[str, _ViewMaps | None] = OrderedDict()

    def get(self, view: View) -> _ViewMaps | None:
        if view.name in self.entries:
            self.entries.move_to_end(view.name)
            return self.entries[view.name]
        maps = self._load(view)
        self.entries[view.name] = maps
        while len(self.entries) > self.capacity:
            self.entries.popitem(last=False)
        return maps

    def _load(self, view: View) -> _ViewMaps | None:
        stereo = self.stereo_dir
        depth_file = map_path(stereo, view.name, "depth", self.pass_)
        if not depth_file.is_file():
            return None
        depth, normal = _read_view_maps(stereo, view, self.pass_)
        if self.masks is not None and self.masks.active:
            # A masked pixel neither starts a point nor joins one: as if it had no depth. The
            # stored mask is read: a reloaded view does not ask the provider again.
            keep = self.masks.load(view)
            depth = np.where(keep, depth, 0).astype(np.float32)
        rgb = np.clip(np.round(view.load_rgb() * 255), 0, 255).astype(np.uint8)
        return _ViewMaps(depth, np.ascontiguousarray(normal, np.float32), rgb)


def _stack(maps: list[_ViewMaps], views: list[View]):
    HN = max(m.depth.shape[0] for m in maps)
    WN = max(m.depth.shape[1] for m in maps)
    N = len(maps)
    depth = np.zeros((N, HN, WN), np.float32)
    normal = np.zeros((N, HN, WN, 3), np.float32)
    rgb = np.zeros((N, HN, WN, 3), np.uint8)
    size = np.zeros((N, 2), np.int32)
    for j, m in enumerate(maps):
        h, w = m.depth.shape
        depth[j, :h, :w] = m.depth
        normal[j, :h, :w] = m.normal
        rgb[j, :h, :w] = m.rgb
        size[j] = (w, h)
    K = np.ascontiguousarray([v.K for v in views], np.float64)
    R = np.ascontiguousarray([v.R for v in views], np.float64)
    t = np.ascontiguousarray([v.t for v in views], np.float64)
    return depth, normal, rgb, size, K, R, t


@dataclass
class _FusedView:
    """The points one reference view adds (see :class:`FusedCloud`)."""

    name: str
    points: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    visibility_counts: np.ndarray
    visibility_images: np.ndarray


def _neighbours(view: View, fused: set[str], max_neighbours: int) -> list[str]:
    """The views whose maps a reference's pixels are checked against: its first
    ``max_neighbours`` sources among the views fused (COLMAP's fusion takes no pixel of an image
    ``fusion.cfg`` leaves out)."""
    return [name for name in view.sources if name in fused][:max_neighbours]


def _last_uses(references: list[View], max_neighbours: int) -> dict[str, int]:
    """Per view, the index of the last reference whose fusion reads or marks its pixels (as the
    reference or one of its neighbours)."""
    fused = {view.name for view in references}
    last = {}
    for i, view in enumerate(references):
        for name in (view.name, *_neighbours(view, fused, max_neighbours)):
            last[name] = i
    return last


def _checked_masks(options: FusionOptions, masks):
    """The masks fusion applies: ``masks`` (the views' masks of ``options.mask``, which the
    caller makes and stores, :class:`dvpmvs.dense.MaskStore`), required where ``options.mask``
    names a provider."""
    if options.mask is not None and masks is None:
        raise ValueError(
            "fusion options name a mask provider (mask=...): give the views' masks too "
            "(masks=dvpmvs.dense.MaskStore.from_config(options.mask, stereo_dir, workspace.root)), "
            "or fuse through dvpmvs.dense.fuse_workspace, which makes them"
        )
    return masks


def _fused_views(
    workspace: Workspace,
    options: FusionOptions,
    progress: Callable[[str], None] | None,
    stereo: Path,
    masks,
    views: list[View] | None,
) -> Iterator[_FusedView]:
    """Fuse the reference views in order, yielding each one's points. What it holds: the maps
    of at most ``cache_views`` views, and the used-pixel masks of the views that a later
    reference still reads (a mask is dropped after the last reference that reads it), so its
    memory follows the views in a neighbourhood, not the scene."""
    pass_ = Pass(options.input_type)
    threads = resolve_threads(options.num_threads)
    cache = _MapCache(
        workspace,
        pass_,
        max(options.cache_views, options.max_neighbours + 1),
        stereo,
        _checked_masks(options, masks),
    )
    used: dict[str, np.ndarray] = {}
    image_index = workspace.colmap_image_indices
    references = workspace.fusion_views(stereo) if views is None else views
    fused = {view.name for view in references}
    if not any(map_path(stereo, v.name, "depth", pass_).is_file() for v in references):
        raise FusionError(
            f"no {pass_.value} depth maps in {stereo / 'depth_maps'}; "
            f"{missing_maps_hint(workspace, stereo, pass_, [v.name for v in references])}"
        )
    last_use = _last_uses(references, options.max_neighbours)
    for i, view in enumerate(references):
        if progress:
            progress(view.name)
        yield _fuse_view(view, workspace, options, cache, used, image_index, threads, pass_, fused)
        for name in [n for n in used if last_use.get(n, -1) <= i]:
            del used[name]


def _fuse_view(
    view: View,
    workspace: Workspace,
    options: FusionOptions,
    cache: _MapCache,
    used: dict[str, np.ndarray],
    image_index: dict[str, int],
    threads: int,
    pass_: Pass,
    fused: set[str],
) -> _FusedView:
    empty = _FusedView(
        view.name,
        np.zeros((0, 3), np.float32),
        np.zeros((0, 3), np.float32),
        np.zeros((0, 3), np.uint8),
        np.zeros(0, np.uint32),
        np.zeros(0, np.uint32),
    )
    ref = cache.get(view)
    if ref is None:
        log.warning("no %s maps for %s; it adds no points", pass_.value, view.name)
        return empty
    neighbours, nb_maps = [], []
    for name in _neighbours(view, fused, options.max_neighbours):
        maps = cache.get(workspace[name])
        if maps is not None:
            neighbours.append(workspace[name])
            nb_maps.append(maps)
    if len(neighbours) < options.min_consistent_views:
        return empty
    for v in (view, *neighbours):
        if v.name not in used:
            used[v.name] = np.zeros((v.height, v.width), np.uint8)
    nb_depth, nb_normal, nb_rgb, nb_size, nb_K, nb_R, nb_t = _stack(nb_maps, neighbours)
    nb_used = np.zeros(nb_depth.shape, np.uint8)
    for j, v in enumerate(neighbours):
        nb_used[j, : v.height, : v.width] = used[v.name]
    h, w = ref.depth.shape
    out_point = np.zeros((h, w, 3), np.float32)
    out_normal = np.zeros((h, w, 3), np.float32)
    out_rgb = np.zeros((h, w, 3), np.float32)
    valid = np.zeros((h, w), np.uint8)
    agreeing = np.zeros((h, w), np.uint64)
    _fusion.fuse_view(
        ref.depth,
        ref.normal,
        ref.rgb,
        view.K,
        view.R,
        view.t,
        used[view.name],
        nb_depth,
        nb_normal,
        nb_rgb,
        nb_size,
        nb_K,
        nb_R,
        nb_t,
        nb_used,
        options.max_reproj_error,
        options.max_depth_error,
        options.max_normal_error,
        options.min_consistent_views,
        out_point,
        out_normal,
        out_rgb,
        valid,
        agreeing,
        threads,
        options.point_average == "median",
    )
    for j, v in enumerate(neighbours):
        used[v.name] |= nb_used[j, : v.height, : v.width]
    keep = valid.astype(bool)
    used[view.name] |= valid
    counts, images = _supporting_images(
        agreeing[keep], [image_index[view.name]] + [image_index[v.name] for v in neighbours]
    )
    return _FusedView(
        view.name,
        out_point[keep],
        out_normal[keep],
        np.clip(np.round(out_rgb[keep]), 0, 255).astype(np.uint8),
        counts,
        images,
    )


def fuse(
    workspace: Workspace,
    options: FusionOptions | None = None,
    progress: Callable[[str], None] | None = None,
    stereo_dir: str | Path | None = None,
    masks=None,
    views: list[View] | None = None,
) -> FusedCloud:
    """Fuse the ``options.input_type`` maps in ``stereo_dir`` (default the workspace's
    ``stereo/``) into one cloud in memory (see the module doc; :func:`fuse_to_ply` streams it
    to a file instead). ``masks``: the views' masks of ``options.mask`` (a
    :class:`dvpmvs.dense.MaskStore`; needed where ``options.mask`` names a provider).
    ``views``: the views to fuse, in order (default :meth:`Workspace.fusion_views`)."""
    options = options or FusionOptions()
    stereo = workspace.stereo_dir if stereo_dir is None else Path(stereo_dir)
    views = list(_fused_views(workspace, options, progress, stereo, masks, views))
    return FusedCloud(
        np.concatenate([v.points for v in views]),
        np.concatenate([v.normals for v in views]),
        np.concatenate([v.colors for v in views]),
        {v.name: len(v.points) for v in views},
        np.concatenate([v.visibility_counts for v in views]),
        np.concatenate([v.visibility_images for v in views]),
    )


def fuse_to_ply(
    workspace: Workspace,
    output: str | Path,
    options: FusionOptions | None = None,
    progress: Callable[[str], None] | None = None,
    stereo_dir: str | Path | None = None,
    masks=None,
    views: list[View] | None = None,
) -> dict[str, int]:
    """Fuse as :func:`fuse` does (``masks`` and ``views`` as there), writing each view's points
    to ``output`` (binary PLY, as :func:`write_fused_cloud` writes it, with its ``.vis`` beside
    it) as they are made: the cloud is never held in memory. Returns the points per view."""
    options = options or FusionOptions()
    stereo = workspace.stereo_dir if stereo_dir is None else Path(stereo_dir)
    per_view = {}
    with _StreamedCloud(Path(output)) as writer:
        for view in _fused_views(workspace, options, progress, stereo, masks, views):
            writer.add(
                view.points,
                view.normals,
                view.colors,
                view.visibility_counts,
                view.visibility_images,
            )
            per_view[view.name] = len(view.points)
    return per_view


def _supporting_images(agreeing: np.ndarray, images: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Per kept pixel the number of supporting images and, concatenated, their indices: the
    reference ``images[0]`` first, then neighbour j (``images[j + 1]``) where bit j of
    ``agreeing`` is set."""
    n = len(images) - 1
    # The bits of the first ceil(n / 8) bytes of each little-endian mask, bit j in column j.
    as_bytes = agreeing.astype("<u8").view(np.uint8).reshape(-1, 8)[:, : (n + 7) // 8]
    bits = np.unpackbits(as_bytes, axis=1, bitorder="little")[:, :n].astype(bool)
    support = np.concatenate([np.ones((len(bits), 1), bool), bits], axis=1)
    candidates = np.broadcast_to(np.asarray(images, np.uint32), support.shape)
    return support.sum(axis=1).astype(np.uint32), candidates[support]


def empty_cloud_message(options: FusionOptions, stereo: Path, masks=None, views=()) -> str:
    """Why a cloud is empty, from what the run has: masks that keep no pixel of ``views``, else
    the fusion thresholds, with the maps' previews where ``stereo`` holds them."""
    if masks is not None and masks.active and views:
        if not any(masks.load(view).any() for view in views):
            return (
                f"fusion kept no point: the masks (mask={masks.masks.config.get('name')}) keep no "
                f"pixel of any view, so no pixel has a depth; check the masks (a mask keeps the "
                f"pixels whose value is not 0 in COLMAP's layout)"
            )
    previews = Path(stereo) / "previews"
    look = (
        f"Look at the depth previews in {previews}"
        if previews.is_dir()
        else "Look at the depth maps (`dvpmvs report` draws them)"
    )
    return (
        f"fusion kept no point: no pixel of the {options.input_type} maps was confirmed by "
        f"{options.min_consistent_views} other view(s) within the fusion thresholds; the cloud is empty. "
        f"{look} (empty maps: too small images, no overlap, a wrong depth range); "
        f"fusion_options.min_consistent_views=1 or looser fusion_options thresholds keep more"
    )


def missing_maps_hint(workspace: Workspace, stereo: Path, pass_: Pass, views: list[str]) -> str:
    """What to do when ``views`` have no ``pass_`` maps in ``stereo``: fuse the other pass's
    maps where every one of them has those (a run with ``geometric=false`` made photometric maps
    only), else compute them."""
    other = Pass.PHOTOMETRIC if pass_ is Pass.GEOMETRIC else Pass.GEOMETRIC
    if views and all(map_path(stereo, name, "depth", other).is_file() for name in views):
        extra = " (the dense run had geometric=false)" if other is Pass.PHOTOMETRIC else ""
        return (
            f"they have {other.value} maps{extra}: fuse those with input_type={other.value}, or compute the "
            f"{pass_.value} ones with `dvpmvs dense workspace={workspace.root}`"
        )
    return f"run `dvpmvs dense workspace={workspace.root}` first"


def check_maps(views: list[View], pass_: Pass, stereo_dir: str | Path) -> None:
    """Read the ``pass_`` maps of every view fused as our fusion does (size, NaN, negative
    depths, normals that are not unit vectors), so that a corrupt map is an error naming it,
    whoever fuses."""
    for view in views:
        _read_view_maps(Path(stereo_dir), view, pass_)


def _read_view_maps(stereo: Path, view: View, pass_: Pass) -> tuple[np.ndarray, np.ndarray]:
    """A view's depth and normal maps of ``pass_``, checked by the readers and against its size."""
    depth = read_depth_map(map_path(stereo, view.name, "depth", pass_))
    normal = read_normal_map(map_path(stereo, view.name, "normal", pass_))
    if depth.shape != (view.height, view.width) or normal.shape != (view.height, view.width, 3):
        raise FusionError(
            f"the maps of {view.name} are {depth.shape[1]}x{depth.shape[0]} but the view is "
            f"{view.width}x{view.height}; fuse with the max_image_size (or resolution_level) the maps were "
            f"computed with"
        )
    return depth, normal


def write_fused_cloud(path: str | Path, cloud: FusedCloud) -> Path:
    """Binary PLY with float32 positions and normals, uint8 colours, and beside it the views
    that support each point (:func:`write_visibility`); each file written atomically, the
    visibility first, so that a cloud is never newer than its visibility file."""
    with _StreamedCloud(Path(path)) as writer:
        writer.add(
            cloud.points,
            cloud.normals,
            cloud.colors,
            cloud.visibility_counts,
            cloud.visibility_images,
        )
    return Path(path)


_PLY_VERTEX = np.dtype(
    [
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("nx", "<f4"),
        ("ny", "<f4"),
        ("nz", "<f4"),
        ("red", "u1"),
        ("green", "u1"),
        ("blue", "u1"),
    ]
)


class _StreamedCloud:
    """A fused cloud written chunk by chunk: the vertices and the visibility records go to
    temporary files beside the outputs; on a clean exit the ``.vis`` and then the PLY are made
    (header, then the body copied) and renamed into place, so neither is ever seen half-written
    and memory holds one chunk at a time."""

    def __init__(self, path: Path):
        self.path = path
        self.points = 0

    def __enter__(self) -> _StreamedCloud:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._bodies = []
        for target in (self.path, visibility_path(self.path)):
            # Named as atomic_path names its temporaries, so that an interrupted run's are removed.
            fd, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
            self._bodies.append((Path(name), os.fdopen(fd, "wb")))
        return self

    def add(
        self,
        points: np.ndarray,
        normals: np.ndarray,
        colors: np.ndarray,
        counts: np.ndarray,
        images: np.ndarray,
    ) -> None:
        n = len(points)
        if not (len(normals) == len(colors) == len(counts) == n) or int(
            np.sum(counts, dtype=np.uint64)
        ) != len(images):
            raise ValueError(
                "a fused chunk's arrays disagree on its number of points or supporting images"
            )
        vertices = np.empty(n, _PLY_VERTEX)
        for k, name in enumerate(("x", "y", "z")):
            vertices[name] = points[:, k]
        for k, name in enumerate(("nx", "ny", "nz")):
            vertices[name] = normals[:, k]
        for k, name in enumerate(("red", "green", "blue")):
            vertices[name] = colors[:, k]
        try:
            self._bodies[0][1].write(vertices.tobytes())
            self._bodies[1][1].write(
                _visibility_records(np.asarray(counts, np.uint32), np.asarray(images, np.uint32))
            )
        except OSError as exc:
            if exc.errno in (errno.ENOSPC, errno.EDQUOT):
                raise DiskFullError(
                    disk_full_message(
                        self.path.parent,
                        f"writing the fused cloud {self.path.name}, "
                        f"{self.points + n:,} points so far",
                    )
                ) from None
            raise
        self.points += n

    def __exit__(self, kind, value, traceback) -> None:
        try:
            failed = []
            for _, body in self._bodies:
                try:
                    body.close()  # flushes the last chunk: a full disk shows here too
                except OSError as exc:
                    failed.append(exc)
            if kind is not None:
                return
            if failed and failed[0].errno in (errno.ENOSPC, errno.EDQUOT):
                raise DiskFullError(
                    disk_full_message(self.path.parent, f"writing the fused cloud {self.path.name}")
                )
            if failed:
                raise failed[0]
            (vertices, _), (visibility, _) = self._bodies
            # The visibility first: a cloud is never newer than its visibility file.
            _write_with_header(
                visibility_path(self.path),
                np.uint64(self.points).astype("<u8").tobytes(),
                visibility,
            )
            _write_with_header(self.path, ply_header(_PLY_VERTEX, self.points), vertices)
        finally:
            for path, _ in self._bodies:
                path.unlink(missing_ok=True)


def _write_with_header(path: Path, header: bytes, body: Path) -> None:
    """``header`` then the bytes of the file ``body``, written atomically to ``path``."""
    with atomic_path(path) as tmp, open(tmp, "wb") as out, open(body, "rb") as data:
        out.write(header)
        shutil.copyfileobj(data, out, 16 << 20)


def visibility_path(cloud: str | Path) -> Path:
    """Where COLMAP's tools look for a fused cloud's visibility: ``<cloud>.vis``."""
    cloud = Path(cloud)
    return cloud.with_name(cloud.name + ".vis")


def write_visibility(path: str | Path, counts: np.ndarray, images: np.ndarray) -> Path:
    """COLMAP's points-visibility file (as ``stereo_fusion`` writes it and ``delaunay_mesher``
    reads it): little-endian uint64 number of points, then per point a uint32 number of images
    followed by that many uint32 image indices. ``counts`` / ``images``: see :class:`FusedCloud`."""
    counts = np.asarray(counts, np.uint32)
    images = np.asarray(images, np.uint32)
    if int(counts.sum(dtype=np.uint64)) != len(images):
        raise ValueError(
            f"the visibility counts add up to {int(counts.sum())} but {len(images)} image indices "
            f"were given"
        )
    with atomic_path(path, suffix=".tmp.vis") as tmp:
        with open(tmp, "wb") as f:
            f.write(np.uint64(len(counts)).astype("<u8").tobytes())
            f.write(_visibility_records(counts, images))
    return Path(path)


def _visibility_records(counts: np.ndarray, images: np.ndarray) -> bytes:
    """Per point its number of images and their indices, as little-endian uint32."""
    record = np.empty(len(counts) + len(images), "<u4")
    starts = np.arange(len(counts)) + np.concatenate([[0], np.cumsum(counts[:-1], dtype=np.int64)])
    is_count = np.zeros(len(record), bool)
    is_count[starts] = True
    record[is_count] = counts
    record[~is_count] = images
    return record.tobytes()


def read_visibility(path: str | Path) -> list[np.ndarray]:
    """The image indices supporting each point of a ``.vis`` file (see :func:`write_visibility`)."""
    path = Path(path)
    data = path.read_bytes()
    if len(data) < 8:
        raise FusionError(
            f"{path} is not a COLMAP visibility file: {len(data)} bytes, fewer than its header's 8"
        )
    num_points = int(np.frombuffer(data[:8], "<u8")[0])
    words = np.frombuffer(data[8 : 8 + (len(data) - 8) // 4 * 4], "<u4")
    points, at = [], 0
    for _ in range(num_points):
        if at >= len(words) or at + 1 + int(words[at]) > len(words):
            raise FusionError(
                f"{path} is truncated: it ends before the {num_points} points its header declares"
            )
        n = int(words[at])
        points.append(words[at + 1 : at + 1 + n].copy())
        at += 1 + n
    if at != len(words) or (len(data) - 8) % 4:
        raise FusionError(
            f"{path} has bytes after its {num_points} points: corrupt or of another format"
        )
    return points


def fuse_with_colmap(
    workspace: Workspace,
    output: str | Path,
    options: FusionOptions | None = None,
    min_num_pixels: int | None = None,
    root: str | Path | None = None,
    masks=None,
    views: list[View] | None = None,
) -> int:
    """COLMAP's own ``stereo_fusion`` (through pycolmap) on the maps of the COLMAP workspace
    ``root`` (default the workspace itself; an output folder of :meth:`Workspace.link_output`);
    returns the number of points written to ``output`` (binary PLY). Thresholds come from
    ``options`` (the reprojection one from ``colmap_max_reproj_error``, see FusionOptions);
    ``min_num_pixels`` defaults to min_consistent_views + 1 (the reference pixel counts);
    ``masks`` and ``views`` as :func:`fuse` takes them."""
    import pycolmap

    options = options or FusionOptions()
    pass_ = Pass(options.input_type)
    root = workspace.root if root is None else Path(root)
    stereo = root / "stereo"
    views = workspace.fusion_views(stereo) if views is None else views
    missing = [v.name for v in views if not map_path(stereo, v.name, "depth", pass_).is_file()]
    if missing:
        raise FusionError(
            f"{len(missing)} view(s) have no {pass_.value} maps (e.g. {missing[0]}); COLMAP's "
            f"fusion needs every view of stereo/fusion.cfg: "
            f"{missing_maps_hint(workspace, stereo, pass_, missing)}"
        )
    if not (stereo / "fusion.cfg").is_file():
        raise FusionError(
            f"{stereo / 'fusion.cfg'} is missing; COLMAP's fusion reads the image list from it"
        )
    # COLMAP reads whatever floats the files hold: the checks of our own fusion first.
    check_maps(views, pass_, stereo)
    colmap_options = pycolmap.StereoFusionOptions()
    colmap_options.min_num_pixels = (
        options.min_consistent_views + 1 if min_num_pixels is None else min_num_pixels
    )
    colmap_options.max_reproj_error = options.colmap_max_reproj_error
    colmap_options.max_depth_error = options.max_depth_error
    colmap_options.max_normal_error = options.max_normal_error
    colmap_options.num_threads = options.num_threads or -1
    colmap_options.max_image_size = workspace.max_image_size
    output = Path(output)
    visibility = output.with_name(output.name + ".vis")
    masks = _checked_masks(options, masks)
    try:
        with (
            atomic_path(output, suffix=".tmp.ply") as tmp,
            tempfile.TemporaryDirectory(prefix=".dvpmvs-masks-", dir=output.parent) as mask_dir,
        ):
            if masks is not None and masks.active:
                # COLMAP's StereoFusion.mask_path, in its layout, whatever layout the user's are
                # in: the stored masks, or a copy where the maps' folder cannot hold them.
                stored = masks.stored_folder(views)
                if stored is None:
                    for view in views:
                        target = Path(mask_dir) / f"{view.name}.png"
                        target.parent.mkdir(parents=True, exist_ok=True)
                        cv2.imwrite(str(target), masks.load(view).astype(np.uint8) * 255)
                colmap_options.mask_path = str(stored) if stored is not None else mask_dir
            # COLMAP writes which views support each point to <its output>.vis: beside ours.
            tmp_visibility = tmp.with_name(tmp.name + ".vis")
            try:
                reconstruction = pycolmap.stereo_fusion(
                    tmp,
                    root,
                    workspace_format="COLMAP",
                    input_type=pass_.value,
                    options=colmap_options,
                    output_type="PLY",
                )
                if not reconstruction.num_points3D():
                    log.warning(empty_cloud_message(options, stereo, masks, views))
                if tmp_visibility.is_file():
                    os.replace(tmp_visibility, visibility)
            finally:
                tmp_visibility.unlink(missing_ok=True)
    except FusionError:
        raise
    except (RuntimeError, ValueError) as exc:
        raise FusionError(f"COLMAP's stereo_fusion failed on {root}: {exc}") from None
    return int(reconstruction.num_points3D())
