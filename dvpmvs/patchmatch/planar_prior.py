"""Planar prior from reliable pixels (the idea of ACMMP, Xu and Tao 2022).

Textureless surfaces give every hypothesis the same photometric cost, so PatchMatch alone leaves
them empty or noisy. Their outlines, though, are usually textured and well estimated. The prior
takes the most reliable pixel of every ``grid`` x ``grid`` cell (lowest cost, under
``max_cost``), triangulates these support pixels in the image (Delaunay), and gives every pixel
inside a triangle the plane through the triangle's three 3D points. The estimator then adds a
penalty for leaving that plane (see ``_prior_term`` in ``_window_cost.pxd``): negligible against
a decisive photometric cost, decisive where the images say nothing.

Where the images say nothing, a low cost can be chance: on a plain surface the cheapest of a
cell's 25 pixels often matches noise at a wrong depth. A triangle therefore gives its plane only
where a share of its own pixels already lie on it (``_has_consensus``). A plain wall then has no
triangle of its own; with the aligned prior's regions, a large region without triangles gets the
plane the largest share of its pixels hold (``_region_plane_prior``): the coarse levels, where
the wall's faint texture shows, found that plane for many of its pixels, and the others scatter.
That plane is the least-squares plane of the pixels holding it (``_refined_plane``): the prior
keeps a pixel within PRIOR_SIGMA_DEPTH of it, so a plane only roughly the wall's holds the wall
at that error.
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
    "holds_plane",
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
# A triangle gives its plane only where this share of its pixels already lie on it (within
# PRIOR_SIGMA_DEPTH): see ``_has_consensus``.
PRIOR_CONSENSUS = 0.2
# A region of the aligned prior covering REGION_MIN_SHARE of the image or more gives its pixels
# without a triangle its dominant plane (``_region_plane_prior``): the best of REGION_HYPOTHESES
# planes through three of (at most) REGION_SAMPLE of its pixels, where REGION_CONSENSUS of them
# lie on it, refitted REGION_REFITS times to the pixels on it (``_refined_plane``).
REGION_MIN_SHARE = 0.01
REGION_SAMPLE = 4000
REGION_HYPOTHESES = 256
REGION_CONSENSUS = 0.3
REGION_REFITS = 3
# ... and only where REGION_LOCAL_SHARE of the region's pixels within the REGION_LOCAL_WINDOW
# square around a pixel hold it (``_held_nearby``).
REGION_LOCAL_WINDOW = 101
REGION_LOCAL_SHARE = 0.1


def holds_plane(depth: np.ndarray, plane_depth: np.ndarray) -> np.ndarray:
    """Whether ``depth`` lies within PRIOR_SIGMA_DEPTH (relative) of a plane's ``plane_depth``
    along the same rays: a pixel that holds the plane, or stays on its prior."""
    return np.abs(depth - plane_depth) <= PRIOR_SIGMA_DEPTH * plane_depth


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


def _has_consensus(
    simplex: np.ndarray, plane_depth: np.ndarray, depth: np.ndarray, valid: np.ndarray, count: int
) -> np.ndarray:
    """Per pixel: whether its triangle's plane is held by at least PRIOR_CONSENSUS of the
    triangle's pixels (their current depth within PRIOR_SIGMA_DEPTH of the plane's). A vertex
    whose low cost is chance (on a plain surface, the best of a cell's pixels matches noise)
    spans its triangles with a plane that nothing inside holds; a plane the surface's pixels
    found, even a minority of them, is kept."""
    known = valid & (depth > 0)  # a masked pixel (no estimate) neither holds nor refutes
    with np.errstate(invalid="ignore"):
        held = known & holds_plane(depth, plane_depth)
    pixels = np.bincount(simplex[known], minlength=count)
    holding = np.bincount(simplex[held], minlength=count)
    return holding[simplex] >= PRIOR_CONSENSUS * np.maximum(pixels[simplex], 1)


def planar_prior(
    depth: np.ndarray,
    cost: np.ndarray,
    K: np.ndarray,
    grid: int = SUPPORT_GRID,
    max_cost: float = SUPPORT_MAX_COST,
    labels: np.ndarray | None = None,
    weak: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Prior depth (H, W), 0 where there is none, and prior camera-frame normals (H, W, 3).
    With region ``labels`` (H, W), a triangle gives a prior only when its three support pixels
    lie in one region (label > 0): a triangle from a table edge to the wall behind it is in
    thin air; and a large region's pixels without a triangle get its dominant plane (those of
    the ``weak`` mask only, where given).
    """
    h, w = depth.shape
    prior_depth = np.zeros((h, w), np.float32)
    prior_normal = np.zeros((h, w, 3), np.float32)
    _triangle_prior(depth, cost, K, grid, max_cost, labels, prior_depth, prior_normal)
    if labels is not None:
        _region_plane_prior(depth, K, labels, weak, prior_depth, prior_normal)
    return prior_depth, prior_normal


def _triangle_prior(
    depth: np.ndarray,
    cost: np.ndarray,
    K: np.ndarray,
    grid: int,
    max_cost: float,
    labels: np.ndarray | None,
    prior_depth: np.ndarray,
    prior_normal: np.ndarray,
) -> None:
    """The planes of the support pixels' triangles, into ``prior_depth`` and ``prior_normal``."""
    h, w = depth.shape
    support = support_pixels(depth, cost, grid, max_cost)
    if len(support) < 3:
        return
    xy = support[:, ::-1].astype(np.float64)  # image points (col, row)
    # Imported here: scipy.spatial is among the slowest imports of a command, and one that stops
    # at its checks (or `--help`) never triangulates.
    from scipy.spatial import Delaunay, QhullError

    try:
        triangulation = Delaunay(xy)
    except QhullError:  # all support pixels on a line
        return
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
    valid &= _has_consensus(simplex, d, depth.ravel()[inside], valid, len(ok))
    flat = np.flatnonzero(inside)[valid]
    prior_depth.ravel()[flat] = d[valid]
    prior_normal.reshape(-1, 3)[flat] = n[valid]


def _region_plane_prior(
    depth: np.ndarray,
    K: np.ndarray,
    labels: np.ndarray,
    weak: np.ndarray | None,
    prior_depth: np.ndarray,
    prior_normal: np.ndarray,
) -> None:
    """For the pixels of a large region that no triangle gave a plane: the region's dominant
    plane, where it holds REGION_CONSENSUS of the region's pixels (RANSAC over their current
    depths). A plain wall has no support pixel of its own, but the planes the coarse levels
    found there hold a good share of its pixels (the others scatter), so its dominant plane is
    the wall's; a region of several surfaces or a curved one has no plane that many hold. The
    plane is given only where its own pixels hold it nearby (``_held_nearby``)."""
    h, w = depth.shape
    flat_labels = labels.ravel()
    counts = np.bincount(flat_labels)
    large = np.flatnonzero(counts >= REGION_MIN_SHARE * h * w)
    large = large[large > 0]
    if not len(large):
        return
    K_inv = np.linalg.inv(K)
    order = np.argsort(flat_labels, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)])
    for label in large:
        pixels = order[starts[label] : starts[label + 1]]
        # Held by a share of all the region's pixels: where the filter emptied most of a region
        # (open sky in the geometric pass), the few left are no consensus.
        known_share = np.count_nonzero(depth.ravel()[pixels] > 0) / len(pixels)
        pixels = pixels[depth.ravel()[pixels] > 0]
        if len(pixels) < 3:
            continue
        rng = np.random.default_rng(int(label))  # the same maps for the same inputs
        if len(pixels) > REGION_SAMPLE:
            pixels = np.sort(rng.choice(pixels, REGION_SAMPLE, replace=False))
        rows, cols = np.divmod(pixels, w)
        rays = np.column_stack([cols, rows, np.ones(len(cols))]) @ K_inv.T
        z = depth.ravel()[pixels].astype(np.float64)
        points = rays * z[:, None]
        trios = rng.integers(0, len(pixels), (REGION_HYPOTHESES, 3))
        a, b, c = points[trios[:, 0]], points[trios[:, 1]], points[trios[:, 2]]
        normals = np.cross(b - a, c - a)
        length = np.linalg.norm(normals, axis=1)
        usable = length > 1e-12
        normals = normals[usable] / length[usable, None]
        offsets = -np.einsum("ij,ij->i", normals, a[usable])
        if not len(normals):
            continue
        facing = rays @ normals.T  # (pixels, hypotheses)
        with np.errstate(divide="ignore", invalid="ignore"):
            plane_z = -offsets[None, :] / facing
            held = holds_plane(z[:, None], plane_z)
        share = held.mean(axis=0) * known_share
        best = int(np.argmax(share))
        if share[best] < REGION_CONSENSUS:
            continue
        normal, offset = _refined_plane(rays, z, held[:, best], normals[best], offsets[best])
        if offset < 0:  # orient towards the camera: n . X < 0 on the plane
            normal, offset = -normal, -offset
        region = order[starts[label] : starts[label + 1]]
        rows, cols = np.divmod(region, w)
        pixel_rays = np.column_stack([cols, rows, np.ones(len(cols))]) @ K_inv.T
        facing = pixel_rays @ normal
        with np.errstate(divide="ignore", invalid="ignore"):
            d = -offset / facing
        ray_length = np.linalg.norm(pixel_rays, axis=1)
        valid = (facing < -0.05 * ray_length) & (d > 0)
        current = depth.ravel()[region]
        with np.errstate(invalid="ignore"):
            held = valid & (current > 0) & holds_plane(current, d)
        valid &= _held_nearby(rows, cols, held)
        valid &= prior_depth.ravel()[region] == 0
        if weak is not None:
            valid &= weak.ravel()[region]
        prior_depth.ravel()[region[valid]] = d[valid]
        prior_normal.reshape(-1, 3)[region[valid]] = normal


