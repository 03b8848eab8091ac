"""The planar prior (``planar_prior.py``): triangulated reliable pixels, kept inside regions."""

import numpy as np

from tests.plane_scenes import K, plane_scene


def test_planar_prior_reproduces_a_plane_from_its_reliable_pixels():
    from dvpmvs.patchmatch.planar_prior import planar_prior, support_pixels

    _, plane_depth, normals = plane_scene()
    rng = np.random.default_rng(2)
    cost = rng.uniform(0.5, 1.0, plane_depth.shape).astype(np.float32)
    reliable = rng.random(plane_depth.shape) < 0.05
    cost[reliable] = 0.05
    support = support_pixels(plane_depth, cost, grid=5, max_cost=0.2)
    assert len(support) > 20 and (cost[support[:, 0], support[:, 1]] < 0.2).all()
    # Each support pixel is the cheapest of its 5x5 cell.
    r, c = support[0]
    cell = cost[r // 5 * 5 : r // 5 * 5 + 5, c // 5 * 5 : c // 5 * 5 + 5]
    assert cost[r, c] == cell.min()
    depth = np.where(reliable, plane_depth, 0).astype(np.float32)  # only the reliable pixels known
    prior_depth, prior_normal = planar_prior(depth, cost, K)
    covered = prior_depth > 0
    assert 0.5 < covered.mean() < 1.0  # inside the support pixels' convex hull only
    np.testing.assert_allclose(prior_depth[covered], plane_depth[covered], rtol=1e-4)
    np.testing.assert_allclose(prior_normal[covered], normals[covered], atol=1e-3)


def test_planar_prior_keeps_triangles_inside_one_region():
    from dvpmvs.patchmatch.planar_prior import planar_prior

    # A frontal plane at depth 3 (left half, region 1) in front of one at depth 5 (right half,
    # region 2); every pixel is a candidate support pixel.
    h, w = 60, 80
    depth = np.full((h, w), 3.0, np.float32)
    depth[:, w // 2 :] = 5.0
    labels = np.ones((h, w), np.int32)
    labels[:, w // 2 :] = 2
    cost = np.random.default_rng(4).uniform(0.0, 0.05, (h, w)).astype(np.float32)
    spanning, _ = planar_prior(depth, cost, K)
    wrong = (spanning > 0) & (np.abs(spanning - depth) > 1e-3)
    assert wrong.sum() > 20  # triangles across the depth edge put planes in thin air
    regional, _ = planar_prior(depth, cost, K, labels=labels)
    covered = regional > 0
    assert covered.mean() > 0.8
    np.testing.assert_allclose(regional[covered], depth[covered], rtol=1e-4)


def test_planar_prior_needs_three_support_pixels():
    from dvpmvs.patchmatch.planar_prior import planar_prior

    depth = np.full((20, 20), 3.0, np.float32)
    cost = np.ones((20, 20), np.float32)
    cost[2, 2] = cost[10, 10] = 0.0
    prior_depth, _ = planar_prior(depth, cost, K)
    assert not (prior_depth > 0).any()
