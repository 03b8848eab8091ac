"""Starting planes from the sparse points: the view's sparse points triangulated in the image
(Delaunay) and each pixel given the plane of the triangle it falls in, or outside the points'
hull the plane of the nearest triangle, extrapolated.

Why: random hypotheses drawn in the view's depth range rarely land on surfaces that are near the
camera and seen at a slant, such as the ground in front of it: drawn evenly in depth over a
street view's range of 2.1-27.2 m, 6 % of the draws fall between 2.6 and 4.1 m, where the bottom
fifth of the image sees the ground, and within 1 % of a pixel's true depth a fraction of a
percent, while the sparse points lie on that ground and their triangles give its plane. The
estimator scores a pixel's seeded plane beside its random hypothesis at the coarsest
level and keeps the better (``PatchMatchOptions.sparse_seed``); wrong planes (a triangle that
spans a depth edge) lose to the random one or are corrected by propagation, as any hypothesis.
OpenMVS starts its depth maps the same way (the sparse points' Delaunay triangulation in the image,
the image corners extrapolated from the nearest faces' planes); COLMAP and ACMM start from random
hypotheses alone.
"""

from __future__ import annotations

import numpy as np

__all__ = ["sparse_planes"]

# A triangle whose plane is seen within this angle of edge-on gives depths that change fast and
# a normal matching cannot use; its pixels keep their random hypothesis.
MAX_VIEWING_ANGLE_DEGREES = 85.0


def sparse_planes(
    points: np.ndarray,
    K: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    size: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel of a ``size`` = (width, height) image with calibration ``K`` and pose ``R``,
    ``t`` (world -> camera), the depth and camera-frame unit normal of the plane through the
    sparse ``points`` ((N, 3) world) triangulated in the image, facing the camera. Pixels
    without a plane (fewer than 3 points in front of the camera, triangles seen nearly edge-on)
    have depth 0 and normal 0. Depths are not bounded by the range of the random draws: the
    plane extrapolated below the points' hull reaches nearer than the sparse points' depths do,
    where the ground runs toward the camera. Returns ((H, W) float32, (H, W, 3) float32)."""
    w, h = size
    depth = np.zeros((h, w), np.float32)
    normal = np.zeros((h, w, 3), np.float32)
    X = np.asarray(points, np.float64).reshape(-1, 3) @ np.asarray(R, np.float64).T + np.asarray(
        t, np.float64
    )
    X = X[X[:, 2] > 0]
    if len(X) < 3:
        return depth, normal
    uv = X @ np.asarray(K, np.float64).T
    uv = uv[:, :2] / uv[:, 2:]
    # Points seen at the same spot (within a hundredth of a pixel) make qhull's triangles degenerate.
    unique = np.sort(np.unique(np.round(uv * 100).astype(np.int64), axis=0, return_index=True)[1])
    X, uv = X[unique], uv[unique]
    if len(X) < 3:
        return depth, normal
    from scipy.spatial import Delaunay, QhullError, cKDTree  # here: see planar_prior.planar_prior

    try:
        triangulation = Delaunay(uv)
    except QhullError:  # all points on one line: no triangle
        return depth, normal
    corners = X[triangulation.simplices]  # (T, 3, 3)
    n = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    length = np.linalg.norm(n, axis=1)
    usable = length > 0
    n[usable] /= length[usable, None]
    # Facing the camera: n . X < 0 for the triangle's points.
    n[np.einsum("ij,ij->i", n, corners[:, 0]) > 0] *= -1
    offset = np.einsum("ij,ij->i", n, corners[:, 0])  # the plane n . X = offset (< 0)

    rows, cols = np.mgrid[0:h, 0:w]
    pixels = np.stack([cols.ravel(), rows.ravel()], axis=1).astype(np.float64)
    triangle = triangulation.find_simplex(pixels)
    outside = triangle < 0
    if outside.any():
        centroids = triangulation.points[triangulation.simplices].mean(axis=1)
        triangle[outside] = cKDTree(centroids).query(pixels[outside])[1]
    rays = np.concatenate([pixels, np.ones((len(pixels), 1))], axis=1) @ np.linalg.inv(K).T  # z = 1
    nt = n[triangle]
    facing = np.einsum("ij,ij->i", nt, rays)
    plane_depth = np.divide(offset[triangle], facing, out=np.zeros(len(pixels)), where=facing < 0)
    cos_view = -facing / np.linalg.norm(rays, axis=1)
    ok = (
        usable[triangle]
        & (cos_view > np.cos(np.deg2rad(MAX_VIEWING_ANGLE_DEGREES)))
        & (plane_depth >= 0)
    )
    depth.ravel()[ok] = plane_depth[ok]
    normal.reshape(-1, 3)[ok] = nt[ok]
    return depth, normal