def _held_nearby(rows: np.ndarray, cols: np.ndarray, held: np.ndarray) -> np.ndarray:
    """Per pixel of a region (``rows``, ``cols``): whether REGION_LOCAL_SHARE of the region's
    pixels in the REGION_LOCAL_WINDOW square around it hold the region's plane (``held``). The
    segmentation can merge a plain wall with the plain sky above it into one region: the wall's
    plane is held on the wall, and would carry on into the sky, where the images agree with
    any depth."""
    top, left = rows.min(), cols.min()
    shape = (rows.max() - top + 1, cols.max() - left + 1)
    member = np.zeros(shape, np.float32)
    holding = np.zeros(shape, np.float32)
    member[rows - top, cols - left] = 1
    holding[rows - top, cols - left] = held
    size = (REGION_LOCAL_WINDOW, REGION_LOCAL_WINDOW)
    around = cv2.boxFilter(member, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
    on_plane = cv2.boxFilter(holding, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
    share = on_plane / np.maximum(around, 1)
    return share[rows - top, cols - left] >= REGION_LOCAL_SHARE


def _refined_plane(
    rays: np.ndarray, z: np.ndarray, inliers: np.ndarray, normal: np.ndarray, offset: float
) -> tuple[np.ndarray, float]:
    """The plane (unit normal n, offset d: n . X + d = 0) fitted to the ``inliers`` of a RANSAC
    hypothesis (``normal``, ``offset``; returned where fewer than three pixels hold it), refitted
    REGION_REFITS times to the pixels within PRIOR_SIGMA_DEPTH of the last fit (the local
    optimisation of LO-RANSAC, Chum et al. 2003). Three noisy pixels span a plane only roughly
    the surface's, off by a share of their scatter; the least-squares plane of its inliers
    averages the scatter out.

    On a plane, the inverse depth is affine in the normalised image coordinates (x, y):
    1 / z = a x + b y + c. The fit minimises the relative depth error, (1 / z - a x - b y - c) z.
    """
    plane = None
    for _ in range(REGION_REFITS):
        if inliers.sum() < 3:
            break
        weight = z[inliers]
        design = rays[inliers] * weight[:, None]  # rows (x z, y z, z): relative residuals
        solution, *_ = np.linalg.lstsq(design, np.ones(len(weight)), rcond=None)
        plane = solution
        with np.errstate(divide="ignore", invalid="ignore"):
            plane_z = 1.0 / (rays @ plane)
            inliers = (plane_z > 0) & holds_plane(z, plane_z)
    if plane is None:
        return normal, offset
    # 1 / z = p . r  <=>  p . X = 1 for X = z r: n . X + d = 0 with n = -p / |p|, d = 1 / |p|.
    length = float(np.linalg.norm(plane))
    return -plane / length, 1.0 / length
