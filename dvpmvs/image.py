"""Image loading and small image operations backed by the private kernels in ``_image.pyx``."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

import dvpmvs._image as _image
from dvpmvs._kernel_sources import require_current
from dvpmvs.errors import DvpmvsError

require_current(_image)

__all__ = [
    "ImageReadError",
    "check_image_file",
    "read_image",
    "to_grey",
    "sample_bilinear",
    "image_gradient",
    "noise_sigma",
    "smooth_untextured",
]


class ImageReadError(DvpmvsError, OSError):
    """An image file is missing or cannot be decoded."""


_JPEG_STANDALONE = frozenset({0x01, *range(0xD0, 0xD8)})  # TEM, RST0-7: markers without a length
_JPEG_FRAMES = frozenset(
    {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
)


def _jpeg_size(path: Path, data: bytes) -> tuple[int, int]:
    """(width, height) of a complete JPEG: its segments walked up to the first scan, then the
    end-of-image marker searched after it (entropy-coded data never holds 0xFF 0xD9, so only a
    complete file has one there; data appended after it, as by motion photos, is allowed)."""

    def truncated(where: str) -> ImageReadError:
        return ImageReadError(
            f"image {path} is truncated ({len(data)} bytes, {where}): the file was cut off "
            f"while written or copied; copy it again"
        )

    offset, size = 2, None
    while True:
        while (
            offset < len(data)
            and data[offset] == 0xFF
            and offset + 1 < len(data)
            and data[offset + 1] == 0xFF
        ):
            offset += 1  # fill bytes
        if offset + 4 > len(data):
            raise truncated("it ends inside its headers")
        if data[offset] != 0xFF:
            raise ImageReadError(
                f"image {path} is corrupt: no JPEG marker at byte {offset}; replace the file"
            )
        marker = data[offset + 1]
        if marker in _JPEG_STANDALONE:
            offset += 2
            continue
        length = int.from_bytes(data[offset + 2 : offset + 4], "big")
        if marker in _JPEG_FRAMES and offset + 9 <= len(data):
            height = int.from_bytes(data[offset + 5 : offset + 7], "big")
            width = int.from_bytes(data[offset + 7 : offset + 9], "big")
            size = (width, height)
        if marker == 0xDA:  # start of scan
            if data.find(b"\xff\xd9", offset + 2 + length) < 0:
                raise truncated("no end-of-image marker after its image data")
            if size is None:
                raise ImageReadError(
                    f"image {path} is corrupt: a JPEG scan without a frame header; replace the file"
                )
            return size
        offset += 2 + length


def check_image_file(path: str | Path) -> tuple[int, int]:
    """Check that an image file is complete and return its (width, height): from the header for
    JPEG, PNG, BMP and TIFF, by decoding it for other formats. A truncated JPEG is an error
    (libjpeg decodes one with a warning and grey rows); a PNG must end with its IEND chunk."""
    path = Path(path)
    if not path.is_file():
        raise ImageReadError(f"image file not found: {path}")
    data = path.read_bytes()
    size = _check_image_bytes(path, data)
    if size is None:
        size = _bmp_size(data) or _tiff_size(data)
    if size is None:
        raw = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
        if raw is None or raw.size == 0:
            raise ImageReadError(
                f"cannot decode image {path}: the file is corrupt or not an image format OpenCV "
                f"reads"
            )
        size = (int(raw.shape[1]), int(raw.shape[0]))
    return size


def _bmp_size(data: bytes) -> tuple[int, int] | None:
    """A BMP's (width, height) from its info header (height negative: stored top-down)."""
    if data[:2] != b"BM" or len(data) < 26:
        return None
    if int.from_bytes(data[14:18], "little") == 12:  # the OS/2 core header: 16-bit sizes
        return int.from_bytes(data[18:20], "little"), int.from_bytes(data[20:22], "little")
    width = int.from_bytes(data[18:22], "little", signed=True)
    height = int.from_bytes(data[22:26], "little", signed=True)
    return abs(width), abs(height)


def _tiff_size(data: bytes) -> tuple[int, int] | None:
    """A classic TIFF's first image's (width, height) from its first directory (ImageWidth,
    ImageLength); None for anything else (BigTIFF is decoded instead)."""
    order = {b"II": "little", b"MM": "big"}.get(data[:2])
    if order is None or len(data) < 8 or int.from_bytes(data[2:4], order) != 42:
        return None
    offset = int.from_bytes(data[4:8], order)
    if offset + 2 > len(data):
        return None
    count = int.from_bytes(data[offset : offset + 2], order)
    tags = {}
    for i in range(count):
        entry = data[offset + 2 + 12 * i : offset + 14 + 12 * i]
        if len(entry) < 12:
            return None
        tag, kind = int.from_bytes(entry[0:2], order), int.from_bytes(entry[2:4], order)
        if tag in (256, 257):
            tags[tag] = (
                int.from_bytes(entry[8:10], order)
                if kind == 3
                else int.from_bytes(entry[8:12], order)
            )
    return (tags[256], tags[257]) if 256 in tags and 257 in tags else None


