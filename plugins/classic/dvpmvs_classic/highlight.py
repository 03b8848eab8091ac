"""Highlight correctors: per view, a corrected grey image to match and a highlight mask.

- ``none``: the images as they are, no mask (highlight perception off).
- ``multiview``: no single-image detection: the masks come from the views' disagreement alone,
  once the photometric pass has given every view a depth map (``patch_match.highlight_multiview``,
  :func:`dvpmvs.highlight.multiview_highlight`); the photometric pass matches the images as they are.
- ``dichromatic``: weight-free specular removal under the dichromatic reflection model, after
  Shen and Cai, "Simple and efficient method for specularity removal in an image", Applied
  Optics 48(14), 2009. A pixel's colour is diffuse (the surface's colour) plus specular (the
  light's colour, white for a white-balanced image). The specular part is estimated per pixel
  from the smallest channel above the image's threshold ``mean(I_min) + eta * std(I_min)``;
  removing it from every channel gives the modified specular-free image. The mask keeps the
  pixels with a specular part of at least ``min_specular`` that are also brighter than their
  neighbourhood's median by ``min_contrast`` (a highlight is a local lobe; a white wall, whose
  smallest channel is high everywhere, is not one).
- ``threshold``: a plain detector for comparison: saturated (brightest channel at least
  ``saturation``), colourless (chroma at most ``max_chroma``) and locally brightest (as above)
  pixels; the corrected image fills them from their surroundings (OpenCV's Telea inpainting).
- ``file``: masks (and optionally corrected images) made elsewhere, for example by a learned
  detector run outside dvpmvs: ``path`` holds ``<image name>`` or ``<image stem>`` as an 8-bit
  image (> 127: highlight) or ``.npy`` / ``.bin`` (> 0.5); ``corrected``, if set, a folder of
  corrected images named as the views' images (else the images are matched as they are).

Both clean the mask (an opening removes specks) and grow it by ``dilate`` pixels: a highlight's
fading rim breaks photo-consistency as its core does.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

__all__ = [
    "NoHighlight",
    "DichromaticHighlight",
    "ThresholdHighlight",
    "FileHighlight",
    "make_none",
    "make_multiview",
    "make_dichromatic",
    "make_threshold",
    "make_file",
    "local_contrast",
    "clean_mask",
]


class NoHighlight:
    def __call__(self, ctx) -> tuple[np.ndarray, np.ndarray]:
        return ctx.image, np.zeros(ctx.shape, bool)


def make_none(params: dict) -> NoHighlight:
    if params:
        raise ValueError(
            f"the 'none' highlight corrector takes no parameters, got {sorted(params)}"
        )
    return NoHighlight()


def make_multiview(params: dict) -> NoHighlight:
    if params:
        raise ValueError(
            f"the 'multiview' highlight corrector takes no parameters, got {sorted(params)}"
        )
    return NoHighlight()


def local_contrast(grey: np.ndarray, window: int) -> np.ndarray:
    """How much brighter each pixel is than the median of the ``window`` x ``window``
    neighbourhood around it (intensity in [0, 1]; the median at 1/255 steps)."""
    size = window if window % 2 else window + 1
    grey8 = np.clip(np.round(grey * 255), 0, 255).astype(np.uint8)
    return grey - cv2.medianBlur(grey8, size).astype(np.float32) / 255.0


def clean_mask(mask: np.ndarray, dilate: int) -> np.ndarray:
    """The mask without specks (a 3x3 opening) grown by ``dilate`` pixels."""
    mask = mask.astype(np.uint8)
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    if dilate > 0:
        mask = cv2.dilate(
            mask, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * dilate + 1, 2 * dilate + 1))
        )
    return mask.astype(bool)


def _check_params(name: str, params: dict, defaults: dict) -> dict:
    unknown = sorted(set(params) - set(defaults))
    if unknown:
        raise ValueError(
            f"the '{name}' highlight corrector has no parameter(s) {unknown}; "
            f"it takes {sorted(defaults)}"
        )
    values = {**defaults, **params}
    for key, value in values.items():
        if key == "window":
            if int(value) < 3:
                raise ValueError(f"highlight.window must be >= 3 pixels, got {value}")
        elif key == "dilate":
            if int(value) < 0:
                raise ValueError(f"highlight.dilate must be >= 0 pixels, got {value}")
        elif not 0 <= float(value) <= (10 if key == "eta" else 1):
            raise ValueError(f"highlight.{key} is out of range: {value}")
    return values


class DichromaticHighlight:
    """See the module docstring (``dichromatic``)."""

    def __init__(
        self,
        eta: float = 0.5,
        min_specular: float = 0.06,
        min_contrast: float = 0.08,
        window: int = 31,
        dilate: int = 2,
    ):
        self.eta, self.min_specular, self.min_contrast = (
            float(eta),
            float(min_specular),
            float(min_contrast),
        )
        self.window, self.dilate = int(window), int(dilate)

    def specular(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W) the specular part of every pixel: the smallest channel above the threshold
        ``mean(I_min) + eta * std(I_min)`` (Shen and Cai's offset)."""
        smallest = rgb.min(axis=2)
        threshold = float(smallest.mean() + self.eta * smallest.std())
        return np.maximum(smallest - threshold, 0).astype(np.float32)

    def __call__(self, ctx) -> tuple[np.ndarray, np.ndarray]:
        rgb = np.asarray(ctx.rgb(), np.float32)
        grey = np.asarray(ctx.image, np.float32)
        specular = self.specular(rgb)
        mask = clean_mask(
            (specular >= self.min_specular)
            & (local_contrast(grey, self.window) >= self.min_contrast),
            self.dilate,
        )
        # The specular part is removed from every channel alike, so from the grey image too;
        # only in the mask, so that the rest of the image is matched as it is.
        corrected = np.where(mask, np.clip(grey - specular, 0, 1), grey).astype(np.float32)
        return corrected, mask


