"""Camera geometry shared by the stages: back-projection, planes fitted to depth, intrinsics
of a resized image. The aligned prior (:mod:`dvpmvs.segmentation`) and the estimator
(:mod:`dvpmvs.patchmatch`) both build on it."""

from __future__ import annotations

import numpy as np

__all__ = ["back_project", "RansacPlanes", "least_squares_plane", "scale_intrinsics"]


def scale_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """K of an image resized by (sx, sy) with pixel areas aligned (what cv2.resize does), in
    the dense convention where pixel index i is the image point i: x' = sx x + (sx - 1) / 2."""
    S = np.array([[sx, 0, 0.5 * (sx - 1)], [0, sy, 0.5 * (sy - 1)], [0, 0, 1]])
    return S @ np.asarray(K, np.float64)


def back_project(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Camera-frame points (H, W, 3) of a depth map (float64): depth times the pixel's ray
    K^-1 (col, row, 1), whose z is 1."""
    h, w = depth.shape
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    Ki = np.linalg.inv(K)
    rays = np.stack(
        [
            Ki[0, 0] * cols + Ki[0, 1] * rows + Ki[0, 2],
            Ki[1, 1] * rows + Ki[1, 2],
            np.ones_like(cols),
        ],
        axis=2,
    )
    return rays * depth[..., None]


class RansacPlanes:
    """RANSAC planes of pixel sets of one view: ``points`` (H*W, 3) camera-frame points, ``valid``
    the pixels that may support a plane; a point is an inlier within ``distance_unit`` times its
    depth of the plane. Deterministic for a given ``seed`` and call order."""

    def __init__(
        self,
        points: np.ndarray,
        valid: np.ndarray,
        distance_unit: float,
        iterations: int,
        max_points: int,
        seed: int,
    ):
        self.points = points.reshape(-1, 3)
        self.z = self.points[:, 2]
        self.valid = valid.ravel()
        self.distance_unit = distance_unit
        self.iterations = iterations
        self.max_points = max_points
        self.rng = np.random.default_rng(seed)

    def distance(self, plane: np.ndarray, index: np.ndarray) -> np.ndarray:
        """Relative point-to-plane distance in distance units."""
        p = self.points[index]
        return np.abs(p @ plane[:3] + plane[3]) / (self.z[index] * self.distance_unit)

    def fit(self, index: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
        """(plane [n, d] facing the camera, inlier ratio, inlier mask over the valid ones of
        ``index``) of the pixels ``index``."""
        index = index[self.valid[index]]
        if index.size < 3:
            return np.full(4, np.nan), 0.0, np.zeros(index.size, bool)
        sample = (
            index
            if index.size <= self.max_points
            else self.rng.choice(index, self.max_points, replace=False)
        )
        p = self.points[sample]
        triples = self.rng.integers(0, sample.size, size=(self.iterations, 3))
        a, b, c = p[triples[:, 0]], p[triples[:, 1]], p[triples[:, 2]]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n, axis=1)
        ok = norm > 1e-12
        if not ok.any():
            return np.full(4, np.nan), 0.0, np.zeros(index.size, bool)
        n = n[ok] / norm[ok, None]
        d = -(n * a[ok]).sum(axis=1)
        dist = np.abs(p @ n.T + d) / (p[:, 2:3] * self.distance_unit)
        best = int(np.argmax((dist < 1.0).sum(axis=0)))
        inliers = dist[:, best] < 1.0
        plane = (
            least_squares_plane(p[inliers]) if inliers.sum() >= 3 else np.append(n[best], d[best])
        )
        full = self.distance(plane, index) < 1.0
        if plane[:3] @ np.array([0, 0, 1.0]) > 0:  # face the camera
            plane = -plane
        return plane, float(full.mean()), full


def least_squares_plane(points: np.ndarray) -> np.ndarray:
    """The plane [n, d] (n . p + d = 0, |n| = 1) through ``points`` (N, 3) by least squares."""
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre, full_matrices=False)
    n = vt[2]
    return np.append(n, -n @ centre)
