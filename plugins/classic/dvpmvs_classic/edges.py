"""Edge detectors: the Roberts cross (the paper's choice) and OpenCV's Canny.

A detector is called as ``detector(ctx)`` with a :class:`dvpmvs.priors.PriorContext` and returns
an (H, W) bool edge map of the view's grey image. The edges split the image into the dispersed
regions of the depth-normal-edge aligned prior (:mod:`dvpmvs.segmentation`).
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["RobertsEdges", "CannyEdges", "make_roberts", "make_canny"]


def _smoothed(image: np.ndarray, sigma: float) -> np.ndarray:
    image = np.ascontiguousarray(image, np.float32)
    return cv2.GaussianBlur(image, (0, 0), sigma) if sigma > 0 else image


class RobertsEdges:
    """Pixels whose Roberts cross gradient magnitude (grey levels in [0, 1]) exceeds
    ``threshold``, after a Gaussian blur of ``blur_sigma`` pixels that keeps sensor noise out."""

    def __init__(self, threshold: float = 0.03, blur_sigma: float = 1.0):
        if not 0 < threshold < 1:
            raise ValueError(f"threshold must be in (0, 1), got {threshold}")
        if blur_sigma < 0:
            raise ValueError(f"blur_sigma must be >= 0, got {blur_sigma}")
        self.threshold, self.blur_sigma = float(threshold), float(blur_sigma)
        self._k1 = np.array([[1, 0], [0, -1]], np.float32)
        self._k2 = np.array([[0, 1], [-1, 0]], np.float32)

    def __call__(self, ctx) -> np.ndarray:
        image = _smoothed(ctx.image, self.blur_sigma)
        g1 = cv2.filter2D(image, -1, self._k1, anchor=(0, 0), borderType=cv2.BORDER_REPLICATE)
        g2 = cv2.filter2D(image, -1, self._k2, anchor=(0, 0), borderType=cv2.BORDER_REPLICATE)
        return np.sqrt(g1 * g1 + g2 * g2) > self.threshold


class CannyEdges:
    """OpenCV's Canny with hysteresis thresholds given for grey levels in [0, 1]."""

    def __init__(
        self, low_threshold: float = 0.1, high_threshold: float = 0.3, blur_sigma: float = 1.0
    ):
        if not 0 < low_threshold <= high_threshold < 1:
            raise ValueError(
                f"need 0 < low_threshold <= high_threshold < 1, got {low_threshold}, {high_threshold}"
            )
        self.low, self.high, self.blur_sigma = (
            float(low_threshold),
            float(high_threshold),
            float(blur_sigma),
        )

    def __call__(self, ctx) -> np.ndarray:
        image = _smoothed(ctx.image, self.blur_sigma)
        eight_bit = np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)
        return cv2.Canny(eight_bit, self.low * 255.0, self.high * 255.0, L2gradient=True) > 0


def make_roberts(params: dict) -> RobertsEdges:
    return RobertsEdges(**params)


def make_canny(params: dict) -> CannyEdges:
    return CannyEdges(**params)
