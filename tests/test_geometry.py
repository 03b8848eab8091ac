"""Camera geometry: intrinsics of a resized image, back-projection, planes fitted to points."""

import cv2
import numpy as np

from dvpmvs.geometry import RansacPlanes, back_project, least_squares_plane, scale_intrinsics
from tests.plane_scenes import K, depth_of_plane


def test_scale_intrinsics_follows_cv2_resize():
    # A bright pixel at (x, y) = (40, 20) of a 80x60 image lands at 0.5 (x + 0.5) - 0.5 after halving.
    image = np.zeros((60, 80), np.float32)
    image[20:22, 40:42] = 1.0  # a 2x2 block centred on (40.5, 20.5)
    small = cv2.resize(image, (40, 30), interpolation=cv2.INTER_AREA)
    y, x = np.unravel_index(np.argmax(small), small.shape)
    K2 = scale_intrinsics(K, 0.5, 0.5)
    X = np.linalg.inv(K) @ np.array([40.5, 20.5, 1.0])
    projected = K2 @ X
    assert np.allclose(projected[:2], (x, y))


def test_back_projected_points_project_to_their_pixels_at_their_depth():
    depth = np.random.default_rng(0).uniform(2.0, 6.0, (30, 40))
    points = back_project(depth, K)
    assert points.shape == (30, 40, 3) and np.allclose(points[..., 2], depth)
    projected = points @ K.T
    rows, cols = np.mgrid[0:30, 0:40]
    assert np.allclose(projected[..., 0] / projected[..., 2], cols)
    assert np.allclose(projected[..., 1] / projected[..., 2], rows)


def test_least_squares_plane_recovers_an_exact_plane():
    rng = np.random.default_rng(1)
    normal = np.array([0.2, -0.1, -1.0]) / np.linalg.norm([0.2, -0.1, -1.0])
    basis = np.linalg.svd(normal[None])[2][1:]  # two directions in the plane
    points = np.array([0, 0, 4.0]) + rng.normal(size=(50, 2)) @ basis
    plane = least_squares_plane(points)
    assert (
        abs(abs(plane[:3] @ normal) - 1) < 1e-12
        and np.abs(points @ plane[:3] + plane[3]).max() < 1e-12
    )


def test_ransac_finds_the_plane_under_a_third_of_outliers_and_faces_the_camera():
    h, w = 60, 80
    rows, cols = np.mgrid[0:h, 0:w]
    normal, point = np.array([0.2, -0.1, -1.0]), np.array([0.0, 0.0, 4.0])
    depth = depth_of_plane(K, normal, point, rows, cols)
    outliers = np.random.default_rng(2).random((h, w)) < 0.3
    depth[outliers] *= 1.5
    points = back_project(depth, K)
    valid = np.ones((h, w), bool)
    valid[:5] = False  # pixels that may not support a plane are never inliers
    planes = RansacPlanes(
        points, valid, distance_unit=0.005, iterations=200, max_points=2000, seed=0
    )
    plane, ratio, inliers = planes.fit(np.arange(h * w))
    unit = normal / np.linalg.norm(normal)
    assert plane[2] < 0 and abs(plane[:3] @ unit - 1) < 1e-6  # n . z < 0: towards the camera
    truth = ~outliers.ravel()[valid.ravel()]
    assert np.array_equal(inliers, truth) and abs(ratio - truth.mean()) < 1e-12
    # The same seed and calls, the same plane; too few pixels, no plane.
    again = RansacPlanes(
        points, valid, distance_unit=0.005, iterations=200, max_points=2000, seed=0
    )
    assert np.array_equal(again.fit(np.arange(h * w))[0], plane)
    nothing, ratio, _ = planes.fit(np.arange(2))
    assert np.isnan(nothing).all() and ratio == 0.0
