"""Image loading and small image operations backed by the private kernels in ``_image.pyx``."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from dvpmvs import _image
from dvpmvs.errors import DvpmvsError

__all__ = ["ImageReadError", "read_image", "to_grey", "sample_bilinear", "image_gradient"]


class ImageReadError(DvpmvsError, OSError):
    """An image file is missing or cannot be decoded."""


def read_image(path: str | Path) -> np.ndarray:
    """Read an image as float32 RGB in [0, 1], shape (H, W, 3).

    Grey images are replicated to three channels; 16-bit images are scaled by 65535.
    """
    path = Path(path)
    if not path.is_file():
        raise ImageReadError(f"image file not found: {path}")
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None or raw.size == 0:
        raise ImageReadError(
            f"cannot decode image {path}: the file is corrupt or not an image format OpenCV reads"
        )
    scale = 65535.0 if raw.dtype == np.uint16 else 255.0 if raw.dtype == np.uint8 else 1.0
    image = raw.astype(np.float32) / np.float32(scale)
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    elif image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    else:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    return np.ascontiguousarray(image)


def to_grey(rgb: np.ndarray) -> np.ndarray:
    """Luma (ITU-R BT.601) of a float32 RGB image, shape (H, W), float32."""
    return np.ascontiguousarray(cv2.cvtColor(np.asarray(rgb, np.float32), cv2.COLOR_RGB2GRAY))


def sample_bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray, fill: float = np.nan) -> np.ndarray:
    """Bilinearly sample a single-channel image at continuous positions.

    Integer coordinates are pixel centres: ``sample_bilinear(img, 2.0, 3.0) == img[3, 2]``.
    Positions outside ``[0, W-1] x [0, H-1]`` (and NaN positions) give ``fill``.
    ``x`` and ``y`` broadcast against each other; the result has their broadcast shape.
    """
    image = np.ascontiguousarray(image, dtype=np.float32)
    if image.ndim != 2:
        raise ValueError(f"sample_bilinear expects a single-channel (H, W) image, got shape {image.shape}")
    x, y = np.broadcast_arrays(np.asarray(x, np.float32), np.asarray(y, np.float32))
    shape = x.shape
    xs = np.ascontiguousarray(x.reshape(1, -1))
    ys = np.ascontiguousarray(y.reshape(1, -1))
    out = np.empty_like(xs)
    _image.sample_bilinear(image, xs, ys, out, float(fill))
    return out.reshape(shape)


def image_gradient(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference gradient (d/dx, d/dy) of a single-channel image, one-sided at borders."""
    image = np.ascontiguousarray(image, dtype=np.float32)
    if image.ndim != 2:
        raise ValueError(f"image_gradient expects a single-channel (H, W) image, got shape {image.shape}")
    gx = np.empty_like(image)
    gy = np.empty_like(image)
    _image.central_gradient(image, gx, gy)
    return gx, gy
