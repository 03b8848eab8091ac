"""One image of a workspace with its calibration, depth range and sources (COLMAP's
``mvs::Image`` with the problem's per-view fields)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from dvpmvs.image import ImageReadError, read_image, to_grey

__all__ = ["View"]


@dataclass
class View:
    """One image of the workspace with its (possibly downscaled) calibration.

    The image itself is not held: :meth:`load_rgb` / :meth:`load_grey` read it from disk each
    time, so memory grows with the views in flight, not with the scene.
    """

    image_id: int
    name: str
    path: Path
    K: np.ndarray  # (3, 3) float64, scaled to (width, height)
    R: np.ndarray  # (3, 3) float64, world -> camera rotation
    t: np.ndarray  # (3,) float64, world -> camera translation
    width: int
    height: int
    original_size: tuple[int, int]  # (width, height) of the file on disk
    depth_range: tuple[float, float] = (0.0, 0.0)
    depth_range_is_fallback: bool = False
    num_sparse_points: int = 0
    sources: tuple[str, ...] = ()
    source_scores: tuple[float, ...] = ()

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates."""
        return -self.R.T @ self.t

    @property
    def P(self) -> np.ndarray:
        """(3, 4) projection matrix K [R | t]."""
        return self.K @ np.hstack([self.R, self.t[:, None]])

    @property
    def scale(self) -> tuple[float, float]:
        """(sx, sy): this view's size over the size on disk."""
        return self.width / self.original_size[0], self.height / self.original_size[1]

    def load_rgb(self) -> np.ndarray:
        """The image as float32 RGB in [0, 1], (height, width, 3), downscaled if requested."""
        image = read_image(self.path)
        h, w = image.shape[:2]
        if (w, h) != self.original_size:
            raise ImageReadError(
                f"image {self.path} is {w}x{h} but its camera in the sparse model is "
                f"{self.original_size[0]}x{self.original_size[1]}; the workspace images do not "
                f"match the model (was image_undistorter run with another max_image_size?)"
            )
        if (w, h) != (self.width, self.height):
            image = cv2.resize(image, (self.width, self.height), interpolation=cv2.INTER_AREA)
        return image

    def load_grey(self) -> np.ndarray:
        """The image as float32 grey in [0, 1], (height, width)."""
        return to_grey(self.load_rgb())
