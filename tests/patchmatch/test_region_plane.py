"""The region plane (``region_plane.py``) of weak pixels."""

import numpy as np
import pytest

from dvpmvs.patchmatch import PatchMatchOptions
from dvpmvs.patchmatch.region_plane import region_planes
from tests.plane_scenes import K, plane_scene


def test_region_plane_extends_the_strong_pixels_plane_over_their_region():
    _, plane_depth, normals = plane_scene()
    h, w = plane_depth.shape
    depth = plane_depth.copy()
    labels = np.zeros((h, w), np.int32)
    labels[:, :50] = 1  # the plane: strong pixels only in a 10x10 "picture" at its top left
    labels[:, 52:] = 2  # a second region whose strong pixels lie on no plane
    strong = np.zeros((h, w), np.uint8)
    strong[5:15, 5:15] = 1
    strong[5:25, 55:75] = 1
    rng = np.random.default_rng(0)
    depth[:, 52:] = rng.uniform(3.0, 6.0, (h, w - 52))
    outliers = (slice(5, 8), slice(5, 15))  # 30 of the picture's 100 pixels 10 % off the plane
    depth[outliers] *= 1.1
    fit_depth, fit_normal = region_planes(depth, strong, labels, K, (2.0, 8.0), 0.005, 50, 0.6)
    np.testing.assert_allclose(fit_depth[:, :50], plane_depth[:, :50], rtol=1e-5)
    np.testing.assert_allclose(fit_normal[:, :50], normals[:, :50], atol=1e-5)
    assert (fit_depth[:, 50:] == 0).all()  # boundary (label 0) and the non-planar region
    # Too few strong pixels (100 < 120), or too few of them on the plane (70 % < 80 %): no plane.
    assert (region_planes(depth, strong, labels, K, (2.0, 8.0), 0.005, 120, 0.6)[0] == 0).all()
    assert (region_planes(depth, strong, labels, K, (2.0, 8.0), 0.005, 50, 0.8)[0] == 0).all()
    again = region_planes(depth, strong, labels, K, (2.0, 8.0), 0.005, 50, 0.6)
    np.testing.assert_array_equal(again[0], fit_depth)  # same seed, same planes
    # With anchors, a pixel keeps the plane only when >= 2 and 3/4 of its anchors lie on it.
    anchors = np.full((h, w, 8), -1, np.int32)
    anchors[40, 30, :2] = [10 * w + 10, 12 * w + 12]  # two on the plane: kept
    anchors[40, 20, :4] = [10 * w + 10, 12 * w + 12, 6 * w + 6, 7 * w + 7]  # two of four off it
    anchors[40, 10, 0] = 10 * w + 10  # a single anchor
    checked = region_planes(depth, strong, labels, K, (2.0, 8.0), 0.005, 50, 0.6, anchors=anchors)[
        0
    ]
    assert checked[40, 30] == fit_depth[40, 30]
    assert checked[40, 20] == 0 and checked[40, 10] == 0
    assert np.count_nonzero(checked) == 1  # no anchors, no plane
    with pytest.raises(ValueError, match="share one image size"):
        region_planes(depth, strong[:10], labels, K, (2.0, 8.0))
    with pytest.raises(ValueError, match="region_plane_min_inliers"):
        PatchMatchOptions(region_plane_min_inliers=0)
