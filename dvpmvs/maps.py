"""Depth, normal and extra per-view maps in COLMAP's on-disk format.

COLMAP stores a map as the ASCII header ``"<width>&<height>&<channels>&"`` followed by
little-endian float32 values, channel-planar: value (row, col, c) is at ``c * W * H + row * W +
col`` (``colmap::mvs::Mat::Get``). Depth is z in the camera frame (0 = no estimate), normals are
unit vectors in the camera frame.

pycolmap's ``NormalMap.from_array`` / ``to_array`` copy a NumPy (H, W, 3) buffer as it lies in
memory, i.e. with a pixel's channels together, which COLMAP's C++ (fusion, ``to_bitmap``) then
reads as planar data: scrambled normals. We therefore hand pycolmap planar memory viewed as
(H, W, 3), and undo that on reading (a test pins this against ``NormalMap.to_bitmap``).

Depth and normal maps go through ``pycolmap.DepthMap`` / ``pycolmap.NormalMap`` so that
``colmap stereo_fusion`` and ``pycolmap.stereo_fusion`` read them unchanged. Extra maps (matching
cost, per-source visibility, region labels) use the same container format but live in folders
COLMAP never looks at (``stereo/cost_maps/`` ...). Every write is atomic: the file is written
under a temporary name in the destination folder and renamed over the target, so an interrupted
run never leaves a half-written map behind.
"""

from __future__ import annotations

import errno
import json
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pycolmap

from dvpmvs.errors import DvpmvsError
from dvpmvs.passes import Pass

__all__ = [
    "MapFormatError",
    "DiskFullError",
    "disk_full_message",
    "write_json",
    "read_json_object",
    "Pass",
    "MAP_KINDS",
    "map_path",
    "atomic_path",
    "remove_temporaries",
    "write_depth_map",
    "read_depth_map",
    "write_normal_map",
    "read_normal_map",
    "write_extra_map",
    "read_extra_map",
    "read_map_header",
]


class MapFormatError(DvpmvsError, ValueError):
    """A map file is missing, truncated, or not in COLMAP's format."""


# Folder under ``stereo/`` for each kind of map. ``depth`` and ``normal`` are COLMAP's own.
MAP_KINDS = {
    "depth": "depth_maps",
    "normal": "normal_maps",
    "cost": "cost_maps",
    "visibility": "visibility_maps",
    "labels": "label_maps",
}

_MAX_HEADER_BYTES = 64


def map_path(stereo_dir: str | Path, image_name: str, kind: str, pass_: Pass | str) -> Path:
    """Path of a map: ``stereo/<kind>_maps/<image_name>.<pass>.bin`` (COLMAP's naming)."""
    if kind not in MAP_KINDS:
        raise ValueError(f"unknown map kind {kind!r}; known kinds: {', '.join(MAP_KINDS)}")
    pass_value = Pass(pass_).value
    return Path(stereo_dir) / MAP_KINDS[kind] / f"{image_name}.{pass_value}.bin"


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _current_umask()


@contextmanager
def atomic_path(path: str | Path, suffix: str = ".tmp") -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is renamed over ``path``.

    The temporary file lives in the destination folder so that the rename is atomic (same file
    system). On an exception the temporary file is removed and ``path`` is left untouched.
    ``suffix`` ends the temporary name, for writers that pick the format from it (``.tmp.ply``).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    # mkstemp creates the file private (0600); give it the permissions a plain open() would.
    os.chmod(tmp, 0o666 & ~_UMASK)
    try:
        yield tmp
        os.replace(tmp, path)
    except OSError as exc:
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            raise DiskFullError(disk_full_message(path.parent, f"writing {path.name}")) from None
        raise
    finally:
        if tmp.exists():
            tmp.unlink()


class DiskFullError(DvpmvsError, OSError):
    """The disk (or the user's quota) holding an output folder is full; nothing was half-written."""


def write_json(path: str | Path, data: dict) -> Path:
    """Write ``data`` as indented JSON with sorted keys (stable bytes), atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n")
    return Path(path)


def path_for_manifest(path: str | Path, folder: Path | None) -> str:
    """How a run's manifest names ``path``: relative to the run's ``folder`` when inside it (a
    copied or moved run folder keeps its own files), else absolute (never relative to the folder
    the command ran in)."""
    path = Path(path).absolute()
    if folder is not None:
        try:
            return path.relative_to(Path(folder).absolute()).as_posix()
        except ValueError:
            pass
    return str(path)


def path_from_manifest(recorded: str, folder: Path) -> Path:
    """A path a manifest in ``folder`` names (:func:`path_for_manifest`)."""
    path = Path(recorded)
    return path if path.is_absolute() else folder / path


def read_json_object(path: str | Path) -> dict | None:
    """The JSON object in ``path``, or None where there is none (no file, not JSON, not an
    object): for the optional files a report shows when a run wrote them."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def disk_full_message(folder: Path, what: str, needed: int | None = None) -> str:
    """``folder``'s disk is full (or would be): what was being written, the space free (and
    needed), and what to do."""
    try:
        free = f"{shutil.disk_usage(folder).free / 2**20:,.1f} MB free"
    except OSError:
        free = "free space unknown"
    need = f"; about {needed / 2**20:,.1f} MB needed" if needed is not None else ""
    return (
        f"no space left on the disk of {folder} ({what}; {free}{need}): free some space there, or write "
        f"to another disk; nothing was half-written, and a rerun of the same command resumes"
    )


