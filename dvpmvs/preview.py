"""Images people look at: coloured depth and normal maps, written as PNG atomically."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from dvpmvs.errors import DvpmvsError
from dvpmvs.maps import atomic_path

__all__ = ["colorize_depth", "colorize_normals", "colorize_cost", "colorize_labels", "write_png"]


def write_png(path: str | Path, bgr: np.ndarray) -> Path:
    """Write an 8-bit BGR (or grey) image as PNG, atomically."""
    ok, data = cv2.imencode(".png", bgr)
    if not ok:
        raise DvpmvsError(f"could not encode {path} as PNG")
    with atomic_path(path) as tmp:
        tmp.write_bytes(data.tobytes())
    return Path(path)


def colorize_depth(
    depth: np.ndarray, lo: float | None = None, hi: float | None = None
) -> np.ndarray:
    """An 8-bit BGR preview of a depth map (turbo colour map; black where depth is 0)."""
    valid = depth > 0
    if not np.any(valid):
        return np.zeros((*depth.shape, 3), np.uint8)
    lo = float(np.percentile(depth[valid], 1)) if lo is None else lo
    hi = float(np.percentile(depth[valid], 99)) if hi is None else hi
    scaled = np.clip((depth - lo) / max(hi - lo, 1e-9), 0, 1)
    bgr = cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    bgr[~valid] = 0
    return bgr


def colorize_normals(normal: np.ndarray) -> np.ndarray:
    """An 8-bit BGR preview of a camera-frame normal map (RGB = (n + 1) / 2, black if 0)."""
    rgb = np.clip((normal + 1) * 127.5, 0, 255).astype(np.uint8)
    rgb[np.all(normal == 0, axis=-1)] = 0
    return np.ascontiguousarray(rgb[..., ::-1])


def colorize_cost(cost: np.ndarray, max_cost: float = 1.0) -> np.ndarray:
    """An 8-bit grey preview of a matching-cost map: black is 0 (certain), white >= ``max_cost``."""
    return (np.clip(np.nan_to_num(cost, nan=max_cost) / max_cost, 0, 1) * 255).astype(np.uint8)


def colorize_labels(labels: np.ndarray) -> np.ndarray:
    """RGB uint8 image of a label map: a hashed colour per region, black on boundaries."""
    labels = np.asarray(labels, np.int64)
    hashed = (labels * 2654435761) & 0xFFFFFF
    rgb = np.stack([(hashed >> 16) & 255, (hashed >> 8) & 255, hashed & 255], axis=-1).astype(
        np.uint8
    )
    rgb = np.maximum(rgb, 40)
    rgb[labels == 0] = 0
    return rgb