def _check_image_bytes(path: Path, data: bytes) -> tuple[int, int] | None:
    if data[:3] == b"\xff\xd8\xff":
        return _jpeg_size(path, data)
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        if len(data) < 33 or data.rfind(b"IEND", max(0, len(data) - 64)) < 0:
            raise ImageReadError(
                f"image {path} is truncated ({len(data)} bytes, no IEND chunk at its end): the "
                f"file was cut off while written or copied; copy it again"
            )
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    return None


def read_image(path: str | Path) -> np.ndarray:
    """Read an image as float32 RGB in [0, 1], shape (H, W, 3).

    Grey images are replicated to three channels; 16-bit images are scaled by 65535. A truncated
    file is an error (:func:`check_image_file`), not an image with grey rows.
    """
    path = Path(path)
    if not path.is_file():
        raise ImageReadError(f"image file not found: {path}")
    # One read: the bytes checked are the bytes decoded (imdecode is imread's decoder).
    data = path.read_bytes()
    _check_image_bytes(path, data)
    raw = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED) if data else None
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


def sample_bilinear(
    image: np.ndarray, x: np.ndarray, y: np.ndarray, fill: float = np.nan
) -> np.ndarray:
    """Bilinearly sample a single-channel image at continuous positions.

    Integer coordinates are pixel centres: ``sample_bilinear(img, 2.0, 3.0) == img[3, 2]``.
    Positions outside ``[0, W-1] x [0, H-1]`` (and NaN positions) give ``fill``.
    ``x`` and ``y`` broadcast against each other; the result has their broadcast shape.
    """
    image = np.ascontiguousarray(image, dtype=np.float32)
    if image.ndim != 2:
        raise ValueError(
            f"sample_bilinear expects a single-channel (H, W) image, got shape {image.shape}"
        )
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
        raise ValueError(
            f"image_gradient expects a single-channel (H, W) image, got shape {image.shape}"
        )
    gx = np.empty_like(image)
    gy = np.empty_like(image)
    _image.central_gradient(image, gx, gy)
    return gx, gy


def noise_sigma(image: np.ndarray) -> float:
    """Standard deviation of a grey image's pixel noise, estimated from the image itself.

    The second-difference kernel [[1, -2, 1], [-2, 4, -2], [1, -2, 1]] cancels constant and
    linear intensity and multiplies white noise's deviation by 6; the median of its absolute
    response (x 1.4826, a Gaussian's median-to-deviation ratio) ignores the minority of pixels
    where texture or edges answer instead of noise.
    """
    image = np.asarray(image, np.float32)
    if image.ndim != 2:
        raise ValueError(
            f"noise_sigma expects a single-channel (H, W) image, got shape {image.shape}"
        )
    if image.shape[0] < 3 or image.shape[1] < 3:
        return 0.0
    kernel = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    response = cv2.filter2D(image, -1, kernel)[1:-1, 1:-1]
    return float(1.4826 * np.median(np.abs(response)) / 6.0)


def smooth_untextured(image: np.ndarray, sigma: float, noise_scale: float = 1.0) -> np.ndarray:
    """Smooth a grey image where it has no texture above its noise, keep it elsewhere (a Lee filter).

    Each pixel becomes its Gaussian mean (``sigma``, pixels) plus ``k`` times its deviation from
    that mean, ``k = max(0, 1 - (noise_scale * noise)^2 / local variance)``, the local variance
    taken over a Gaussian window of 2 pixels. Where the image is flat but for sensor noise (walls,
    sky), ``k`` is 0 and the noise is averaged away; where texture dominates, ``k`` is near 1 and
    the detail that sub-pixel matching needs stays. ``noise`` is the image's own
    :func:`noise_sigma`.
    ``sigma`` 0 returns the image unchanged.
    """
    image = np.asarray(image, np.float32)
    if image.ndim != 2:
        raise ValueError(
            f"smooth_untextured expects a single-channel (H, W) image, got shape {image.shape}"
        )
    if sigma < 0 or noise_scale < 0:
        raise ValueError(f"sigma and noise_scale must be >= 0, got {sigma} and {noise_scale}")
    if sigma == 0:
        return image
    noise = noise_sigma(image)

    def blur(values, s):
        return cv2.GaussianBlur(values, (0, 0), s, borderType=cv2.BORDER_REFLECT)

    mean = blur(image, sigma)
    local_mean = blur(image, 2.0)
    local_var = blur(image * image, 2.0) - local_mean * local_mean
    keep = np.clip(1.0 - (noise_scale * noise) ** 2 / np.maximum(local_var, 1e-12), 0.0, 1.0)
    return np.ascontiguousarray(mean + keep * (image - mean), dtype=np.float32)