# The names atomic_path (and the map cache's links) give their temporaries: mkstemp's
# ".<target>.<8 characters><suffix>".
_TEMPORARY_NAME = re.compile(r"^\..+\.[A-Za-z0-9_]{8}(\.tmp(\.ply)?(\.vis)?|\.link)$")


def remove_temporaries(folder: str | Path, recursive: bool = True) -> list[Path]:
    """Remove the temporary files that interrupted atomic writes left in ``folder`` (and below
    it); returns them. Only safe while no other process writes there: call it holding the
    folder's writer lock (:mod:`dvpmvs.writer_lock`)."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    found = [
        p
        for p in (folder.rglob(".*") if recursive else folder.glob(".*"))
        if p.is_file() and not p.is_symlink() and _TEMPORARY_NAME.match(p.name)
    ]
    for path in found:
        path.unlink(missing_ok=True)
    return found


def read_map_header(path: str | Path) -> tuple[int, int, int, int]:
    """Return ``(width, height, channels, header_bytes)`` of a COLMAP map file, checking its size."""
    path = Path(path)
    if not path.is_file():
        raise MapFormatError(f"map file not found: {path}")
    with open(path, "rb") as f:
        head = f.read(_MAX_HEADER_BYTES)
    fields = []
    start = 0
    for _ in range(3):
        end = head.find(b"&", start)
        if end < 0:
            raise MapFormatError(f"{path}: not a COLMAP map (no 'width&height&channels&' header)")
        token = head[start:end]
        if not token.strip().isdigit():
            raise MapFormatError(
                f"{path}: not a COLMAP map (header field {token!r} is not an integer)"
            )
        fields.append(int(token))
        start = end + 1
    width, height, channels = fields
    if width <= 0 or height <= 0 or channels <= 0:
        raise MapFormatError(f"{path}: invalid map size {width}x{height}x{channels}")
    expected = start + 4 * width * height * channels
    actual = path.stat().st_size
    if actual != expected:
        raise MapFormatError(
            f"{path}: file has {actual} bytes but a {width}x{height}x{channels} float32 map needs "
            f"{expected}; the file is truncated or corrupt (delete it and rerun to recompute)"
        )
    return width, height, channels, start


def _check_channels(path: Path, channels: int, expected: int, what: str) -> None:
    if channels != expected:
        raise MapFormatError(
            f"{path}: a {what} map has {expected} channel(s), this file has {channels}"
        )


_RECOMPUTE_HINT = "the file is corrupt: delete it and rerun `dvpmvs dense` to recompute it"


def _check_finite(path: Path, array: np.ndarray) -> np.ndarray:
    if not np.isfinite(array).all():
        raise MapFormatError(f"{path}: map contains NaN or infinite values; {_RECOMPUTE_HINT}")
    return array


def _write_through_pycolmap(path: str | Path, colmap_map, shape: tuple[int, ...]) -> Path:
    """``colmap_map`` written to ``path`` (atomically), checked to hold every value: pycolmap's
    writer stops silently where the disk is full."""
    height, width = shape[:2]
    channels = shape[2] if len(shape) == 3 else 1
    expected = len(f"{width}&{height}&{channels}&") + 4 * width * height * channels
    with atomic_path(path) as tmp:
        colmap_map.write(str(tmp))
        if tmp.stat().st_size != expected:
            raise OSError(
                errno.ENOSPC, f"pycolmap wrote {tmp.stat().st_size} of {expected} bytes", str(tmp)
            )
    return Path(path)


def _read_through_pycolmap(path: str | Path, colmap_map, channels: int, what: str) -> np.ndarray:
    """Check the header and size first: pycolmap does not diagnose a truncated file."""
    path = Path(path)
    _check_channels(path, read_map_header(path)[2], channels, what)
    colmap_map.read(str(path))
    values = np.asarray(colmap_map.to_array(), dtype=np.float32)
    if values.ndim == 3:
        values = _from_planar(values)
    return _check_finite(path, values)


def _to_planar(array: np.ndarray) -> np.ndarray:
    """(H, W, C) -> the same values in COLMAP's planar memory order, viewed as (H, W, C)."""
    h, w, c = array.shape
    return np.ascontiguousarray(array.transpose(2, 0, 1)).reshape(h, w, c)


