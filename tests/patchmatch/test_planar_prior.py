"""The planar prior (``planar_prior.py``): triangulated reliable pixels, kept inside regions."""

import numpy as np

from tests.plane_scenes import K, depth_of_plane, plane_scene


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


def _plain_surface(share_on_plane: float, seed: int):
    """The plane of ``plane_scene`` as a textureless surface after propagation: ``share`` of
    its pixels on their plane, the others scattered, every photometric cost flat (high)."""
    _, plane_depth, normals = plane_scene()
    rng = np.random.default_rng(seed)
    on = rng.random(plane_depth.shape) < share_on_plane
    depth = np.where(on, plane_depth, plane_depth * rng.uniform(0.7, 1.4, plane_depth.shape))
    cost = rng.uniform(0.3, 0.9, plane_depth.shape).astype(np.float32)
    return depth.astype(np.float32), cost, plane_depth, normals, rng


def test_a_triangle_that_no_pixel_inside_holds_gives_no_plane(monkeypatch):
    """On a plain surface the cheapest pixel of a cell can match noise at a wrong depth: its
    triangles' planes are held by none of the surface's pixels, and are dropped."""
    import dvpmvs.patchmatch.planar_prior as module

    depth, cost, plane_depth, _, rng = _plain_surface(0.5, seed=5)
    cells = [(r, c) for r in range(2, 60, 10) for c in range(2, 80, 10)]
    for k, (r, c) in enumerate(cells):
        cost[r, c] = 0.01  # a support pixel of its cell
        depth[r, c] = plane_depth[r, c] * (1.0 if k % 3 else 1.15)  # a third of them by chance
    prior, _ = module.planar_prior(depth, cost, K)
    covered = prior > 0
    assert covered.mean() > 0.1  # the triangles of three right vertices
    np.testing.assert_allclose(prior[covered], plane_depth[covered], rtol=1e-4)
    monkeypatch.setattr(module, "PRIOR_CONSENSUS", 0.0)
    unchecked, _ = module.planar_prior(depth, cost, K)
    wrong = (unchecked > 0) & (np.abs(unchecked - plane_depth) > 0.01 * plane_depth)
    assert wrong.mean() > 0.3  # without the check, most of the surface gets a wrong plane


def test_a_plain_region_gets_the_plane_a_share_of_its_pixels_hold():
    from dvpmvs.patchmatch.planar_prior import REGION_CONSENSUS, planar_prior

    # No support pixel at all (every cost flat): the triangles give nothing; the region's
    # dominant plane, held by 40 % of its pixels, is the surface's.
    depth, cost, plane_depth, normals, _ = _plain_surface(0.4, seed=6)
    labels = np.ones(depth.shape, np.int32)
    prior, prior_normal = planar_prior(depth, cost, K, labels=labels)
    assert (prior > 0).mean() > 0.99
    np.testing.assert_allclose(prior[prior > 0], plane_depth[prior > 0], rtol=2e-3)
    assert np.degrees(np.arccos(np.clip((prior_normal * normals).sum(-1), -1, 1))).max() < 2
    # Only for its weak pixels where the estimator names them: a strong one keeps its own plane.
    weak = np.zeros(depth.shape, bool)
    weak[:, :40] = True
    half, _ = planar_prior(depth, cost, K, labels=labels, weak=weak)
    assert (half[:, :40] > 0).mean() > 0.99 and not (half[:, 40:] > 0).any()
    # Scattered depths (no plane holds REGION_CONSENSUS of them), or a region too small: none.
    scattered, _, _, _, _ = _plain_surface(REGION_CONSENSUS / 3, seed=7)
    assert not (planar_prior(scattered, cost, K, labels=labels)[0] > 0).any()
    tiny = np.zeros(depth.shape, np.int32)
    tiny[:4, :4] = 1
    assert not (planar_prior(depth, cost, K, labels=tiny)[0] > 0).any()


def test_a_region_plane_is_refitted_to_the_pixels_that_hold_it(monkeypatch):
    """Three noisy pixels span a plane only roughly the surface's; the least-squares plane of
    the pixels it holds is the surface's within their scatter (LO-RANSAC's local step)."""
    import dvpmvs.patchmatch.planar_prior as module

    depth, cost, plane_depth, _, rng = _plain_surface(0.5, seed=8)
    noisy = depth * np.where(
        np.abs(depth - plane_depth) < 1e-6, 1 + rng.normal(0, 0.003, depth.shape), 1
    )
    noisy = noisy.astype(np.float32)
    labels = np.ones(depth.shape, np.int32)

    def error(prior):
        return np.median(np.abs(prior - plane_depth)[prior > 0] / plane_depth[prior > 0])

    refitted = error(module.planar_prior(noisy, cost, K, labels=labels)[0])
    monkeypatch.setattr(module, "REGION_REFITS", 0)
    hypothesis = error(module.planar_prior(noisy, cost, K, labels=labels)[0])
    assert refitted < 0.0003  # the pixels scatter by 0.3 %; their plane is the surface's
    assert hypothesis > 3 * refitted


def test_a_region_the_filter_emptied_gets_no_plane():
    """Where most of a region has no estimate (open sky after the filter), the few pixels left
    agreeing on a plane are no consensus of the region."""
    from dvpmvs.patchmatch.planar_prior import REGION_CONSENSUS, planar_prior

    depth, cost, _, _, rng = _plain_surface(1.0, seed=9)
    labels = np.ones(depth.shape, np.int32)
    kept = rng.random(depth.shape) < REGION_CONSENSUS * 0.8
    assert not (planar_prior(np.where(kept, depth, 0), cost, K, labels=labels)[0] > 0).any()
    kept = rng.random(depth.shape) < REGION_CONSENSUS * 1.5
    assert (planar_prior(np.where(kept, depth, 0), cost, K, labels=labels)[0] > 0).mean() > 0.99


def test_a_region_plane_stays_where_the_region_holds_it(monkeypatch):
    """A region the segmentation merged across a silhouette, a plain wall below the plain sky:
    the wall's plane, held on the wall, is not carried into the sky, whose pixels hold none."""
    import dvpmvs.patchmatch.planar_prior as module

    # Taller than plane_scene, so that sky rows lie beyond REGION_LOCAL_WINDOW of the wall.
    h, w, sky = 200, 80, 80
    rows, cols = np.mgrid[0:h, 0:w]
    normal = np.array([0.2, -0.1, -1.0]) / np.linalg.norm([0.2, -0.1, -1.0])
    wall = depth_of_plane(K, normal, np.array([0.0, 0.0, 4.0]), rows, cols).astype(np.float32)
    rng = np.random.default_rng(10)
    on = rng.random((h, w)) < 0.6
    depth = np.where(on, wall, wall * rng.uniform(0.7, 1.4, (h, w))).astype(np.float32)
    depth[:sky] = wall[:sky] * rng.uniform(1.5, 3.0, (sky, w))
    cost = rng.uniform(0.3, 0.9, (h, w)).astype(np.float32)
    labels = np.ones((h, w), np.int32)
    prior = module.planar_prior(depth, cost, K, labels=labels)[0]
    assert (prior[sky:] > 0).mean() > 0.99
    np.testing.assert_allclose(prior[sky:], wall[sky:], rtol=2e-3)
    reach = sky - module.REGION_LOCAL_WINDOW // 2  # rows whose window holds no wall pixel
    assert reach > 0 and not (prior[:reach] > 0).any()
    monkeypatch.setattr(module, "REGION_LOCAL_SHARE", 0.0)
    assert (module.planar_prior(depth, cost, K, labels=labels)[0][:reach] > 0).all()
