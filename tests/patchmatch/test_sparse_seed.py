"""The sparse points' planes as starting hypotheses (dvpmvs.patchmatch.sparse_seed)."""

import cv2
import numpy as np
import pytest

from dvpmvs.patchmatch import PatchMatchOptions, Problem, ViewData, estimate
from dvpmvs.patchmatch.sparse_seed import sparse_planes

K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
SIZE = (320, 240)
HEIGHT = 1.5  # the camera above the ground (camera y points down)


def _ground_depth(K, size, height):
    """Depth of the ground plane y = height along each pixel's ray (0 above the horizon)."""
    w, h = size
    rows = np.mgrid[0:h, 0:w][0].astype(np.float64)
    ray_y = (rows - K[1, 2]) / K[1, 1]
    return np.where(ray_y > 0, height / np.where(ray_y > 0, ray_y, 1), 0)


def _far_ground_points(count, seed=0):
    """``count`` points on the ground 10-20 m ahead: none on the near ground the bottom rows see."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(10, 20, count)
    return np.stack([rng.uniform(-0.3, 0.3, count) * z, np.full(count, HEIGHT), z], axis=1)


def test_ground_below_the_points_gets_the_ground_plane_nearer_than_the_sparse_depth_range():
    # Fifteen sparse points on the far ground; the bottom fifth of the image sees the ground at
    # 3.8-6.2 m, nearer than every point and than the depth range from their quantiles.
    points = _far_ground_points(15)
    depth_range = (0.75 * points[:, 2].min(), 1.25 * points[:, 2].max())
    truth = _ground_depth(K, SIZE, HEIGHT)
    bottom = slice(SIZE[1] * 4 // 5, None)
    assert truth[bottom].max() < depth_range[0]

    depth, normal = sparse_planes(points, K, np.eye(3), np.zeros(3), SIZE)
    np.testing.assert_allclose(depth[bottom], truth[bottom], rtol=1e-5)
    np.testing.assert_allclose(
        normal[bottom], np.broadcast_to([0, -1, 0], normal[bottom].shape), atol=1e-6
    )
    # Above the horizon the plane is behind the camera, and just below it seen edge-on: no seed.
    assert not depth[: int(K[1, 2]) + 1].any() and not normal[: int(K[1, 2]) + 1].any()
    seeded = depth > 0
    np.testing.assert_allclose(depth[seeded], truth[seeded], rtol=1e-4)


def test_the_pose_moves_the_points_into_the_camera_and_too_few_points_give_no_seed():
    points = _far_ground_points(15)
    R = cv2.Rodrigues(np.array([0.0, 0.1, 0.0]))[0]
    t = np.array([0.2, -0.1, 0.5])
    # The same ground seen from a camera at pose (R, t): the points mapped into it are the
    # same camera-frame points as before, so the same seeds come out.
    world = (points - t) @ R  # R^T (X - t): camera -> world
    depth, normal = sparse_planes(world, K, R, t, SIZE)
    reference, reference_normal = sparse_planes(points, K, np.eye(3), np.zeros(3), SIZE)
    np.testing.assert_allclose(depth, reference, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(normal, reference_normal, atol=1e-5)

    for few in (
        points[:2],
        points[:0],
        np.tile(points[:1], (5, 1)),
        -points,
    ):  # 2, none, one spot, behind
        depth, normal = sparse_planes(few, K, np.eye(3), np.zeros(3), SIZE)
        assert not depth.any() and not normal.any()
    with pytest.raises(ValueError, match=r"\(N, 3\) world points"):
        Problem(
            ViewData("r", np.zeros((4, 4)), K, np.eye(3), np.zeros(3)),
            [ViewData("s", np.zeros((4, 4)), K, np.eye(3), np.ones(3))],
            (1.0, 2.0),
            sparse_points=np.zeros((3, 2)),
        )


def _ground_scene(num_sources=3, seed=0):
    """A textured ground plane running toward the camera (the bottom rows 1.5 m away, the
    top ones 5.6 m), seen by sources beside the reference, rendered with the exact plane warp."""
    w, h = 120, 90
    Ks = np.array([[100.0, 0, 59.5], [0, 100.0, 44.5], [0, 0, 1]])
    rng = np.random.default_rng(seed)
    reference_image = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 1.2)
    # The plane n . X = d through the reference camera's frame: tilted 70 degrees from facing it.
    n = np.array([0.0, -np.sin(np.deg2rad(70)), -np.cos(np.deg2rad(70))])
    d = n @ np.array([0.0, 0.0, 4.0])
    rows, cols = np.mgrid[0:h, 0:w]
    rays = np.stack([cols, rows, np.ones_like(cols)], -1).astype(np.float64) @ np.linalg.inv(Ks).T
    truth = (d / (rays @ n)).astype(np.float32)
    sources = []
    for j in range(num_sources):
        R = cv2.Rodrigues(np.array([0.0, 0.02 * (j + 1), 0.0]))[0]
        t = np.array([0.15 * (j + 1) * (-1) ** j, 0.03, 0.0])
        H = Ks @ (R + np.outer(t, n) / d) @ np.linalg.inv(Ks)
        image = cv2.warpPerspective(
            reference_image, H, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
        )
        sources.append(ViewData(f"s{j}", image, Ks, R, t))
    reference = ViewData("ref", reference_image, Ks, np.eye(3), np.zeros(3))
    # A dozen sparse points on the plane's upper half (world = reference camera frame).
    pick = rng.choice(np.flatnonzero((rows < h // 2).ravel()), 12, replace=False)
    points = rays.reshape(-1, 3)[pick] * truth.ravel()[pick, None]
    return reference, sources, truth, points


def test_seeded_planes_find_ground_that_random_draws_in_a_wide_range_miss():
    reference, sources, truth, points = _ground_scene()
    # A range 20x deeper than the plane: one random draw in a hundred falls within 1 % of a depth.
    problem = Problem(reference, sources, (1.0, 60.0), sparse_points=points)
    inner = np.zeros(truth.shape, bool)
    inner[8:-8, 8:-8] = True

    def within(sparse_seed):
        options = PatchMatchOptions(
            num_scales=1,
            num_iterations=1,
            seed=1,
            num_threads=2,
            filter_min_region=0,
            planar_prior=False,
            deformable=False,
            sparse_seed=sparse_seed,
        )
        depth = estimate(problem, options).depth
        return (np.abs(depth - truth) <= 0.01 * truth)[inner].mean()

    seeded, unseeded = within(True), within(False)
    assert seeded > 0.95 and unseeded < 0.25, (seeded, unseeded)  # measured 0.958 and 0.128
    # Without sparse points in the problem the switch changes nothing.
    no_points = Problem(reference, sources, (1.0, 60.0))
    options = PatchMatchOptions(
        num_scales=1, num_iterations=1, seed=1, num_threads=2, sparse_seed=True
    )
    np.testing.assert_array_equal(
        estimate(no_points, options).depth,
        estimate(
            no_points, PatchMatchOptions(num_scales=1, num_iterations=1, seed=1, num_threads=2)
        ).depth,
    )