def _from_planar(array: np.ndarray) -> np.ndarray:
    """Inverse of :func:`_to_planar`."""
    h, w, c = array.shape
    return np.ascontiguousarray(np.ascontiguousarray(array).reshape(c, h, w).transpose(1, 2, 0))


def write_depth_map(
    path: str | Path, depth: np.ndarray, depth_range: tuple[float, float] | None = None
) -> Path:
    """Write an (H, W) float32 depth map through ``pycolmap.DepthMap`` (0 marks no estimate)."""
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"a depth map is (H, W); got shape {depth.shape}")
    if not np.isfinite(depth).all():
        raise ValueError(
            "depth map contains NaN or infinite values; use 0 for pixels without an estimate"
        )
    if depth_range is None:
        valid = depth[depth > 0]
        depth_range = (float(valid.min()), float(valid.max())) if valid.size else (0.0, 0.0)
    return _write_through_pycolmap(
        path,
        pycolmap.DepthMap.from_array(depth, float(depth_range[0]), float(depth_range[1])),
        depth.shape,
    )


def read_depth_map(path: str | Path) -> np.ndarray:
    """Read an (H, W) float32 depth map written by COLMAP, pycolmap or dvpmvs. Depths are z in
    the camera frame, so a negative one (like NaN) is corruption, not data: an error."""
    depth = _read_through_pycolmap(path, pycolmap.DepthMap(), 1, "depth")
    negative = int((depth < 0).sum())
    if negative:
        raise MapFormatError(
            f"{path}: {negative} negative depth(s) (depth is z in front of the camera, "
            f"0 for no estimate); {_RECOMPUTE_HINT}"
        )
    return depth


def write_normal_map(path: str | Path, normals: np.ndarray) -> Path:
    """Write an (H, W, 3) float32 normal map (camera frame) through ``pycolmap.NormalMap``."""
    normals = np.ascontiguousarray(normals, dtype=np.float32)
    if normals.ndim != 3 or normals.shape[2] != 3:
        raise ValueError(f"a normal map is (H, W, 3); got shape {normals.shape}")
    if not np.isfinite(normals).all():
        raise ValueError(
            "normal map contains NaN or infinite values; use (0, 0, 0) for pixels without an estimate"
        )
    return _write_through_pycolmap(
        path, pycolmap.NormalMap.from_array(_to_planar(normals)), normals.shape
    )


def read_normal_map(path: str | Path) -> np.ndarray:
    """Read an (H, W, 3) float32 normal map written by COLMAP, pycolmap or dvpmvs. Every normal
    is a unit vector or (0, 0, 0) (no estimate); anything else is an error."""
    normal = _read_through_pycolmap(path, pycolmap.NormalMap(), 3, "normal")
    length = np.sqrt(np.einsum("ijk,ijk->ij", normal, normal, dtype=np.float64))
    bad = int(((length != 0) & (np.abs(length - 1) > 1e-3)).sum())
    if bad:
        raise MapFormatError(
            f"{path}: {bad} normal(s) are neither unit vectors nor (0, 0, 0); {_RECOMPUTE_HINT}"
        )
    return normal


def write_extra_map(path: str | Path, array: np.ndarray) -> Path:
    """Write an (H, W) or (H, W, C) map (cost, visibility, labels) in COLMAP's container format.

    Values are stored as float32; integer labels are exact up to 2**24.
    """
    array = np.asarray(array)
    if array.ndim == 2:
        array = array[:, :, None]
    if array.ndim != 3 or array.shape[2] < 1:
        raise ValueError(f"an extra map is (H, W) or (H, W, C); got shape {array.shape}")
    if np.issubdtype(array.dtype, np.integer) and array.size and np.abs(array).max() > 2**24:
        raise ValueError("integer map values above 2**24 cannot be stored exactly as float32")
    values = array.astype(np.float32)
    if not np.isfinite(values).all():
        raise ValueError("extra map contains NaN or infinite values")
    height, width, channels = values.shape
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(f"{width}&{height}&{channels}&".encode("ascii"))
            f.write(np.ascontiguousarray(values.transpose(2, 0, 1), dtype="<f4").tobytes())
            f.flush()
            os.fsync(f.fileno())
    return Path(path)


def read_extra_map(path: str | Path) -> np.ndarray:
    """Read a map written by :func:`write_extra_map`: (H, W) for one channel, else (H, W, C)."""
    path = Path(path)
    width, height, channels, offset = read_map_header(path)
    planar = np.fromfile(path, dtype="<f4", offset=offset).reshape(channels, height, width)
    values = _check_finite(path, np.ascontiguousarray(planar.transpose(1, 2, 0), dtype=np.float32))
    return values[:, :, 0] if channels == 1 else values
