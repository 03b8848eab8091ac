"""Weight-free normal priors: ``from_depth`` (local planes of the depth prior) and ``file``.

A provider is called as ``provider(ctx, depth)`` (``depth``: the view's aligned depth prior or
None) and returns (H, W, 3) unit normals in the camera frame, facing the camera.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from dvpmvs.priors import PriorError, face_camera, fit_prior_to_view, read_prior_array
from dvpmvs_classic.depth_priors import find_prior_file, resolve_folder

__all__ = ["normals_from_depth", "FromDepthNormals", "FileNormals", "make_from_depth", "make_file"]


def normals_from_depth(depth: np.ndarray, K: np.ndarray, sigma: float = 1.5) -> np.ndarray:
    """Camera-frame normals of a depth map: the cross product of the back-projected points'
    derivatives along rows and columns (Sobel on a Gaussian-smoothed depth)."""
    depth = np.ascontiguousarray(depth, np.float32)
    if sigma > 0:
        depth = cv2.GaussianBlur(depth, (0, 0), sigma)
    h, w = depth.shape
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float32)
    Ki = np.linalg.inv(K).astype(np.float32)
    X = np.stack(
        [
            (Ki[0, 0] * cols + Ki[0, 1] * rows + Ki[0, 2]) * depth,
            (Ki[1, 1] * rows + Ki[1, 2]) * depth,
            depth,
        ],
        axis=2,
    )
    dx = cv2.Sobel(X, cv2.CV_32F, 1, 0, ksize=3)
    dy = cv2.Sobel(X, cv2.CV_32F, 0, 1, ksize=3)
    normal = np.cross(dx, dy)
    norm = np.linalg.norm(normal, axis=2, keepdims=True)
    normal = np.where(
        norm > 1e-12, normal / np.maximum(norm, 1e-12), np.array([0, 0, -1], np.float32)
    )
    return face_camera(normal.astype(np.float32), K)


class FromDepthNormals:
    """Normals of the depth prior's local planes (``sigma``: smoothing in pixels)."""

    derived_from_depth = True  # segmentation: no second, independent view of the depth's steps

    def __init__(self, sigma: float = 1.5):
        if sigma < 0:
            raise ValueError(f"sigma must be >= 0, got {sigma}")
        self.sigma = float(sigma)

    def __call__(self, ctx, depth) -> np.ndarray:
        if depth is None:
            raise PriorError(
                "the from_depth normal prior needs a depth prior (depth_prior=none was given)"
            )
        return normals_from_depth(depth, ctx.K, self.sigma)


class FileNormals:
    """Per-view (H, W, 3) camera-frame normals from ``path`` (relative to the workspace);
    ``flip_y_z``: for networks whose camera looks along -z with y up (OpenGL convention). A prior
    of the image at another size is resized; another aspect ratio is an error unless ``resize``."""

    def __init__(self, path: str | None = None, flip_y_z: bool = False, resize: bool = False):
        for key, value in (("flip_y_z", flip_y_z), ("resize", resize)):
            if not isinstance(value, bool):
                raise ValueError(f"{key} must be true or false, got {value!r}")
        self.path, self.flip_y_z, self.resize = path, flip_y_z, resize

    def input_files(self, name: str, root=None) -> list[Path]:
        """The prior file of view ``name`` (its content joins the maps' provenance)."""
        return [find_prior_file(resolve_folder(self.path, root, "normal_prior"), name)]

    def __call__(self, ctx, depth) -> np.ndarray:
        folder = resolve_folder(self.path, ctx.root, "normal_prior")
        file = find_prior_file(folder, ctx.name)
        array = read_prior_array(file)
        if array.ndim != 3 or array.shape[2] != 3:
            raise PriorError(f"{file}: a normal prior is (H, W, 3), got shape {array.shape}")
        if not np.isfinite(array).all():
            raise PriorError(f"{file}: {int((~np.isfinite(array)).sum())} NaN or infinite value(s)")
        array = fit_prior_to_view(array, ctx.shape, file, self.resize)
        if self.flip_y_z:
            array = array * np.array([1, -1, -1], np.float32)
        norm = np.linalg.norm(array, axis=2, keepdims=True)
        array = array / np.maximum(norm, 1e-6)
        return face_camera(array.astype(np.float32), ctx.K)


def make_from_depth(params: dict) -> FromDepthNormals:
    return FromDepthNormals(**params)


def make_file(params: dict) -> FileNormals:
    return FileNormals(**params)
