"""Planar prior from reliable pixels (the idea of ACMMP, Xu and Tao 2022).

Textureless surfaces give every hypothesis the same photometric cost, so PatchMatch alone leaves
them empty or noisy. Their outlines, though, are usually textured and well estimated. The prior
takes the most reliable pixel of every ``grid`` x ``grid`` cell (lowest cost, under
``max_cost``), triangulates these support pixels in the image (Delaunay), and gives every pixel
inside a triangle the plane through the triangle's three 3D points. The estimator then adds a
penalty for leaving that plane (see ``_prior_term`` in ``_window_cost.pxd``): negligible against
a decisive photometric cost, decisive where the images say nothing.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = [
    "PRIOR_SIGMA_ANGLE",
    "PRIOR_SIGMA_DEPTH",
    "PRIOR_WEIGHT",
    "SUPPORT_GRID",
    "SUPPORT_MAX_COST",
    "planar_prior",
    "support_pixels",
]

# The support pixels: the lowest-cost pixel of each SUPPORT_GRID x SUPPORT_GRID cell, where its
# cost is under SUPPORT_MAX_COST (1 - NCC).
SUPPORT_GRID = 5
SUPPORT_MAX_COST = 0.1
# The penalty for leaving the prior plane (``_prior_term``): PRIOR_WEIGHT * (1 - exp(-r^2 /
# (2 PRIOR_SIGMA_DEPTH^2) - (1 - cos a) / PRIOR_SIGMA_ANGLE^2)), r the depth difference relative
# to the prior's depth and a the angle between the normals. A pixel within PRIOR_SIGMA_DEPTH of
# its prior is on it: kept whatever its photometric cost.
PRIOR_WEIGHT = 0.3
PRIOR_SIGMA_DEPTH = 0.01
PRIOR_SIGMA_ANGLE = 0.2


def support_pixels(depth: np.ndarray, cost: np.ndarray, grid: int, max_cost: float) -> np.ndarray:
    """(N, 2) [row, col] of the lowest-cost pixel of each grid cell, where it is under ``max_cost``."""
    h, w = depth.shape
    gh, gw = h // grid, w // grid
    if gh == 0 or gw == 0:
        return np.zeros((0, 2), np.int64)
    masked = np.where(depth > 0, cost, np.inf)[: gh * grid, : gw * grid]
    cells = masked.reshape(gh, grid, gw, grid).transpose(0, 2, 1, 3).reshape(gh, gw, grid * grid)
    best = cells.argmin(axis=2)
    best_cost = np.take_along_axis(cells, best[..., None], axis=2)[..., 0]
    keep = best_cost < max_cost
    cell_r, cell_c = np.nonzero(keep)
    offset = best[keep]
    return np.column_stack([cell_r * grid + offset // grid, cell_c * grid + offset % grid])


def planar_prior(
    depth: np.ndarray,
    cost: np.ndarray,
    K: np.ndarray,
    grid: int = SUPPORT_GRID,
    max_cost: float = SUPPORT_MAX_COST,
    labels: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Prior depth (H, W), 0 where there is none, and prior camera-frame normals (H, W, 3).
    With region ``labels`` (H, W), a triangle gives a prior only when its three support pixels
    lie in one region (label > 0): a triangle from a table edge to the wall behind it is in
    thin air.
    """
    h, w = depth.shape
    prior_depth = np.zeros((h, w), np.float32)
    prior_normal = np.zeros((h, w, 3), np.float32)
    support = support_pixels(depth, cost, grid, max_cost)
    if len(support) < 3:
        return prior_depth, prior_normal
    xy = support[:, ::-1].astype(np.float64)  # image points (col, row)
    # Imported here: scipy.spatial is among the slowest imports of a command, and one that stops
    # at its checks (or `--help`) never triangulates.
    from scipy.spatial import Delaunay, QhullError

    try:
        triangulation = Delaunay(xy)
    except QhullError:  # all support pixels on a line
        return prior_depth, prior_normal
    K_inv = np.linalg.inv(K)
    rays = np.column_stack([xy, np.ones(len(xy))]) @ K_inv.T
    points = rays * depth[support[:, 0], support[:, 1]][:, None]
    tri = points[triangulation.simplices]  # (T, 3 vertices, 3)
    plane_normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(plane_normal, axis=1)
    ok = length > 1e-12
    plane_normal[ok] /= length[ok, None]
    offset = np.einsum("ij,ij->i", plane_normal, tri[:, 0])
    flip = offset > 0  # orient towards the camera: n . X < 0 on the plane
    plane_normal[flip] *= -1
    offset[flip] *= -1
    if labels is not None:
        vertex_labels = labels[support[:, 0], support[:, 1]][triangulation.simplices]  # (T, 3)
        ok &= (
            (vertex_labels[:, 0] > 0)
            & (vertex_labels[:, 0] == vertex_labels[:, 1])
            & (vertex_labels[:, 0] == vertex_labels[:, 2])
        )

    # Triangle index per pixel: rasterise the triangles (their vertices are pixel centres);
    # much faster than scipy's point location.
    label = np.full((h, w), -1, np.int32)
    corners = support[:, ::-1].astype(np.int32)[triangulation.simplices]  # (T, 3, 2) as (x, y)
    for index in np.flatnonzero(ok):
        cv2.fillConvexPoly(label, corners[index], int(index))
    inside = label.ravel() >= 0
    simplex = label.ravel()[inside]
    rows, cols = np.divmod(np.flatnonzero(inside), w)
    pixel_rays = np.column_stack([cols, rows, np.ones(len(cols))]) @ K_inv.T
    n = plane_normal[simplex]
    facing = np.einsum("ij,ij->i", n, pixel_rays)
    with np.errstate(divide="ignore", invalid="ignore"):
        d = offset[simplex] / facing
    # Planes seen nearly edge-on (< ~3 degrees) give no prior. Depths are not bounded by the
    # view's range, as in propagation: a surface without sparse points lies outside it.
    ray_length = np.linalg.norm(pixel_rays, axis=1)
    valid = ok[simplex] & (facing < -0.05 * ray_length) & (d >= 0)
    flat = np.flatnonzero(inside)[valid]
    prior_depth.ravel()[flat] = d[valid]
    prior_normal.reshape(-1, 3)[flat] = n[valid]
    return prior_depth, prior_normal
