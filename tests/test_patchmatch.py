"""The PatchMatch kernels against NumPy references, and the estimator on a rendered scene."""

from dataclasses import replace

import cv2
import numpy as np
import pytest

from dvpmvs.maps import Pass
from dvpmvs.patchmatch import (PatchMatchOptions, Problem, ViewData, estimate, hypothesis_costs, pyramid_sizes,
                               scale_intrinsics, upsample_planes)
from dvpmvs.patchmatch import _anchors, _patchmatch
from dvpmvs.patchmatch.region_plane import region_planes

K = np.array([[70.0, 0, 39.5], [0, 72.0, 29.5], [0, 0, 1]])


def _rays(K, rows, cols):
    """K^-1 (col, row, 1) of pixels (rows, cols): depth times it is the camera-frame point."""
    return np.stack([cols, rows, np.ones_like(cols)], -1).astype(np.float64) @ np.linalg.inv(K).T


def _plane_depth(K, normal, point, rows, cols):
    """Depth along the rays of pixels (rows, cols) of the plane through ``point`` with ``normal``."""
    return float(np.dot(normal, point)) / (_rays(K, rows, cols) @ normal)


def _texture(shape, seed):
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), 1.2)


def _rotation(axis, degrees):
    return cv2.Rodrigues(np.asarray(axis, np.float64) * np.deg2rad(degrees))[0]


