"""Rendered planes and NumPy references shared by the estimator's tests."""

import cv2
import numpy as np

from dvpmvs.patchmatch import Problem, ViewData

K = np.array([[70.0, 0, 39.5], [0, 72.0, 29.5], [0, 0, 1]])


def rays_through(K, rows, cols):
    """K^-1 (col, row, 1) of pixels (rows, cols): depth times it is the camera-frame point."""
    return np.stack([cols, rows, np.ones_like(cols)], -1).astype(np.float64) @ np.linalg.inv(K).T


def depth_of_plane(K, normal, point, rows, cols):
    """Depth along the rays of pixels (rows, cols) of the plane through ``point`` with ``normal``."""
    return float(np.dot(normal, point)) / (rays_through(K, rows, cols) @ normal)


def random_texture(shape, seed):
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.random(shape).astype(np.float32), (0, 0), 1.2)


def rotation_about(axis, degrees):
    return cv2.Rodrigues(np.asarray(axis, np.float64) * np.deg2rad(degrees))[0]


def plane_scene(depth=4.0, normal=(0.2, -0.1, -1.0), num_sources=2, seed=0):
    """A textured plane seen by a reference camera (identity pose) and sources rendered from it
    with the exact plane-induced warp, so the true plane is the best hypothesis."""
    n = np.asarray(normal, np.float64)
    n /= np.linalg.norm(n)
    h, w = 60, 80
    ref = random_texture((h, w), seed)
    sources = []
    for j in range(num_sources):
        R = rotation_about((0, 1, 0.2), 3.0 * (j + 1))
        t = np.array([0.3 * (j + 1), 0.05 * j, 0.02])
        # Source pixel -> reference pixel through the plane n.X = n.(depth * ray(centre)).
        centre = depth * np.linalg.inv(K) @ np.array([w / 2, h / 2, 1.0])
        d = n @ centre  # plane: n.X = d in the reference camera
        H_ref_to_src = K @ (R + np.outer(t, n) / d) @ np.linalg.inv(K)
        src = cv2.warpPerspective(
            ref, H_ref_to_src, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
        )
        sources.append(ViewData(f"s{j}", src, K, R, t))
    reference = ViewData("ref", ref, K, np.eye(3), np.zeros(3))
    rows, cols = np.mgrid[0:h, 0:w]
    plane_depth = depth_of_plane(K, n, centre, rows, cols).astype(np.float32)
    normals = np.broadcast_to(n.astype(np.float32), (h, w, 3)).copy()
    return Problem(reference, sources, (2.0, 8.0)), plane_depth, normals


def numpy_cost(problem, depth, normal, row, col, options, window_at=None, step=None):
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
                s = (1 - b) * ((1 - a) * img[v0, u0] + a * img[v0, u1]) + b * (
                    (1 - a) * img[v1, u0] + a * img[v1, u1]
                )
                value = ref.image[y, x]
                colour = (value - ref.image[wrow, wcol]) ** 2 / (2 * options.sigma_color**2)
                rv.append(value)
                sv.append(s)
                wt.append(np.exp(-(dx * dx + dy * dy) / (2 * options.sigma_spatial**2) - colour))
        rv, sv, wt = map(np.asarray, (rv, sv, wt))
        wt = wt / wt.sum()
        mr, ms = wt @ rv, wt @ sv
        cov = wt @ (rv * sv) - mr * ms
        var_r, var_s = wt @ (rv * rv) - mr * mr, wt @ (sv * sv) - ms * ms
        out.append(float(np.clip(1 - cov / np.sqrt(var_r * var_s), 0, 2)))
    return np.array(out)