class ThresholdHighlight:
    """See the module docstring (``threshold``)."""

    def __init__(
        self,
        saturation: float = 0.92,
        max_chroma: float = 0.2,
        min_contrast: float = 0.08,
        window: int = 31,
        dilate: int = 2,
    ):
        self.saturation, self.max_chroma = float(saturation), float(max_chroma)
        self.min_contrast, self.window, self.dilate = float(min_contrast), int(window), int(dilate)

    def __call__(self, ctx) -> tuple[np.ndarray, np.ndarray]:
        rgb = np.asarray(ctx.rgb(), np.float32)
        grey = np.asarray(ctx.image, np.float32)
        brightest = rgb.max(axis=2)
        chroma = (brightest - rgb.min(axis=2)) / np.maximum(brightest, 1e-6)
        mask = clean_mask(
            (brightest >= self.saturation)
            & (chroma <= self.max_chroma)
            & (local_contrast(grey, self.window) >= self.min_contrast),
            self.dilate,
        )
        if not mask.any():
            return grey, mask
        grey8 = np.clip(np.round(grey * 255), 0, 255).astype(np.uint8)
        filled = (
            cv2.inpaint(grey8, mask.astype(np.uint8), 3, cv2.INPAINT_TELEA).astype(np.float32)
            / 255.0
        )
        return np.where(mask, filled, grey).astype(np.float32), mask


def make_dichromatic(params: dict) -> DichromaticHighlight:
    return DichromaticHighlight(
        **_check_params(
            "dichromatic",
            params,
            {"eta": 0.5, "min_specular": 0.06, "min_contrast": 0.08, "window": 31, "dilate": 2},
        )
    )


def make_threshold(params: dict) -> ThresholdHighlight:
    return ThresholdHighlight(
        **_check_params(
            "threshold",
            params,
            {
                "saturation": 0.92,
                "max_chroma": 0.2,
                "min_contrast": 0.08,
                "window": 31,
                "dilate": 2,
            },
        )
    )


_MASK_SUFFIXES = ("", ".png", ".jpg", ".npy", ".bin")


class FileHighlight:
    """See the module docstring (``file``)."""

    def __init__(self, path: str | None = None, corrected: str | None = None):
        self.path, self.corrected = path, corrected

    def _mask_file(self, name: str, root) -> Path:
        from dvpmvs_classic.depth_priors import find_prior_file, resolve_folder

        return find_prior_file(
            resolve_folder(self.path, root, "highlight"), name, _MASK_SUFFIXES, "highlight mask"
        )

    def _corrected_file(self, name: str, root) -> Path:
        from dvpmvs.priors import PriorError
        from dvpmvs_classic.depth_priors import resolve_folder

        folder = resolve_folder(self.corrected, root, "highlight.corrected")
        if not (folder / name).is_file():
            raise PriorError(f"no corrected image for image {name} in {folder}")
        return folder / name

    def input_files(self, name: str, root=None) -> list[Path]:
        """The view's mask (and corrected image): their contents join the maps' provenance."""
        files = [self._mask_file(name, root)]
        if self.corrected not in (None, ""):
            files.append(self._corrected_file(name, root))
        return files

    def __call__(self, ctx) -> tuple[np.ndarray, np.ndarray]:
        from dvpmvs.image import read_image, to_grey
        from dvpmvs.priors import PriorError, fit_prior_to_view, read_prior_array

        file = self._mask_file(ctx.name, ctx.root)
        if file.suffix.lower() in (".npy", ".bin"):
            mask = read_prior_array(file)
            if mask.ndim == 3 and mask.shape[2] == 1:
                mask = mask[..., 0]
            if mask.ndim != 2 or not np.isfinite(mask).all():
                raise PriorError(
                    f"{file}: a highlight mask is a finite (H, W) array, got shape {mask.shape}"
                )
            mask = mask > 0.5
        else:
            image = cv2.imread(str(file), cv2.IMREAD_GRAYSCALE)
            if image is None:
                raise PriorError(f"{file}: not a readable image")
            mask = image > 127
        mask = fit_prior_to_view(mask.astype(np.float32), ctx.shape, file) > 0.5
        grey = np.asarray(ctx.image, np.float32)
        if self.corrected in (None, ""):
            return grey, mask
        path = self._corrected_file(ctx.name, ctx.root)
        corrected = fit_prior_to_view(to_grey(read_image(path)), ctx.shape, path)
        return np.clip(corrected, 0, 1).astype(np.float32), mask


def make_file(params: dict) -> FileHighlight:
    unknown = sorted(set(params) - {"path", "corrected"})
    if unknown:
        raise ValueError(
            f"the 'file' highlight corrector has no parameter(s) {unknown}; it takes path, corrected"
        )
    return FileHighlight(**params)