def _plane_scene(depth=4.0, normal=(0.2, -0.1, -1.0), num_sources=2, seed=0):
    """A textured plane seen by a reference camera (identity pose) and sources rendered from it
    with the exact plane-induced warp, so the true plane is the best hypothesis."""
    n = np.asarray(normal, np.float64)
    n /= np.linalg.norm(n)
    h, w = 60, 80
    ref = _texture((h, w), seed)
    sources = []
    for j in range(num_sources):
        R = _rotation((0, 1, 0.2), 3.0 * (j + 1))
        t = np.array([0.3 * (j + 1), 0.05 * j, 0.02])
        # Source pixel -> reference pixel through the plane n.X = n.(depth * ray(centre)).
        centre = depth * np.linalg.inv(K) @ np.array([w / 2, h / 2, 1.0])
        d = n @ centre  # plane: n.X = d in the reference camera
        H_ref_to_src = K @ (R + np.outer(t, n) / d) @ np.linalg.inv(K)
        src = cv2.warpPerspective(ref, H_ref_to_src, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        sources.append(ViewData(f"s{j}", src, K, R, t))
    reference = ViewData("ref", ref, K, np.eye(3), np.zeros(3))
    rows, cols = np.mgrid[0:h, 0:w]
    plane_depth = _plane_depth(K, n, centre, rows, cols).astype(np.float32)
    normals = np.broadcast_to(n.astype(np.float32), (h, w, 3)).copy()
    return Problem(reference, sources, (2.0, 8.0)), plane_depth, normals


def _numpy_cost(problem, depth, normal, row, col, options, window_at=None, step=None):
    """Independent reference: ray-plane intersection per window sample, projection, bilinear
    sampling with border clamping, bilateral-weighted NCC. The plane is (row, col)'s; the window
    is centred on ``window_at`` (default (row, col); an anchor for a deformed pixel) and sampled
    every ``step`` pixels (default ``options.window_step``)."""
    ref = problem.reference
    Kinv = np.linalg.inv(ref.K)
    X = depth[row, col] * Kinv @ np.array([col, row, 1.0])
    n = normal[row, col].astype(np.float64)
    r = options.window_radius
    offsets = range(-r, r + 1, step or options.window_step)
    wrow, wcol = window_at or (row, col)
    out = []
    for src in problem.sources:
        h, w = src.image.shape
        R = src.R @ ref.R.T
        t = src.t - R @ ref.t
        centre = src.K @ (R @ X + t)
        cx, cy = centre[:2] / centre[2]
        if not (0 <= cx <= w - 1 and 0 <= cy <= h - 1):
            out.append(2.0)
            continue
        rv, sv, wt = [], [], []
        for dy in offsets:
            for dx in offsets:
                x, y = wcol + dx, wrow + dy
                if not (0 <= x < ref.image.shape[1] and 0 <= y < ref.image.shape[0]):
                    continue
                ray = Kinv @ np.array([x, y, 1.0])
                P = ray * (n @ X) / (n @ ray)
                q = src.K @ (R @ P + t)
                u, v = np.clip(q[0] / q[2], 0, w - 1), np.clip(q[1] / q[2], 0, h - 1)
                u0, v0 = int(u), int(v)
                u1, v1 = min(u0 + 1, w - 1), min(v0 + 1, h - 1)
                a, b = u - u0, v - v0
                img = src.image
                s = (1 - b) * ((1 - a) * img[v0, u0] + a * img[v0, u1]) + b * ((1 - a) * img[v1, u0] + a * img[v1, u1])
                value = ref.image[y, x]
                colour = (value - ref.image[wrow, wcol]) ** 2 / (2 * options.sigma_color ** 2)
                rv.append(value)
                sv.append(s)
                wt.append(np.exp(-(dx * dx + dy * dy) / (2 * options.sigma_spatial ** 2) - colour))
        rv, sv, wt = map(np.asarray, (rv, sv, wt))
        wt = wt / wt.sum()
        mr, ms = wt @ rv, wt @ sv
        cov = wt @ (rv * sv) - mr * ms
        var_r, var_s = wt @ (rv * rv) - mr * mr, wt @ (sv * sv) - ms * ms
        out.append(float(np.clip(1 - cov / np.sqrt(var_r * var_s), 0, 2)))
    return np.array(out)


def test_kernel_cost_matches_a_numpy_reference():
    problem, plane_depth, normals = _plane_scene()
    options = PatchMatchOptions()
    rng = np.random.default_rng(1)
    depth = (plane_depth * rng.uniform(0.95, 1.05, plane_depth.shape)).astype(np.float32)
    normal = normals + rng.normal(0, 0.1, normals.shape).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    pixels = np.array([[30, 40], [5, 7], [0, 0], [59, 79], [12, 70], [45, 20]], np.int32)
    got = hypothesis_costs(problem, depth, normal, pixels, options)
    want = np.array([_numpy_cost(problem, depth, normal, r, c, options) for r, c in pixels])
    assert got.shape == (len(pixels), 2)
    np.testing.assert_allclose(got, want, atol=2e-4)
    assert (got < 2).sum() >= 8  # most cases are real NCC evaluations, not the out-of-image cost


def test_true_plane_has_the_lowest_cost():
    problem, plane_depth, normals = _plane_scene()
    pixels = np.array([[r, c] for r in range(15, 45, 6) for c in range(20, 60, 8)], np.int32)
    true_cost = hypothesis_costs(problem, plane_depth, normals, pixels)
    assert true_cost.mean() < 0.05
    # Disparity is ~5 px per source at this depth: 20 % off moves the patch by ~1 px.
    for factor in (0.8, 1.25):
        wrong = hypothesis_costs(problem, plane_depth * factor, normals, pixels)
        assert (wrong > true_cost).mean() > 0.95 and wrong.mean() > true_cost.mean() + 0.1


def _noisy(problem, sigma, seed):
    rng = np.random.default_rng(seed)

    def noisy(view):
        image = (view.image + rng.normal(0, sigma, view.image.shape)).astype(np.float32)
        return ViewData(view.name, image, view.K, view.R, view.t, view.depth)

    return Problem(noisy(problem.reference), [noisy(v) for v in problem.sources], problem.depth_range)


def test_image_sigma_matches_the_smoothed_images():
    from dvpmvs.image import smooth_untextured

    problem, plane_depth, normals = _plane_scene()
    problem = _noisy(problem, 0.03, 5)

    def smoothed(view):
        return ViewData(view.name, smooth_untextured(view.image, 1.0, 2.0), view.K, view.R, view.t, view.depth)

    smooth = Problem(smoothed(problem.reference), [smoothed(v) for v in problem.sources], problem.depth_range)
    pixels = np.array([[r, c] for r in range(5, 55, 7) for c in range(4, 76, 9)], np.int32)
    options = PatchMatchOptions(image_sigma=1.0, image_noise_scale=2.0)
    got = hypothesis_costs(problem, plane_depth, normals, pixels, options)
    as_they_are = PatchMatchOptions(image_sigma=0.0)
    np.testing.assert_array_equal(got, hypothesis_costs(smooth, plane_depth, normals, pixels, as_they_are))
    assert not np.array_equal(got, hypothesis_costs(problem, plane_depth, normals, pixels, as_they_are))


def test_image_sigma_lowers_the_true_planes_cost_on_a_faint_texture():
    # A texture barely above the sensor noise: the raw windows are mostly noise; smoothed, the
    # true plane costs far less, and a plane 20 % off still costs more than it.
    problem, plane_depth, normals = _plane_scene()

    def faint(view):
        return ViewData(view.name, (0.5 + 0.15 * (view.image - view.image.mean())).astype(np.float32), view.K,
                        view.R, view.t, view.depth)

    problem = _noisy(Problem(faint(problem.reference), [faint(v) for v in problem.sources], problem.depth_range),
                     0.01, 6)
    pixels = np.array([[r, c] for r in range(15, 45, 6) for c in range(20, 60, 8)], np.int32)
    smoothing = PatchMatchOptions(image_sigma=1.0, image_noise_scale=1.0)
    raw = hypothesis_costs(problem, plane_depth, normals, pixels, PatchMatchOptions(image_sigma=0.0))
    smooth = hypothesis_costs(problem, plane_depth, normals, pixels, smoothing)
    assert smooth.mean() < 0.75 * raw.mean()  # measured 0.56 -> 0.36
    for factor in (0.8, 1.25):
        wrong = hypothesis_costs(problem, plane_depth * factor, normals, pixels, smoothing)
        assert (wrong > smooth).mean() > 0.9


def test_geometric_term_adds_the_clamped_reprojection_error():
    problem, plane_depth, normals = _plane_scene()
    pixels = np.array([[30, 40], [20, 25]], np.int32)
    photometric = hypothesis_costs(problem, plane_depth, normals, pixels)
    # Sources' depth maps of the true plane: consistent, so the geometric term is ~0.
    _sources_on_the_plane(problem, plane_depth, normals)
    consistent = hypothesis_costs(problem, plane_depth, normals, pixels)
    # Reference: project, read the source depth at the nearest pixel, back-project, reproject.
    expected = photometric.astype(np.float64).copy()
    for i, (row, col) in enumerate(pixels):
        X = plane_depth[row, col] * np.linalg.inv(K) @ np.array([col, row, 1.0])
        for j, src in enumerate(problem.sources):
            q = K @ (src.R @ X + src.t)
            u, v = (int(np.floor(q[0] / q[2] + 0.5)), int(np.floor(q[1] / q[2] + 0.5)))
            back = src.R.T @ (src.depth[v, u] * np.linalg.inv(K) @ np.array([u, v, 1.0]) - src.t)
            p = K @ back
            expected[i, j] += 0.2 * min(np.hypot(p[0] / p[2] - col, p[1] / p[2] - row), 3.0)
    np.testing.assert_allclose(consistent, expected, atol=1e-4)
    assert (consistent - photometric).max() < 0.2 * 0.75  # rounding to the nearest source pixel
    # Far-off source depths: the term saturates at 0.2 * 3 px.
    for src in problem.sources:
        src.depth = src.depth * 10  # ~4.7 px of epipolar displacement or more
    inconsistent = hypothesis_costs(problem, plane_depth, normals, pixels)
    np.testing.assert_allclose(inconsistent, photometric + 0.2 * 3.0, atol=1e-4)


def test_random_numbers_are_counter_based():
    a = _patchmatch.random_uniform(7, 1234, 3, 10000)
    assert np.array_equal(a, _patchmatch.random_uniform(7, 1234, 3, 10000))
    assert not np.array_equal(a, _patchmatch.random_uniform(8, 1234, 3, 10000))
    assert not np.array_equal(a, _patchmatch.random_uniform(7, 1235, 3, 10000))
    assert 0 <= a.min() and a.max() < 1 and abs(a.mean() - 0.5) < 0.01


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


def test_pyramid_sizes():
    assert pyramid_sizes(800, 600, 3, 160) == [(200, 150), (400, 300), (800, 600)]
    assert pyramid_sizes(320, 240, 3, 160) == [(160, 120), (320, 240)]
    assert pyramid_sizes(100, 80, 3, 160) == [(100, 80)]


def test_upsampling_keeps_a_slanted_plane():
    problem, plane_depth, normals = _plane_scene()
    K_coarse = scale_intrinsics(K, 0.5, 0.5)
    rows, cols = np.mgrid[0:30, 0:40]
    n = normals[0, 0].astype(np.float64)
    corner = plane_depth[0, 0] * np.linalg.inv(K) @ np.array([0, 0, 1.0])
    coarse_depth = _plane_depth(K_coarse, n, corner, rows, cols).astype(np.float32)
    depth, normal = upsample_planes(coarse_depth, normals[:30, :40], K_coarse, problem.reference.image, K)
    np.testing.assert_allclose(depth, plane_depth, rtol=1e-4)
    np.testing.assert_allclose(normal, normals, atol=1e-5)


def test_estimator_recovers_the_plane_and_is_thread_independent():
    problem, plane_depth, _ = _plane_scene(num_sources=3)
    options = PatchMatchOptions(num_scales=1, num_iterations=4, seed=3, num_threads=1, filter_min_region=0)
    one = estimate(problem, options)
    two = estimate(problem, PatchMatchOptions(**{**options.as_dict(), "num_threads": 2}))
    for a, b in ((one.depth, two.depth), (one.normal, two.normal), (one.cost, two.cost),
                 (one.visibility, two.visibility)):
        assert np.array_equal(a, b)
    inner = np.zeros(plane_depth.shape, bool)
    inner[8:-8, 8:-8] = True  # sources see the centre of the plane
    rel = np.abs(one.depth - plane_depth) / plane_depth
    assert (rel[inner] < 0.01).mean() > 0.9
    assert one.visibility.shape == (60, 80, 3)
    # What it matched, counted per level, the same on any number of threads: 4 iterations of
    # 8 propagated and a few refined hypotheses per pixel (measured: 75.1), each against at most
    # 3 sources (early stops: 2.5 windows per hypothesis on the vector path, 2.3 on the scalar
    # one), 33 samples per window (36 in an 11x11 window every 2 pixels, fewer at the borders).
    assert one.work == two.work and len(one.work) == 1
    work = one.work[0].per_pixel()
    assert 70 < work["hypotheses"] < 80 and 2.0 * work["hypotheses"] < work["windows"] < 3 * work["hypotheses"]
    assert 30 * work["windows"] < work["samples"] < 36 * work["windows"]
    assert one.hypothesis_evaluations == one.work[0].windows


def test_stage_observer_sees_every_level_and_changes_no_map():
    from dvpmvs.patchmatch.estimator import observe_stages, unobserved

    problem, _, _ = _plane_scene(num_sources=2)
    options = PatchMatchOptions(num_scales=2, min_scale_size=32, num_iterations=2, seed=1, num_threads=1)
    plain = estimate(problem, options)
    seen = []
    with observe_stages(lambda stage, depth, K: seen.append((stage.level, depth.shape, stage.name))):
        observed = estimate(problem, options)
        with unobserved():  # a depth prior's own estimate
            estimate(problem, options)
    assert np.array_equal(plain.depth, observed.depth) and np.array_equal(plain.normal, observed.normal)
    assert seen == [(0, (30, 40), "propagation"), (1, (60, 80), "start"), (1, (60, 80), "propagation"),
                    (1, (60, 80), "prior"), (1, (60, 80), "filtered")]
    estimate(problem, options)  # outside the block: no observer called
    assert len(seen) == 5


def test_estimator_rejects_bad_problems():
    problem, _, _ = _plane_scene()
    bad = problem.reference.image.copy()
    bad[3, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        ViewData("x", bad, K, np.eye(3), np.zeros(3))
    with pytest.raises(ValueError, match="cost map"):
        ViewData("x", problem.reference.image, K, np.eye(3), np.zeros(3), cost=np.zeros((3, 3)))
    costs = np.full(problem.reference.shape, np.nan)
    assert np.isinf(ViewData("x", problem.reference.image, K, np.eye(3), np.zeros(3), cost=costs).cost).all()
    with pytest.raises(ValueError, match="no source views"):
        Problem(problem.reference, [], (1, 2))
    with pytest.raises(ValueError, match="depth range"):
        Problem(problem.reference, problem.sources, (2, 1))
    with pytest.raises(ValueError, match="photometric estimate"):
        estimate(problem, PatchMatchOptions(), Pass.GEOMETRIC)


@pytest.mark.parametrize("bad", [{"window_step": 0}, {"good_cost": 1.5}, {"max_sources": 40},
                                 {"num_threads": -1}, {"perturbation": 0.001},
                                 {"window_radius": 15, "deform_centre_step": 1}, {"deform_anchor_step": 0},
                                 {"deform_anchor_step": 6}, {"image_sigma": -0.5},
                                 {"image_noise_scale": -1}, {"range_slack": 0.5},
                                 {"visibility_max_error": 3.0}, {"visibility_max_error": 0},
                                 {"aggregation_inner": 5.0}, {"aggregation_inner": 0},
                                 {"aggregation_views": 0}, {"area_max_spread": 0.5},
                                 {"area_max_plane_error": -0.1}, {"visibility_restore_radius": -1},
                                 {"deform_select_step": 6}, {"deform_select_step": -1},
                                 {"deform_select_rescore": 0}, {"deform_select_rescore": 9},
                                 {"random_depth": "log"}])
def test_options_validate_themselves(bad):
    with pytest.raises(ValueError):
        PatchMatchOptions(**bad)


def test_options_from_mapping_names_unknown_keys():
    with pytest.raises(ValueError, match="num_iteration"):
        PatchMatchOptions.from_mapping({"num_iteration": 3})


def test_planar_prior_reproduces_a_plane_from_its_reliable_pixels():
    from dvpmvs.patchmatch.planar_prior import planar_prior, support_pixels

    _, plane_depth, normals = _plane_scene()
    rng = np.random.default_rng(2)
    cost = rng.uniform(0.5, 1.0, plane_depth.shape).astype(np.float32)
    reliable = rng.random(plane_depth.shape) < 0.05
    cost[reliable] = 0.05
    support = support_pixels(plane_depth, cost, grid=5, max_cost=0.2)
    assert len(support) > 20 and (cost[support[:, 0], support[:, 1]] < 0.2).all()
    # Each support pixel is the cheapest of its 5x5 cell.
    r, c = support[0]
    cell = cost[r // 5 * 5: r // 5 * 5 + 5, c // 5 * 5: c // 5 * 5 + 5]
    assert cost[r, c] == cell.min()
    depth = np.where(reliable, plane_depth, 0).astype(np.float32)  # only the reliable pixels known
    prior_depth, prior_normal = planar_prior(depth, normals, cost, K, (2.0, 8.0))
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
    depth[:, w // 2:] = 5.0
    labels = np.ones((h, w), np.int32)
    labels[:, w // 2:] = 2
    normals = np.zeros((h, w, 3), np.float32)
    normals[..., 2] = -1
    cost = np.random.default_rng(4).uniform(0.0, 0.05, (h, w)).astype(np.float32)
    spanning, _ = planar_prior(depth, normals, cost, K, (1.0, 8.0))
    wrong = (spanning > 0) & (np.abs(spanning - depth) > 1e-3)
    assert wrong.sum() > 20  # triangles across the depth edge put planes in thin air
    regional, _ = planar_prior(depth, normals, cost, K, (1.0, 8.0), labels=labels)
    covered = regional > 0
    assert covered.mean() > 0.8
    np.testing.assert_allclose(regional[covered], depth[covered], rtol=1e-4)


def test_planar_prior_needs_three_support_pixels():
    from dvpmvs.patchmatch.planar_prior import planar_prior

    depth = np.full((20, 20), 3.0, np.float32)
    cost = np.ones((20, 20), np.float32)
    cost[2, 2] = cost[10, 10] = 0.0
    prior_depth, _ = planar_prior(depth, np.zeros((20, 20, 3), np.float32), cost, K, (1.0, 5.0))
    assert not (prior_depth > 0).any()


# -- deformable PatchMatch --------------------------------------------------------------------

def _sector(dr, dc):
    """The 45-degree sector (0..7, angle measured from +col towards +row) of an offset."""
    return int(np.round(np.arctan2(dr, dc) / (np.pi / 4))) % 8


def test_anchors_never_cross_a_region_border():
    rng = np.random.default_rng(3)
    h, w = 90, 120
    # Regions: 4 vertical stripes and a disc, boundary pixels (label 0) between the stripes.
    labels = np.repeat((np.arange(w) // 30 + 1)[None, :], h, axis=0).astype(np.int32)
    labels[:, 29::30] = 0
    rows, cols = np.mgrid[0:h, 0:w]
    labels[(rows - 45) ** 2 + (cols - 60) ** 2 < 15 ** 2] = 9
    strong = (rng.random((h, w)) < 0.05).astype(np.uint8)
    options = PatchMatchOptions(anchor_max_distance=0.5)
    anchors = _patchmatch_find_anchors(strong, labels, options)
    found = anchors >= 0
    assert found.sum() > 10_000  # the search does find anchors
    pix_rows, pix_cols, sector = np.nonzero(found)
    q = anchors[found]
    q_rows, q_cols = q // w, q % w
    assert np.array_equal(labels[q_rows, q_cols], labels[pix_rows, pix_cols])  # eq. 9
    assert strong[q_rows, q_cols].all() and not strong[pix_rows, pix_cols].any()
    assert not found[labels == 0].any()  # boundary pixels get none
    # Each anchor lies in its own sector (within the +-15 degree search fan) and beyond the minimum distance.
    dr, dc = q_rows - pix_rows, q_cols - pix_cols
    angle = np.degrees(np.arctan2(dr, dc)) - 45.0 * sector
    angle = (angle + 180) % 360 - 180
    assert np.abs(angle).max() <= 15.0 + np.degrees(np.arctan2(1, options.anchor_min_distance))
    assert (np.hypot(dr, dc) >= options.anchor_min_distance - 0.5).all()
    # Without labels (w/o Agn) the same search crosses the borders.
    free = _patchmatch_find_anchors(strong, None, options)
    fr, fc, _ = np.nonzero(free >= 0)
    fq = free[free >= 0]
    assert (labels[fq // w, fq % w] != labels[fr, fc]).any()


def test_anchor_search_crosses_a_large_textureless_region():
    # A 300x400 region strong only along its border: the centre's anchors lie 150-200 px away,
    # found with the default reach (the whole image).
    h, w = 300, 400
    strong = np.zeros((h, w), np.uint8)
    strong[:3], strong[-3:], strong[:, :3], strong[:, -3:] = 1, 1, 1, 1
    labels = np.ones((h, w), np.int32)
    anchors = _patchmatch_find_anchors(strong, labels, PatchMatchOptions())
    centre = anchors[150, 200]
    assert (centre >= 0).all()
    rows, cols = centre // w, centre % w
    assert strong[rows, cols].all() and np.hypot(rows - 150, cols - 200).min() >= 140
    # A reach of 10 % of the side (40 px) finds nothing there.
    short = _patchmatch_find_anchors(strong, labels, PatchMatchOptions(anchor_max_distance=0.1))
    assert (short[150, 200] < 0).all()


_SEARCH_TURNS = (0.0, 1.0 / 3.0, -1.0 / 3.0)  # a sector's three lines, in 45-degree units, centre first


def _weak_region_pixels(strong, labels):
    """The pixels the anchor search serves: weak ones inside a region, with their region."""
    for row, col in np.ndindex(*strong.shape):
        own = labels[row, col] if labels is not None else 1
        if not strong[row, col] and own > 0:
            yield row, col, own


def _search_line_point(row, col, sector, turn, r):
    """The pixel r px from (row, col) on one of a sector's search lines, rounded as the kernel does."""
    angle = (sector + turn) * np.pi / 4.0
    return row + int(np.floor(r * np.sin(angle) + 0.5)), col + int(np.floor(r * np.cos(angle) + 0.5))


def _anchor_on_line(strong, labels, own, row, col, sector, turn, r):
    """That pixel, if it may be an anchor of a pixel of region ``own``."""
    qr, qc = _search_line_point(row, col, sector, turn, r)
    h, w = strong.shape
    if 0 <= qr < h and 0 <= qc < w and strong[qr, qc] and (labels is None or labels[qr, qc] == own):
        return qr, qc
    return None


def _reference_anchors(strong, labels, min_distance, max_distance, step):
    """The anchor walk written out plainly: every step from min_distance to max_distance along
    the 3 lines of each sector, nothing skipped."""
    h, w = strong.shape
    out = np.full((h, w, 8), -1, np.int32)
    for row, col, own in _weak_region_pixels(strong, labels):
        for a in range(8):
            for r in range(min_distance, max_distance + 1, step):
                hit = next((q for q in (_anchor_on_line(strong, labels, own, row, col, a, turn, r)
                                        for turn in _SEARCH_TURNS) if q is not None), None)
                if hit is not None:
                    out[row, col, a] = hit[0] * w + hit[1]
                    break
    return out


@pytest.mark.parametrize("with_labels", [True, False])
def test_anchor_search_finds_what_the_plain_walk_finds(with_labels):
    # The kernel walks only the stretch of each line inside the bounding box of the region's
    # strong pixels; it must find exactly the anchors of the walk over the whole distance,
    # including regions without strong pixels, regions wrapping around others and the image border.
    rng = np.random.default_rng(11)
    h, w = 37, 53
    rows, cols = np.mgrid[0:h, 0:w]
    labels = (1 + (cols // 13) + 5 * (rows // 19)).astype(np.int32)
    labels[((rows - 18) ** 2 + (cols - 26) ** 2 > 8 ** 2) & ((rows - 18) ** 2 + (cols - 26) ** 2 < 12 ** 2)] = 20  # a ring
    labels[rng.random((h, w)) < 0.03] = 0
    strong = (rng.random((h, w)) < 0.04).astype(np.uint8)
    strong[labels == 2] = 0  # a region with no strong pixel at all
    labels = labels if with_labels else None
    options = PatchMatchOptions(anchor_min_distance=3, anchor_step=2, anchor_max_distance=1.0)
    expected = _reference_anchors(strong, labels, 3, max(h, w), 2)
    assert (expected >= 0).sum() > 1000
    assert np.array_equal(_patchmatch_find_anchors(strong, labels, options), expected)


def _reference_area_anchors(strong, labels, min_distance, max_distance, step, max_spread, on_plane=None):
    """Paper eq. 12 written out plainly: the first strong pixel on each of a sector's three lines
    (walked over the whole distance), the nearest of them to start with (candidates farther than
    ``max_spread`` times it dropped, and with ``on_plane(nearest, q)`` those it rejects), then
    each sector in turn takes the candidate c maximising (c - p) x (next anchor - previous
    anchor), until no change."""
    h, w = strong.shape
    out = np.full((h, w, 8), -1, np.int32)
    for row, col, own in _weak_region_pixels(strong, labels):
        candidates = [[None] * 3 for _ in range(8)]
        nearest = [None] * 8
        for a in range(8):
            hits = []
            for k, turn in enumerate(_SEARCH_TURNS):
                for r in range(min_distance, max_distance + 1, step):
                    q = _anchor_on_line(strong, labels, own, row, col, a, turn, r)
                    if q is not None:
                        candidates[a][k] = q
                        hits.append((r, k))
                        break
            if hits:
                r, k = min(hits)
                nearest[a] = candidates[a][k]
                reach = max_spread * np.hypot(nearest[a][0] - row, nearest[a][1] - col)
                candidates[a] = [q if q is not None and np.hypot(q[0] - row, q[1] - col) <= reach
                                 and (on_plane is None or q == nearest[a] or on_plane(nearest[a], q)) else None
                                 for q in candidates[a]]
        anchors = list(nearest)
        for _ in range(4):
            changed = False
            for a in range(8):
                if anchors[a] is None:
                    continue
                after = [(a + m) % 8 for m in range(1, 8) if anchors[(a + m) % 8] is not None]
                if not after or after[0] == after[-1]:
                    continue
                nxt, prev = anchors[after[0]], anchors[after[-1]]
                ur, uc = nxt[0] - prev[0], nxt[1] - prev[1]
                def gain(q):
                    return (q[1] - col) * ur - (q[0] - row) * uc
                best = anchors[a]
                for q in candidates[a]:
                    if q is not None and gain(q) > gain(best):
                        best = q
                if best != anchors[a]:
                    anchors[a], changed = best, True
            if not changed:
                break
        out[row, col] = [-1 if q is None else q[0] * w + q[1] for q in anchors]
    return out


def _polygon_areas(anchors, w):
    """Twice the signed area of each pixel's anchor polygon (sectors in order, empty ones skipped)."""
    total = np.zeros(anchors.shape[:2], np.int64)
    for row, col in zip(*np.nonzero((anchors >= 0).sum(axis=2) >= 3)):
        ring = [q for q in anchors[row, col] if q >= 0]
        x = np.array([q % w for q in ring]) - col
        y = np.array([q // w for q in ring]) - row
        total[row, col] = int(np.sum(x * np.roll(y, -1) - y * np.roll(x, -1)))
    return total


@pytest.mark.parametrize("with_labels, max_spread", [(True, np.inf), (False, np.inf), (True, 1.5)])
def test_area_maximisation_grows_the_anchor_polygon(with_labels, max_spread):
    rng = np.random.default_rng(12)
    h, w = 37, 53
    rows, cols = np.mgrid[0:h, 0:w]
    labels = (1 + (cols // 17) + 4 * (rows // 19)).astype(np.int32)
    labels[rng.random((h, w)) < 0.03] = 0
    strong = (rng.random((h, w)) < 0.05).astype(np.uint8)
    labels = labels if with_labels else None
    options = PatchMatchOptions(anchor_min_distance=3, anchor_step=2, anchor_max_distance=1.0)
    nearest = _patchmatch_find_anchors(strong, labels, options)
    area = _patchmatch_find_anchors(strong, labels, replace(options, area_maximisation=True,
                                                            area_max_spread=max_spread))
    assert np.array_equal(area, _reference_area_anchors(strong, labels, 3, max(h, w), 2, max_spread))
    # The same sectors are filled; anchors move in a share of them, and every move grows the
    # polygon, so no pixel's polygon shrinks and many grow.
    assert np.array_equal(area >= 0, nearest >= 0)
    moved = (area != nearest).any(axis=2)
    assert 0.05 < moved[(nearest >= 0).sum(axis=2) >= 3].mean() < 1.0
    before, after = _polygon_areas(nearest, w), _polygon_areas(area, w)
    assert (after >= before).all() and (after[moved] > before[moved]).all()
    # With fewer than three anchors there is no polygon: the nearest anchors stay.
    few = (nearest >= 0).sum(axis=2) < 3
    assert np.array_equal(area[few], nearest[few])


def _chord_pixel():
    """Pixel (50, 50) of a 101x101 strong map. Sector 0 (east) holds a strong pixel 6 px away on
    its centre line and one 20 px away on its +15 degree line; sectors 1 and 7 hold one each,
    10 px away at +-45 degrees, and sector 4 one 10 px west. The neighbours' chord runs at column
    57: the nearest candidate (column 56) lies inside it, the far one (column 69) beyond it.
    Returns the strong map, the near and the far candidate."""
    def on_line(sector, turn, r):
        return _search_line_point(50, 50, sector, turn, r)
    strong = np.zeros((101, 101), np.uint8)
    near, far = on_line(0, 0.0, 6), on_line(0, 1.0 / 3.0, 20)
    for q in (near, far, on_line(1, 0.0, 10), on_line(7, 0.0, 10), on_line(4, 0.0, 10)):
        strong[q] = 1
    assert near == (50, 56) and far == (55, 69)
    return strong, near, far


def test_area_maximisation_takes_the_candidate_beyond_its_neighbours_chord():
    # _chord_pixel's far candidate grows the anchors' polygon; the near one does not.
    strong, near, far = _chord_pixel()
    options = PatchMatchOptions(anchor_min_distance=3, anchor_step=1)
    nearest = _patchmatch_find_anchors(strong, None, options)[50, 50]
    area = _patchmatch_find_anchors(strong, None, replace(options, area_maximisation=True))[50, 50]
    assert nearest[0] == near[0] * 101 + near[1]
    assert area[0] == far[0] * 101 + far[1]
    assert (nearest >= 0).sum() == 4
    assert np.array_equal(area[1:], nearest[1:])
    # The far candidate is 20 / 6 times as far as the nearest: a spread of 3 leaves it out.
    bounded = _patchmatch_find_anchors(strong, None, replace(options, area_maximisation=True, area_max_spread=3.0))
    assert np.array_equal(bounded[50, 50], nearest)


def test_area_maximisation_keeps_only_candidates_on_the_nearest_anchors_plane():
    # _chord_pixel on a slanted plane: the far candidate competes while it lies on the plane of
    # its sector's nearest anchor, and is left out once 2 % off it (plane_error 1 %).
    strong, near, far = _chord_pixel()
    K = np.array([[80.0, 0, 50], [0, 80, 50], [0, 0, 1]])
    n = np.array([0.4, -0.2, -1.0]) / np.linalg.norm([0.4, -0.2, -1.0])
    rows, cols = np.mgrid[0:101, 0:101]
    depth = _plane_depth(K, n, np.array([0.0, 0.0, 3.0]), rows, cols).astype(np.float32)
    normal = np.ascontiguousarray(np.broadcast_to(n, (101, 101, 3)), np.float32)
    from dvpmvs.patchmatch.estimator import find_anchors
    options = PatchMatchOptions(anchor_min_distance=3, anchor_step=1, area_maximisation=True)
    def anchor(plane_error, depth):
        return find_anchors(strong, None, replace(options, area_max_plane_error=plane_error), 2, depth, normal, K)[50, 50, 0]
    assert anchor(0.01, depth) == far[0] * 101 + far[1]
    off = depth.copy()
    off[far] *= 1.02
    assert anchor(0.01, off) == near[0] * 101 + near[1]
    assert anchor(0.03, off) == far[0] * 101 + far[1]
    assert anchor(np.inf, off) == far[0] * 101 + far[1]  # no check
    off[far] = 0  # no depth: not on any plane
    assert anchor(0.5, off) == near[0] * 101 + near[1]
    # Nor is any candidate where the nearest anchor has no plane (no depth, no normal).
    unknown = depth.copy()
    unknown[near] = 0
    normal[near] = 0
    assert anchor(0.5, unknown) == near[0] * 101 + near[1]
    with pytest.raises(ValueError, match="needs depth"):
        find_anchors(strong, None, replace(options, area_max_plane_error=0.01), 2)


def test_area_maximisation_plane_check_matches_the_plain_walk():
    rng = np.random.default_rng(13)
    h, w = 37, 53
    rows, cols = np.mgrid[0:h, 0:w]
    labels = (1 + (cols // 17) + 4 * (rows // 19)).astype(np.int32)
    strong = (rng.random((h, w)) < 0.05).astype(np.uint8)
    K = np.array([[40.0, 0, 26], [0, 40, 18], [0, 0, 1]])
    # Piecewise planes with noise: some candidates on their nearest anchor's plane, some off.
    normal = rng.normal(size=(h, w, 3)) * 0.2 + [0, 0, -1]
    normal[labels % 2 == 0] = [0.3, 0.1, -1]
    normal = (normal / np.linalg.norm(normal, axis=2, keepdims=True)).astype(np.float32)
    depth = (_plane_depth(K, np.array([0.3, 0.1, -1]), np.array([0.0, 0.0, 2.0]), rows, cols)
             * (1 + 0.02 * rng.random((h, w)) * (labels % 3 == 0))).astype(np.float32)
    K_inv = np.linalg.inv(K).astype(np.float32).astype(np.float64)
    def on_plane(a, q):
        # The depth on q's ray of the plane through a's point with a's normal, 1 % of q's depth.
        ray_a, ray_q = (K_inv @ [a[1], a[0], 1]), (K_inv @ [q[1], q[0], 1])
        na = normal[a].astype(np.float64)
        plane = depth[a] * (na @ ray_a) / (na @ ray_q)
        return depth[q] > 0 and plane > 0 and abs(plane - depth[q]) <= 0.01 * depth[q]
    from dvpmvs.patchmatch.estimator import find_anchors
    options = PatchMatchOptions(anchor_min_distance=3, anchor_step=2, anchor_max_distance=1.0,
                                area_maximisation=True)
    checked = find_anchors(strong, labels, replace(options, area_max_plane_error=0.01), 2, depth, normal, K)
    assert np.array_equal(checked, _reference_area_anchors(strong, labels, 3, max(h, w), 2, np.inf, on_plane))
    free = find_anchors(strong, labels, options, 2)
    assert 0 < (checked != free).sum() < (free != _patchmatch_find_anchors(strong, labels, replace(
        options, area_maximisation=False))).sum()


def _kernel_state(depth, normal, num_sources, selected=0):
    """The kernel's per-pixel state around a plane map: (depth, normal, cost, per-source costs,
    per-source weights, selected sources), the costs and weights zero; ``selected`` a bit mask
    per pixel, or one for every pixel."""
    h, w = depth.shape
    return (depth, normal, np.zeros((h, w), np.float32), np.zeros((h, w, num_sources), np.float32),
            np.zeros((h, w, num_sources), np.float32), np.array(np.broadcast_to(selected, (h, w)), np.uint32))


def _patchmatch_find_anchors(strong, labels, options):
    from dvpmvs.patchmatch.estimator import find_anchors
    return find_anchors(strong, labels, options, 2)


def test_deformed_cost_mixes_centre_and_anchor_windows():
    """With anchors set, a pixel's cost is lambda * centre window (stride 5) + (1 - lambda) *
    mean of its anchors' windows, all warped with the pixel's plane; on the exact plane of a
    textured scene it stays near 0, and a wrong depth raises it."""
    problem, depth, normal = _plane_scene(num_sources=2)
    h, w = problem.reference.shape
    from dvpmvs.patchmatch.estimator import _kernel_params, _Level
    options = PatchMatchOptions(num_threads=1)
    level = _Level.build(problem, 1.0, use_depth=False)
    S = len(problem.sources)
    state = _kernel_state(depth.copy(), normal.copy(), S)
    params = _kernel_params(problem, options)
    anchors = np.full((h, w, 8), -1, np.int32)
    anchors[30, 40, :4] = [30 * w + 50, 20 * w + 40, 30 * w + 30, 40 * w + 40]
    _patchmatch.initialise(*level.args, *state, params, False, S, 1, anchors)
    deformed_true = state[2][30, 40]
    wrong = (depth * 1.5).astype(np.float32)
    state_wrong = (wrong, normal.copy()) + tuple(np.zeros_like(a) for a in state[2:])
    _patchmatch.initialise(*level.args, *state_wrong, params, False, S, 1, anchors)
    assert deformed_true < 0.1 and state_wrong[2][30, 40] > deformed_true + 0.3
    # The undeformed pixels' costs do not change when anchors are given to another pixel.
    plain = (depth.copy(), normal.copy()) + tuple(np.zeros_like(a) for a in state[2:])
    _patchmatch.initialise(*level.args, *plain, params, False, S, 1, None)
    mask = np.ones((h, w), bool)
    mask[30, 40] = False
    assert np.array_equal(plain[2][mask], state[2][mask])
    assert plain[2][30, 40] != deformed_true


@pytest.mark.parametrize("anchor_step", [2, 5])
def test_deformed_cost_matches_a_numpy_reference(anchor_step):
    """Eq. 3 per source: lambda * the centre window sampled every deform_centre_step pixels +
    (1 - lambda) * the mean over anchors of their windows sampled every deform_anchor_step
    pixels, every window warped with the pixel's own plane (here a slightly wrong one, so the
    windows' costs differ, the more so the further a window lies from the pixel)."""
    problem, depth, normal = _plane_scene(num_sources=2)
    h, w = problem.reference.shape
    from dvpmvs.patchmatch.estimator import _kernel_params, _Level
    options = PatchMatchOptions(num_threads=1, deform_anchor_step=anchor_step)
    level = _Level.build(problem, 1.0, use_depth=False)
    S = len(problem.sources)
    wrong = (depth * 1.04).astype(np.float32)
    tilted = normal + np.array([0.3, 0.1, 0.0], np.float32)
    tilted /= np.linalg.norm(tilted, axis=-1, keepdims=True)
    state = _kernel_state(wrong, tilted, S)
    anchors = np.full((h, w, 8), -1, np.int32)
    at = [(30, 50), (20, 40), (30, 28), (42, 41)]
    anchors[30, 40, :4] = [r * w + c for r, c in at]
    _patchmatch.initialise(*level.args, *state, _kernel_params(problem, options), False, S, 1, anchors)
    centre = _numpy_cost(problem, wrong, tilted, 30, 40, options, step=options.deform_centre_step)
    windows = [_numpy_cost(problem, wrong, tilted, 30, 40, options, window_at=a, step=anchor_step) for a in at]
    expected = options.deform_lambda * centre + (1 - options.deform_lambda) * np.mean(windows, axis=0)
    assert np.ptp(windows) > 0.1  # the windows disagree, so a wrong window or sampling would show
    np.testing.assert_allclose(state[3][30, 40], expected, atol=2e-4)


def test_anchor_visibility_matches_each_window_only_where_its_anchor_is_seen():
    """Paper eq. 10-11: in source j the mean runs over the anchors visible in j; a source that
    sees none of them is judged by the centre window alone; all-visible masks change nothing."""
    problem, depth, normal = _plane_scene(num_sources=2)
    h, w = problem.reference.shape
    from dvpmvs.patchmatch.estimator import _kernel_params, _Level
    options = PatchMatchOptions(num_threads=1)
    level = _Level.build(problem, 1.0, use_depth=False)
    S = len(problem.sources)
    wrong = (depth * 1.04).astype(np.float32)
    tilted = normal + np.array([0.3, 0.1, 0.0], np.float32)
    tilted /= np.linalg.norm(tilted, axis=-1, keepdims=True)
    anchors = np.full((h, w, 8), -1, np.int32)
    at = [(30, 50), (20, 40), (30, 28), (42, 41)]
    anchors[30, 40, :4] = [r * w + c for r, c in at]
    params = _kernel_params(problem, options)

    def view_costs(visible):
        state = _kernel_state(wrong.copy(), tilted.copy(), S)
        _patchmatch.initialise(*level.args, *state, params, False, S, 1, anchors, visible)
        return state[3]

    visible = np.zeros((h, w), np.uint32)
    for (r, c), mask in zip(at, (0b01, 0b01, 0b11, 0b00)):
        visible[r, c] = mask
    costs = view_costs(visible)[30, 40]
    centre = _numpy_cost(problem, wrong, tilted, 30, 40, options, step=options.deform_centre_step)
    windows = np.array([_numpy_cost(problem, wrong, tilted, 30, 40, options, window_at=a,
                                    step=options.deform_anchor_step) for a in at])
    lam = options.deform_lambda
    expected = [lam * centre[0] + (1 - lam) * windows[:3, 0].mean(), lam * centre[1] + (1 - lam) * windows[2, 1]]
    np.testing.assert_allclose(costs, expected, atol=2e-4)
    np.testing.assert_allclose(view_costs(np.zeros((h, w), np.uint32))[30, 40], centre, atol=2e-4)
    assert np.array_equal(view_costs(np.full((h, w), 0b11, np.uint32)), view_costs(None))


def _pixel_rays(h, w):
    rows, cols = np.mgrid[0:h, 0:w]
    return rows, cols, _rays(K, rows, cols)


def _sources_on_the_plane(problem, depth, normal):
    """Give each source of a ``_plane_scene`` the true plane's depth map in its camera."""
    rows, cols, rays = _pixel_rays(*problem.reference.shape)
    corner = depth[0, 0] * rays[0, 0]
    for src in problem.sources:
        src.depth = _plane_depth(K, src.R @ normal[0, 0], src.R @ corner + src.t, rows, cols).astype(np.float32)


def test_visible_sources_adds_the_reprojection_consistent_ones():
    """A pixel is visible in its selected sources and, with the sources' depth maps, in those
    where its forward-backward reprojection error is at most the threshold (NumPy reference)."""
    problem, depth, normal = _plane_scene(num_sources=2)
    h, w = problem.reference.shape
    from dvpmvs.patchmatch.estimator import _kernel_params, _Level
    rows, cols, rays = _pixel_rays(h, w)
    _sources_on_the_plane(problem, depth, normal)
    # The reference depth a little off the plane, more to the right: errors from 0 to several px.
    ref_depth = (depth * (1 + 0.08 * cols / w)).astype(np.float32)
    ref_depth[:5] = 0  # no depth: visible nowhere
    errors = np.full((h, w, 2), np.inf)
    for j, src in enumerate(problem.sources):
        q = (ref_depth[..., None] * rays) @ src.R.T + src.t
        q = q @ K.T
        u = np.floor(q[..., 0] / q[..., 2] + 0.5).astype(int)
        v = np.floor(q[..., 1] / q[..., 2] + 0.5).astype(int)
        inside = (u >= 0) & (v >= 0) & (u < w) & (v < h) & (ref_depth > 0)
        ds = src.depth[v[inside], u[inside]]
        back = (ds[:, None] * np.stack([u[inside], v[inside], np.ones_like(ds)], -1) @ np.linalg.inv(K).T
                - src.t) @ src.R
        p = back @ K.T
        errors[inside, j] = np.hypot(p[:, 0] / p[:, 2] - cols[inside], p[:, 1] / p[:, 2] - rows[inside])
    options = PatchMatchOptions(num_threads=2)
    S = len(problem.sources)

    def masks(use_depth, selected):
        level = _Level.build(problem, 1.0, use_depth=use_depth)
        state = _kernel_state(ref_depth, normal.copy(), S, selected)
        visible = np.zeros((h, w), np.uint32)
        _patchmatch.visible_sources(*level.args, *state, _kernel_params(problem, options), visible, 2.0, 2)
        return visible

    geometric = masks(True, 0)
    for j in range(S):
        seen = (geometric >> j) & 1 == 1
        clear = np.abs(errors[..., j] - 2.0) > 1e-3  # rounding aside
        assert np.array_equal(seen[clear], errors[..., j][clear] <= 2.0)
        assert 0.1 < seen.mean() < 0.9  # the threshold splits the image
    assert np.array_equal(masks(True, 0b10), np.where(ref_depth > 0, geometric | 0b10, 0))
    # Without depth maps (the photometric pass) only the selection counts.
    assert np.array_equal(masks(False, 0b01), np.where(ref_depth > 0, 1, 0))


def test_visibility_restoration_reprojects_with_the_lowest_cost_depth_nearby():
    """Paper section 3.4: the projected source pixel goes back with the depth of the lowest-cost
    pixel of the window around it. Sources whose depth maps hold outliers on every other pixel
    (a checkerboard, twice too far): on the true plane, the plain reprojection fails wherever the
    projection meets an outlier, the restoration (radius 1) finds a true depth in every 3x3
    window where the outliers cost more, and meets an outlier in every one where they cost less."""
    problem, depth, normal = _plane_scene(num_sources=2)
    h, w = problem.reference.shape
    from dvpmvs.patchmatch.estimator import _kernel_params, _Level
    rows, cols, _ = _pixel_rays(h, w)
    _sources_on_the_plane(problem, depth, normal)
    outlier = (rows + cols) % 2 == 1
    true_depths = [src.depth for src in problem.sources]
    S = len(problem.sources)
    options = PatchMatchOptions(num_threads=2)

    def masks(outlier_cost, radius, outliers=True, true_cost=0.1):
        for src, true_depth in zip(problem.sources, true_depths):
            src.depth = np.where(outlier & outliers, 2.0 * true_depth, true_depth).astype(np.float32)
            src.cost = None if outlier_cost is None else np.where(outlier, outlier_cost, true_cost).astype(np.float32)
        level = _Level.build(problem, 1.0, use_depth=True)
        visible = np.zeros((h, w), np.uint32)
        _patchmatch.visible_sources(*level.args, *_kernel_state(depth.copy(), normal.copy(), S),
                                    _kernel_params(problem, options), visible, 2.0, 2, level.src_cost, radius)
        return np.stack([(visible >> j) & 1 == 1 for j in range(S)], -1)

    clean = masks(None, 0, outliers=False)  # where the projections stay inside the sources
    plain, restored, misled = masks(None, 0), masks(1.5, 1), masks(0.05, 1)
    assert clean.mean() > 0.7
    assert 0.3 < plain[clean].mean() < 0.7
    assert np.array_equal(restored, clean)
    assert misled[clean].mean() < 0.05  # every 3x3 window holds a cheaper outlier
    # Radius 0 is the projected pixel itself: the plain reprojection, whatever the costs; so is
    # a window without known costs, and ties keep the projected pixel's depth.
    assert np.array_equal(masks(1.5, 0), plain)
    assert np.array_equal(masks(np.inf, 1, true_cost=np.inf), plain)
    assert np.array_equal(masks(0.1, 1), plain)
    with pytest.raises(ValueError, match="src_cost"):
        level = _Level.build(problem, 1.0, use_depth=True)
        _patchmatch.visible_sources(*level.args[:-1], None, *_kernel_state(depth.copy(), normal.copy(), S),
                                    _kernel_params(problem, options), np.zeros((h, w), np.uint32), 2.0, 2,
                                    level.src_cost, 1)


def _geometry_scene(seed=0):
    """A reference camera and 4 sources with baselines of 0.2-0.8 at 4-6 m and a focal length
    of 700 px, so that every epipolar line runs far beyond 5 px on both sides of each point;
    random depths and normals facing the reference camera."""
    rng = np.random.default_rng(seed)
    h, w = 30, 40
    K700 = np.array([[700.0, 0, 19.5], [0, 700.0, 14.5], [0, 0, 1]])
    image = _texture((h, w), seed)
    sources = [ViewData(f"s{j}", image, K700, _rotation((0.1, 1, 0.3), (-1) ** j * 2.0 * (j + 1)),
                        np.array([0.2 * (j + 1) * (-1) ** j, 0.1 * j, 0.05])) for j in range(4)]
    problem = Problem(ViewData("ref", image, K700, np.eye(3), np.zeros(3)), sources, (2.0, 8.0))
    depth = rng.uniform(4.0, 6.0, (h, w)).astype(np.float32)
    normal = rng.normal(size=(h, w, 3))
    normal[..., 2] = -np.abs(normal[..., 2]) - 0.2
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return problem, depth, normal.astype(np.float32), K700


def _geometry_constraints(problem, depth, normal, selected, **params):
    from dvpmvs.patchmatch.estimator import _kernel_params, _Level
    h, w = depth.shape
    S = len(problem.sources)
    level = _Level.build(problem, 1.0, use_depth=False)
    state = _kernel_state(depth, normal, S, selected)
    intervals = np.zeros((h, w, 4), np.float32)
    facing = np.zeros((h, w), np.uint8)
    _patchmatch.geometry_constraints(*level.args, *state, _kernel_params(problem, PatchMatchOptions(**params)),
                                     intervals, facing, 2)
    return intervals, facing


def test_depth_aggregation_intervals_move_the_point_along_the_epipolar_lines():
    """Paper section 3.5 (NumPy reference): the near and far intervals are those of the mu-th
    most sensitive selected source on each side. At an inner end at least mu of the pixel's
    selected sources move its point by >= alpha px along their epipolar lines, one of them by
    exactly alpha; at an outer end that one moves it by alpha + beta, and at least (sources -
    mu + 1) by <= alpha + beta."""
    problem, depth, normal, K700 = _geometry_scene()
    h, w = depth.shape
    rng = np.random.default_rng(1)
    selected = rng.integers(0, 16, (h, w)).astype(np.uint32)
    alpha, outer, mu = 1.5, 6.0, 2
    intervals, _ = _geometry_constraints(problem, depth, normal, selected, aggregation_inner=alpha,
                                         aggregation_outer=outer, aggregation_views=mu)
    rows, cols = np.mgrid[0:h, 0:w]
    rays = _rays(K700, rows, cols)

    def moved(t):  # (h, w, 4): how far source j sees the point move from depth to depth t
        out = np.zeros((h, w, 4))
        for j, src in enumerate(problem.sources):
            def project(z):
                q = (z[..., None] * rays) @ src.R.T + src.t
                q = q @ K700.T
                return q[..., :2] / q[..., 2:]
            out[..., j] = np.linalg.norm(project(t.astype(np.float64)) - project(depth.astype(np.float64)), axis=-1)
        return out

    count = np.stack([(selected >> j) & 1 for j in range(4)], -1).astype(bool)
    none = count.sum(-1) == 0
    assert np.all(intervals[none] == 0)
    has = ~none
    near_lo, near_hi, far_lo, far_hi = (intervals[..., k] for k in range(4))
    assert np.all((near_lo < near_hi)[has] & (near_hi < depth)[has] & (depth < far_lo)[has] & (far_lo < far_hi)[has])
    mu_ = np.minimum(mu, count.sum(-1))
    for inner, outer_end in ((near_hi, near_lo), (far_lo, far_hi)):
        m_in, m_out = moved(np.where(has, inner, depth)), moved(np.where(has, outer_end, depth))
        assert np.all((((m_in >= alpha - 1e-2) & count).sum(-1) >= mu_)[has])
        assert np.all((((m_out <= outer + 1e-2) & count).sum(-1) >= count.sum(-1) - mu_ + 1)[has])
        # One source, the same at both ends, moves by exactly alpha and alpha + beta.
        assert np.all(((np.abs(m_in - alpha) < 1e-2) & (np.abs(m_out - outer) < 1e-2) & count).any(-1)[has])


def test_normal_aggregation_keeps_planes_that_face_every_selected_source():
    """A plane faces a source when n . (P - C_j) <= 0 (NumPy reference, the sources' centres
    from their poses); only the selected sources count."""
    problem, depth, normal, K700 = _geometry_scene(seed=2)
    h, w = depth.shape
    # Planes seen at grazing angles from the reference camera, so that the sources' few degrees
    # of parallax put some of them behind.
    normal[..., 2] = -np.random.default_rng(4).uniform(0.0, 0.2, (h, w))
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    selected = np.random.default_rng(3).integers(0, 16, (h, w)).astype(np.uint32)
    _, facing = _geometry_constraints(problem, depth, normal, selected)
    rows, cols = np.mgrid[0:h, 0:w]
    points = depth[..., None] * _rays(K700, rows, cols)
    dots = np.stack([np.sum(normal * (points + src.R.T @ src.t), -1) for src in problem.sources], -1)
    chosen = np.stack([(selected >> j) & 1 for j in range(4)], -1).astype(bool)
    expected = np.all(~chosen | (dots <= 0), -1)
    clear = np.all(np.abs(dots) > 1e-4, -1)
    assert np.array_equal(facing.astype(bool)[clear], expected[clear])
    assert 0.2 < expected.mean() < 0.9  # the random normals face some sources and not others


@pytest.mark.parametrize("switch", ["normal_aggregation", "depth_aggregation"])
def test_estimator_with_geometry_driven_refinement_is_deterministic_and_accurate(switch):
    problem, depth, normal = _plane_scene(num_sources=3)
    problem.labels = np.ones(problem.reference.shape, np.int32)
    options = PatchMatchOptions(num_scales=1, num_iterations=2, seed=5, strong_max_cost=0.05, **{switch: True})
    one, two = (estimate(problem, PatchMatchOptions(**{**options.as_dict(), "num_threads": t})) for t in (1, 2))
    assert np.array_equal(one.depth, two.depth) and np.array_equal(one.normal, two.normal)
    plain = estimate(problem, PatchMatchOptions(**{**options.as_dict(), switch: False}))
    if switch == "normal_aggregation":  # planes the sources would see from behind go unscored
        assert one.hypothesis_evaluations < plain.hypothesis_evaluations
    else:  # other perturbed depths
        assert not np.array_equal(one.depth, plain.depth)
    valid = one.depth > 0
    assert valid.mean() > 0.5
    assert np.median(np.abs(one.depth[valid] - depth[valid]) / depth[valid]) < 0.01


@pytest.mark.parametrize("region_plane", [False, True])
def test_estimator_with_deformation_and_regions_is_deterministic(region_plane):
    problem, depth, normal = _plane_scene(num_sources=2)
    problem.labels = np.ones(problem.reference.shape, np.int32)
    options = PatchMatchOptions(num_scales=1, num_iterations=2, seed=5, strong_max_cost=0.05,
                                region_plane=region_plane, region_plane_min_strong=10)
    one = estimate(problem, PatchMatchOptions(**{**options.as_dict(), "num_threads": 1}))
    two = estimate(problem, PatchMatchOptions(**{**options.as_dict(), "num_threads": 2}))
    assert one.deformed is not None and one.deformed.any()
    assert np.array_equal(one.depth, two.depth)
    valid = one.depth > 0
    assert np.median(np.abs(one.depth[valid] - depth[valid]) / depth[valid]) < 0.01


def test_geometric_pass_deforms_only_with_geom_deformable():
    problem, depth, normal = _plane_scene(num_sources=2)
    problem.labels = np.ones(problem.reference.shape, np.int32)
    options = PatchMatchOptions(num_scales=1, num_iterations=2, seed=5, strong_max_cost=0.05, num_threads=2)
    photometric = estimate(problem, options)
    # Source maps only so that the geometric pass runs (the reference's, not consistent with the
    # sources' poses): this checks the deformation switch, not the reprojection term.
    for src in problem.sources:
        src.depth = photometric.depth
    problem.initial = (photometric.depth, photometric.normal)
    deformed = estimate(problem, options, Pass.GEOMETRIC)
    plain = estimate(problem, PatchMatchOptions(**{**options.as_dict(), "geom_deformable": False}), Pass.GEOMETRIC)
    assert deformed.deformed is not None and deformed.deformed.any()
    assert plain.deformed is None
    # Weak pixels match up to 8 anchor windows more (1.9x the evaluations on this plane).
    assert deformed.hypothesis_evaluations > 1.5 * plain.hypothesis_evaluations
    valid = plain.depth > 0
    assert valid.mean() > 0.5
    assert np.median(np.abs(plain.depth[valid] - depth[valid]) / depth[valid]) < 0.01



def test_estimator_with_anchor_visibility_is_deterministic_and_matches_fewer_windows():
    problem, depth, normal = _plane_scene(num_sources=4)
    problem.labels = np.ones(problem.reference.shape, np.int32)
    options = PatchMatchOptions(num_scales=1, num_iterations=2, seed=5, strong_max_cost=0.05, num_threads=2)
    every = estimate(problem, options)
    visible = [estimate(problem, PatchMatchOptions(**{**options.as_dict(), "anchor_visibility": True,
                                                     "num_threads": t})) for t in (1, 2)]
    assert np.array_equal(visible[0].depth, visible[1].depth)
    assert visible[0].deformed is not None and visible[0].deformed.any()
    # Anchors go unmatched in the sources their view selection left out.
    assert visible[0].hypothesis_evaluations < every.hypothesis_evaluations
    valid = visible[0].depth > 0
    assert valid.mean() > 0.5
    assert np.median(np.abs(visible[0].depth[valid] - depth[valid]) / depth[valid]) < 0.01


def _both_passes(problem, variants):
    """Each of ``variants`` (name -> options) run through the photometric pass, then the geometric
    pass from the first variant's photometric maps (the sources' maps shifted, so that the
    reprojection term varies)."""
    results = {}
    for pass_ in (Pass.PHOTOMETRIC, Pass.GEOMETRIC):
        if pass_ is Pass.GEOMETRIC:
            photometric = next(iter(results[Pass.PHOTOMETRIC].values()))
            for k, src in enumerate(problem.sources):
                src.depth = np.roll(photometric.depth, k + 1, axis=1)
            problem.initial = (photometric.depth, photometric.normal)
        results[pass_] = {name: estimate(problem, options, pass_) for name, options in variants.items()}
    return results


def _assert_same_maps(a, b):
    for name in ("depth", "normal", "cost", "visibility"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name


def test_early_stop_gives_the_maps_of_full_scoring():
    # Giving up a hypothesis once a lower bound of its cost shows it cannot win must not change
    # any map: photometric and geometric passes, plain and deformed pixels, planar prior.
    problem, depth, normal = _plane_scene(num_sources=3)
    problem.labels = np.ones(problem.reference.shape, np.int32)
    options = PatchMatchOptions(num_scales=2, min_scale_size=32, num_iterations=2, seed=7, strong_max_cost=0.05,
                                num_threads=2)
    exhaustive = PatchMatchOptions(**{**options.as_dict(), "early_stop": False})
    for results in _both_passes(problem, {"fast": options, "full": exhaustive}).values():
        fast, full = results["fast"], results["full"]
        assert fast.deformed is not None and fast.deformed.any()
        _assert_same_maps(fast, full)
        assert fast.hypothesis_evaluations < 0.97 * full.hypothesis_evaluations


def test_sparse_view_selection_with_the_full_windows_gives_the_default_maps():
    # View selection's anchor windows as the full ones, and every candidate scored again: the
    # rescoring (selected sources, early stop, the unselected ones rescored where kept) must
    # reproduce the default's maps, planar prior and both passes included.
    problem, depth, normal = _plane_scene(num_sources=3)
    problem.labels = np.ones(problem.reference.shape, np.int32)
    options = PatchMatchOptions(num_scales=2, min_scale_size=32, num_iterations=2, seed=7, strong_max_cost=0.05,
                                num_threads=2)
    same = PatchMatchOptions(**{**options.as_dict(), "deform_select_step": options.deform_anchor_step,
                                "deform_select_rescore": 8})
    for results in _both_passes(problem, {"default": options, "same": same}).values():
        full, rescored = results["default"], results["same"]
        assert full.deformed is not None and full.deformed.any()
        _assert_same_maps(full, rescored)
        # The rescoring's windows come on top of the candidates' (the same ones here).
        assert rescored.hypothesis_evaluations > full.hypothesis_evaluations


def test_sparse_view_selection_is_deterministic_and_accurate():
    problem, depth, normal = _plane_scene(num_sources=3)
    problem.labels = np.ones(problem.reference.shape, np.int32)
    options = PatchMatchOptions(num_scales=2, min_scale_size=32, num_iterations=2, seed=7, strong_max_cost=0.05)
    sparse = {t: PatchMatchOptions(**{**options.as_dict(), "deform_select_step": 5, "num_threads": t}) for t in (1, 2)}
    results = _both_passes(problem, {"default": options, **sparse})
    for pass_, by_name in results.items():
        one, two = by_name[1], by_name[2]
        assert np.array_equal(one.depth, two.depth) and np.array_equal(one.normal, two.normal)
        assert not np.array_equal(one.depth, by_name["default"].depth)  # other costs in view selection
        valid = one.depth > 0
        assert valid.mean() > 0.75
        assert np.median(np.abs(one.depth[valid] - depth[valid]) / depth[valid]) < 0.005


def test_sweep_rescores_unselected_sources_only_when_view_costs_are_kept():
    """``keep_view_costs`` (default): after a sweep every updated pixel's ``view_cost`` is the
    cost of its new plane in every source; without it, only in the sources it selected (the
    others are stale, which the last sweep of a state may leave), and every other map is the same."""
    problem, _, _ = _plane_scene(num_sources=4)
    h, w = problem.reference.shape
    from dvpmvs.patchmatch.estimator import _kernel_params, _Level
    level = _Level.build(problem, 1.0, use_depth=False)
    S = len(problem.sources)
    params = _kernel_params(problem, PatchMatchOptions())
    start = _kernel_state(np.zeros((h, w), np.float32), np.zeros((h, w, 3), np.float32), S)
    _patchmatch.initialise(*level.args, *start, params, True, 2, 1)
    states, evaluations = {}, {}
    for keep in (True, False):
        states[keep] = tuple(a.copy() for a in start)
        evaluations[keep] = _patchmatch.sweep(*level.args, *states[keep], params.replace(keep_view_costs=keep), 0, 2)
    for k in (0, 1, 2, 4, 5):  # depth, normal, cost, weights, selections: all but view_cost
        assert np.array_equal(states[True][k], states[False][k])
    rows, cols = np.mgrid[0:h, 0:w]
    swept = (rows + cols) % 2 == 0
    pixels = np.ascontiguousarray(np.argwhere(swept), np.int32)
    depth, normal = states[True][0], states[True][1]
    truth = _patchmatch.patch_costs(*level.args, depth, normal, params, pixels)
    kept = states[True][3][swept]
    lean = states[False][3][swept]
    selected = states[True][4][swept] > 0
    np.testing.assert_allclose(kept, truth, atol=1e-6)
    np.testing.assert_allclose(lean[selected], truth[selected], atol=1e-6)
    assert np.mean(np.abs(lean[~selected] - truth[~selected]) > 1e-3) > 0.2  # stale
    assert evaluations[False] < evaluations[True]


_AROUND = [(20, 40), (20, 50), (30, 52), (40, 50), (40, 40), (40, 30), (30, 28), (20, 30)]


def _anchors_around_pixel(shape):
    """(H, W, 8) anchors: pixel (30, 40) has the 8 pixels of ``_AROUND``, every other none."""
    anchors = np.full((*shape, 8), -1, np.int32)
    for a, (r, c) in enumerate(_AROUND):
        anchors[30, 40, a] = r * shape[1] + c
    return anchors


def test_anchor_plane_interpolates_the_anchors_plane_and_ignores_an_outlier():
    _, plane_depth, normals = _plane_scene()
    h, w = plane_depth.shape
    depth = plane_depth.copy()
    anchors = _anchors_around_pixel((h, w))
    around = _AROUND
    # Pixel (30, 40) with anchors around it on the plane; one (to the right) 20 % off it.
    depth[30, 52] *= 1.2
    # Pixel (5, 5): three anchors, all to its right and below (it lies outside their triangle).
    for a, (r, c) in enumerate([(10, 10), (10, 20), (20, 10)]):
        anchors[5, 5, a] = r * w + c
    fit_depth = np.zeros((h, w), np.float32)
    fit_normal = np.zeros((h, w, 3), np.float32)
    _anchors.fit_anchor_planes(depth, anchors, K, fit_depth, fit_normal, 0.01, 4, 2)
    assert fit_depth[30, 40] == pytest.approx(plane_depth[30, 40], rel=1e-4)
    np.testing.assert_allclose(fit_normal[30, 40], normals[30, 40], atol=1e-3)
    assert fit_depth[5, 5] == 0  # no triangle contains it: no extrapolation
    assert (fit_depth[anchors[..., 0] < 0] == 0).all()  # no anchors, no plane
    # With five of them filtered out (depth 0), three anchors are left: below min_inliers 4.
    for r, c in around[:5]:
        depth[r, c] = 0
    _anchors.fit_anchor_planes(depth, anchors, K, fit_depth, fit_normal, 0.01, 4, 2)
    assert fit_depth[30, 40] == 0
    _anchors.fit_anchor_planes(depth, anchors, K, fit_depth, fit_normal, 0.01, 3, 2)
    assert fit_depth[30, 40] == 0  # and their triangle (all on the left) does not contain the pixel


def test_coplanar_rule_drops_anchors_off_the_pixels_plane():
    _, plane_depth, _ = _plane_scene()
    h, w = plane_depth.shape
    depth = plane_depth.copy()
    anchors = _anchors_around_pixel((h, w))
    # Pixel (30, 40): six anchors on the plane, two (slots 2 and 5) on a surface 20 % nearer,
    # as anchors across a depth edge would be.
    depth[30, 52] *= 0.8
    depth[40, 30] *= 0.8
    # Pixel (10, 60): four anchors on four different surfaces (no plane agreed with by 4).
    for a, ((r, c), f) in enumerate(zip([(5, 60), (10, 66), (15, 60), (10, 54)], [1.0, 0.7, 1.3, 0.5])):
        anchors[10, 60, a] = r * w + c
        depth[r, c] = plane_depth[r, c] * f
    before = anchors.copy()
    _anchors.keep_coplanar_anchors(depth, anchors, K, 0.01, 4, 2)
    expected = before[30, 40].copy()
    expected[[2, 5]] = -1
    np.testing.assert_array_equal(anchors[30, 40], expected)
    assert (anchors[10, 60] == -1).all()
    # Every other pixel is untouched (it had no anchors).
    untouched = np.ones((h, w), bool)
    untouched[30, 40] = untouched[10, 60] = False
    np.testing.assert_array_equal(anchors[untouched], before[untouched])
    # With min_inliers 7 the six coplanar anchors are not enough either.
    anchors = before.copy()
    _anchors.keep_coplanar_anchors(depth, anchors, K, 0.01, 7, 2)
    assert (anchors[30, 40] == -1).all()


def test_region_plane_extends_the_strong_pixels_plane_over_their_region():
    _, plane_depth, normals = _plane_scene()
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
    checked = region_planes(depth, strong, labels, K, (2.0, 8.0), 0.005, 50, 0.6, anchors=anchors)[0]
    assert checked[40, 30] == fit_depth[40, 30]
    assert checked[40, 20] == 0 and checked[40, 10] == 0
    assert np.count_nonzero(checked) == 1  # no anchors, no plane
    with pytest.raises(ValueError, match="share one image size"):
        region_planes(depth, strong[:10], labels, K, (2.0, 8.0))
    with pytest.raises(ValueError, match="region_plane_min_inliers"):
        PatchMatchOptions(region_plane_min_inliers=0)


def test_range_slack_lets_propagation_leave_the_sparse_depth_range():
    # A slanted plane whose far half lies beyond the view's depth range (as a surface without
    # sparse points does): random hypotheses start inside the range, and only propagation and
    # refinement can carry the plane past its end.
    problem, plane_depth, _ = _plane_scene(num_sources=3, normal=(0.5, -0.1, -1.0))
    hi = float(np.median(plane_depth))
    problem = Problem(problem.reference, problem.sources, (0.9 * float(plane_depth.min()), hi))
    inner = np.zeros(plane_depth.shape, bool)
    inner[8:-8, 8:-8] = True
    far = inner & (plane_depth > 1.02 * hi)
    assert far.sum() > 1000

    def run(range_slack):
        options = PatchMatchOptions(num_scales=1, num_iterations=4, seed=3, num_threads=2, filter_min_region=0,
                                    range_slack=range_slack)
        depth = estimate(problem, options).depth
        return depth, np.abs(depth - plane_depth) / plane_depth < 0.01

    bounded, bounded_ok = run(1.0)
    assert bounded[inner].max() <= hi and not bounded_ok[far].any()
    _, slack_ok = run(2.0)
    assert slack_ok[far].mean() > 0.8 and slack_ok[inner & ~far].mean() > 0.95


@pytest.mark.parametrize("mode, median", [("linear", 5.5), ("inverse", 1 / 0.55)])
def test_random_depths_spread_uniformly_in_depth_or_in_inverse_depth(mode, median):
    # Over the range [1, 10], half the random draws lie below the median of the chosen spread:
    # 5.5 uniform in depth; 1 / 0.55 uniform in inverse depth, which draws as many hypotheses
    # per unit of disparity near the camera as far from it.
    from dvpmvs.patchmatch.estimator import _kernel_params

    problem, _, _ = _plane_scene()
    problem = replace(problem, depth_range=(1.0, 10.0))
    h, w = problem.reference.image.shape[:2]
    depth = np.zeros((h, w), np.float32)
    normal = np.zeros((h, w, 3), np.float32)
    _patchmatch.random_hypotheses(problem.reference.K, depth, normal,
                                  _kernel_params(problem, PatchMatchOptions(random_depth=mode)), 1)
    assert 1.0 <= depth.min() and depth.max() <= 10.0
    assert abs(np.median(depth) - median) < 0.05 * median


def test_flat_pixels_are_those_whose_window_holds_only_noise():
    from dvpmvs.patchmatch.estimator import flat_pixels

    rng = np.random.default_rng(0)
    image = np.full((60, 80), 0.6, np.float32) + rng.normal(0, 0.01, (60, 80)).astype(np.float32)
    image[:, 40:] += 2 * _texture((60, 40), 1) - 1  # texture on the right half only
    flat = flat_pixels(image, PatchMatchOptions())
    assert flat[:, :34].all() and not flat[:, 46:].any()  # the window's radius: 5 pixels


def test_the_geometric_pass_drops_flat_pixels_whose_depth_no_source_confirms():
    from dvpmvs.patchmatch.estimator import _Level, consistent_sources, flat_pixels

    problem, depth, normal = _plane_scene(num_sources=2)
    _sources_on_the_plane(problem, depth, normal)
    rng = np.random.default_rng(1)
    problem.reference.image[:, :30] = 0.5  # the left part of the reference is plain ...
    problem.reference.image += rng.normal(0, 0.01, problem.reference.shape).astype(np.float32)  # ... but for noise
    # The photometric estimate: the plane, but made-up depths on a plain band no source confirms.
    initial = depth.copy()
    initial[:, :20] *= rng.uniform(1.8, 2.5, (60, 20)).astype(np.float32)
    problem = Problem(problem.reference, problem.sources, problem.depth_range, initial=(initial, normal.copy()))
    level = _Level.build(problem, 1.0, use_depth=True)
    from dvpmvs.patchmatch.estimator import _kernel_params

    count = consistent_sources(level, initial, normal, _kernel_params(problem, PatchMatchOptions()), 1.0, 1)
    assert (count[10:50, 25:60] >= 1).mean() > 0.95 and (count[:, :20] == 0).mean() > 0.9
    options = PatchMatchOptions(geom_iterations=1, planar_prior=False, deformable=False, num_threads=1, seed=2,
                                filter_min_region=0)
    kept = estimate(problem, options, "geometric").depth
    dropped = estimate(problem, replace(options, flat_min_consistent=1), "geometric").depth
    unfounded = flat_pixels(problem.reference.image, options) & (count < 1)
    assert unfounded[:, :20].mean() > 0.85
    assert (kept[unfounded] > 0).sum() > 50 and not (dropped[unfounded] > 0).any()
    assert np.array_equal(dropped[:, 36:] > 0, kept[:, 36:] > 0)  # textured pixels untouched
