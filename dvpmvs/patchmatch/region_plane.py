"""Region planes: one plane per homogeneous region, fitted to its strong pixels' estimates.

A weak pixel's anchor plane (``fit_anchor_planes``) needs three of its own anchors that agree.
On a large textureless wall the only strong pixels of the region are often a picture or a
window far away, two sectors' worth: no anchor plane, and two distant anchor windows leave the
deformed cost of eq. 3 too flat for random refinement to find the wall's plane. The region of
the aligned prior (section 3.3) is meant to be one surface; where it is planar, its strong
pixels say which plane. This module fits that plane by RANSAC and offers it to the region's
weak pixels whose own anchors lie on it, as one more hypothesis; the deformed cost still
decides whether it wins.

Why the anchor check: a region is not always one plane, and "strong" pixels on a uniform wall
are sometimes wrong. On an 800x600 room view (simulated priors), the region plane alone was
within 1 % of the true depth at under half of the weak pixels it reached; requiring 3/4 of a
pixel's anchors (at least 2) to lie on it, at about three quarters of the (fewer) pixels.
"""

from __future__ import annotations

import numpy as np

from dvpmvs.geometry import RansacPlanes, back_project

__all__ = ["region_planes"]

_RANSAC_ITERATIONS = 200
_RANSAC_POINTS = 2000


def region_planes(
    depth: np.ndarray,
    strong: np.ndarray,
    labels: np.ndarray,
    K: np.ndarray,
    depth_range: tuple[float, float],
    max_error: float = 0.005,
    min_strong: int = 50,
    min_inlier_ratio: float = 0.6,
    seed: int = 0,
    anchors: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel the plane of its region (labels > 0): depth (H, W), 0 where there is none, and
    camera-frame normal (H, W, 3) facing the camera.

    A region gets a plane when it has at least ``min_strong`` strong pixels with a depth and
    at least ``min_inlier_ratio`` of them lie within ``max_error`` (relative depth) of the
    RANSAC plane; pixels where the plane is seen nearly edge-on or leaves ``depth_range`` get
    none. With ``anchors`` ((H, W, 8) flat pixel indices, -1 for none), a pixel keeps the plane
    only when at least 2 of its anchors and 3/4 of them lie within ``max_error`` of it.
    Deterministic for a given ``seed``.
    """
    h, w = depth.shape
    if (
        strong.shape != (h, w)
        or labels.shape != (h, w)
        or (anchors is not None and anchors.shape[:2] != (h, w))
    ):
        raise ValueError(
            f"depth {depth.shape}, strong {strong.shape}, labels {labels.shape} and anchors "
            f"{None if anchors is None else anchors.shape} must share one image size"
        )
    if max_error <= 0 or min_strong < 3 or not 0 < min_inlier_ratio <= 1:
        raise ValueError(
            "region planes need max_error > 0, min_strong >= 3 and 0 < min_inlier_ratio <= 1"
        )
    plane_depth = np.zeros((h, w), np.float32)
    plane_normal = np.zeros((h, w, 3), np.float32)
    flat_labels = np.asarray(labels).ravel()
    support = (np.asarray(strong).ravel() > 0) & (flat_labels > 0) & (np.asarray(depth).ravel() > 0)
    if support.sum() < min_strong:
        return plane_depth, plane_normal
    rays = back_project(np.ones((h, w)), K).reshape(-1, 3)
    points = rays * np.asarray(depth, np.float64).ravel()[:, None]
    ransac = RansacPlanes(points, support, max_error, _RANSAC_ITERATIONS, _RANSAC_POINTS, seed)
    # Strong pixels grouped by region (sorted labels: the fit order, hence the result, is fixed).
    index = np.flatnonzero(support)
    order = np.argsort(flat_labels[index], kind="stable")
    index = index[order]
    region, start, count = np.unique(flat_labels[index], return_index=True, return_counts=True)
    planes = np.full((int(flat_labels.max()) + 1, 4), np.nan)
    for label, first, n in zip(region, start, count):
        if n < min_strong:
            continue
        plane, ratio, _ = ransac.fit(index[first : first + n])
        if ratio >= min_inlier_ratio and np.isfinite(plane).all():
            planes[label] = plane
    plane = planes[flat_labels]  # (H*W, 4); label 0 (boundaries) is NaN
    facing = np.einsum("ij,ij->i", rays, np.nan_to_num(plane[:, :3]))
    with np.errstate(divide="ignore", invalid="ignore"):
        d = -plane[:, 3] / facing
    # As the planar prior: planes seen nearly edge-on (< ~3 degrees) give nothing.
    valid = (
        np.isfinite(d)
        & (facing < -0.05 * np.linalg.norm(rays, axis=1))
        & (d >= depth_range[0])
        & (d <= depth_range[1])
    )
    if anchors is not None:
        flat_anchors = np.asarray(anchors).reshape(h * w, -1)
        has = flat_anchors >= 0
        at = np.maximum(flat_anchors, 0)
        anchor_depth = np.asarray(depth, np.float64).ravel()[at]
        on_plane = (
            has
            & (anchor_depth > 0)
            & valid[at]
            & (np.abs(np.where(valid, d, 0)[at] - anchor_depth) <= max_error * anchor_depth)
        )
        count = has.sum(axis=1)
        valid &= (count >= 2) & (4 * on_plane.sum(axis=1) >= 3 * count)
    plane_depth.ravel()[valid] = d[valid]
    plane_normal.reshape(-1, 3)[valid] = plane[valid, :3]
    return plane_depth, plane_normal