def kernel_state(depth, normal, num_sources, selected=0):
    """The kernel's per-pixel state around a plane map (a ``PlaneState``: depth, normal, cost,
    per-source costs, per-source weights, selected sources), the costs and weights zero;
    ``selected`` a bit mask per pixel, or one for every pixel."""
    from dvpmvs.patchmatch._patchmatch import PlaneState

    h, w = depth.shape
    return PlaneState(
        depth,
        normal,
        np.zeros((h, w), np.float32),
        np.zeros((h, w, num_sources), np.float32),
        np.zeros((h, w, num_sources), np.float32),
        np.array(np.broadcast_to(selected, (h, w)), np.uint32),
    )


def pixel_rays(h, w):
    rows, cols = np.mgrid[0:h, 0:w]
    return rows, cols, rays_through(K, rows, cols)


def sources_on_the_plane(problem, depth, normal):
    """Give each source of a ``plane_scene`` the true plane's depth map in its camera."""
    rows, cols, rays = pixel_rays(*problem.reference.shape)
    corner = depth[0, 0] * rays[0, 0]
    for src in problem.sources:
        src.depth = depth_of_plane(
            K, src.R @ normal[0, 0], src.R @ corner + src.t, rows, cols
        ).astype(np.float32)


def plain_wall_scene(num_sources=4, seed=0, noise=0.02, faint=0.015, sky_rows=0):
    """A 160x120 plane, textured on its left third and plain elsewhere (an unevenness of
    ``faint`` deviation, smooth over ~3 pixels: under the sensor ``noise`` pixel by pixel, above
    it once a coarser level averages 2x2 pixels), seen by sources rendered from its albedo with
    their own noise; with ``sky_rows``, the top rows of every image are a flat bright band with
    nothing behind it (open sky). Returns the problem, the plane's depth (0 in the sky) and the
    plain pixels' mask."""
    w, h = 160, 120
    Kw = np.array([[140.0, 0, w / 2 - 0.5], [0, 144.0, h / 2 - 0.5], [0, 0, 1]])
    rng = np.random.default_rng(seed)
    n = np.array([0.15, -0.1, -1.0])
    n /= np.linalg.norm(n)
    # The albedo on a grid twice the image's size: reference pixel (x, y) is albedo (x + w/2, y + h/2).
    blob = cv2.GaussianBlur(rng.standard_normal((2 * h, 2 * w)).astype(np.float32), (0, 0), 3)
    albedo = 0.5 + faint * blob / blob.std()
    texture = cv2.GaussianBlur(rng.random((2 * h, 2 * w)).astype(np.float32), (0, 0), 1.5)
    textured = w // 2 + w // 3
    albedo[:, :textured] = 0.5 + 1.6 * (texture[:, :textured] - 0.5)
    shift = np.array([[1, 0, w / 2], [0, 1, h / 2], [0, 0, 1.0]])
    centre = 4.0 * np.linalg.inv(Kw) @ np.array([w / 2, h / 2, 1.0])
    distance = n @ centre

    def render(R, t):
        to_source = Kw @ (R + np.outer(t, n) / distance) @ np.linalg.inv(Kw) @ np.linalg.inv(shift)
        image = cv2.warpPerspective(
            albedo, to_source, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
        )
        image[:sky_rows] = 0.8
        return np.clip(image + rng.normal(0, noise, image.shape).astype(np.float32), 0, 1)

    reference = ViewData("ref", render(np.eye(3), np.zeros(3)), Kw, np.eye(3), np.zeros(3))
    sources = []
    for j in range(num_sources):
        sign = (-1) ** j
        R = rotation_about((0, 1, 0.2), 3.0 * (j + 1) * sign)
        t = np.array([0.3 * (j + 1) * sign, 0.05 * j, 0.02])
        sources.append(ViewData(f"s{j}", render(R, t), Kw, R, t))
    rows, cols = np.mgrid[0:h, 0:w]
    truth = depth_of_plane(Kw, n, centre, rows, cols).astype(np.float32)
    truth[:sky_rows] = 0
    plain = np.zeros((h, w), bool)
    plain[sky_rows:, w // 3 + 6 :] = True  # the window's radius from the texture's edge
    return Problem(reference, sources, (2.0, 8.0)), truth, plain
