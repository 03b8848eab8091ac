"""Procedural textures with natural-image statistics, for synthetic scenes.

- ``dead_leaves``: opaque discs with power-law radii painted over each other; its statistics
  (scale invariance, sharp occlusion edges) match natural images well (Lee, Mumford, Huang 2001).
- ``fractal_noise``: sums of octaves of smooth noise with 1/f amplitude (stone, plaster, wood).
- ``uniform``: a flat colour, the textureless case PatchMatch struggles with.
- ``cobblestone``: rows of rounded stones of varied shade, offset by half a stone from row to
  row, in dark joints (a street or plaza pavement).

All take a NumPy ``Generator`` and return float32 RGB in [0, 1]; the same generator state gives
the same texture.
"""

from __future__ import annotations

import cv2
import numpy as np

from dvpmvs.evaluation.portable import power

__all__ = ["cobblestone", "dead_leaves", "fractal_noise", "uniform", "make_texture"]


def uniform(size: int, color) -> np.ndarray:
    """A flat texture of one colour."""
    return np.broadcast_to(np.asarray(color, np.float32), (size, size, 3)).copy()


def dead_leaves(
    rng: np.random.Generator,
    size: int = 512,
    palette=None,
    r_min: float = 2.0,
    r_max: float = 80.0,
    num_discs: int = 4000,
) -> np.ndarray:
    """Dead-leaves texture: discs with density of radii ~ r^-3 between ``r_min`` and ``r_max`` px.

    Discs are painted back to front (later ones occlude earlier ones) and wrap around the
    borders so the texture tiles.
    """
    # Inverse-CDF sampling of p(r) ~ r^-3 on [r_min, r_max].
    u = rng.random(num_discs)
    a, b = r_min**-2, r_max**-2
    radii = power(a - u * (a - b), -0.5)
    centers = rng.random((num_discs, 2)) * size
    if palette is None:
        colors = rng.random((num_discs, 3))
    else:
        palette = np.asarray(palette, np.float64)
        colors = palette[rng.integers(0, len(palette), num_discs)]
        colors = np.clip(colors * rng.uniform(0.75, 1.25, (num_discs, 1)), 0, 1)
    # Paint on a 3x3 tiled canvas so discs crossing a border wrap around, then keep the middle.
    canvas = np.zeros((3 * size, 3 * size, 3), np.float32)
    canvas[:] = colors[0]
    for (cx, cy), r, color in zip(centers, radii, colors):
        for ox in (0, size, 2 * size):
            for oy in (0, size, 2 * size):
                x, y = cx + ox, cy + oy
                if size - r <= x <= 2 * size + r and size - r <= y <= 2 * size + r:
                    cv2.circle(
                        canvas,
                        (int(round(x * 16)), int(round(y * 16))),
                        int(round(r * 16)),
                        tuple(float(c) for c in color),
                        -1,
                        lineType=cv2.LINE_AA,
                        shift=4,
                    )
    return np.ascontiguousarray(canvas[size : 2 * size, size : 2 * size])


def fractal_noise(
    rng: np.random.Generator,
    size: int = 512,
    color_a=(0.3, 0.3, 0.3),
    color_b=(0.8, 0.8, 0.8),
    octaves: int = 6,
    persistence: float = 0.6,
    base_cells: int = 4,
    stretch: float = 1.0,
) -> np.ndarray:
    """Fractal (1/f) noise mapped between two colours; ``stretch`` > 1 gives wood-like grain."""
    # float64 throughout: OpenCV's float32 resampling has SIMD paths that differ in the last bits
    total = np.zeros((size, size), np.float64)
    amplitude, weight = 1.0, 0.0
    for octave in range(octaves):
        cells = base_cells * 2**octave
        cells_y = max(1, int(round(cells / stretch)))
        grid = rng.standard_normal((cells_y, cells))
        # Tile the grid so that the upsampled noise wraps around seamlessly.
        tiled = np.tile(grid, (3, 3))
        up = cv2.resize(tiled, (3 * size, 3 * size), interpolation=cv2.INTER_CUBIC)
        total += amplitude * up[size : 2 * size, size : 2 * size]
        weight += amplitude
        amplitude *= persistence
    total /= weight
    lo, hi = np.percentile(total, [2, 98])
    t = np.clip((total - lo) / max(hi - lo, 1e-6), 0, 1)[..., None]
    a = np.asarray(color_a, np.float32)
    b = np.asarray(color_b, np.float32)
    return (a * (1 - t) + b * t).astype(np.float32)


def cobblestone(
    rng: np.random.Generator,
    size: int = 512,
    stones: int = 8,
    color=(0.55, 0.52, 0.48),
    joint=(0.18, 0.17, 0.16),
    shade: float = 0.25,
) -> np.ndarray:
    """``stones`` x ``stones`` rounded stones per tile, each row shifted by half a stone, each
    stone's colour ``color`` scaled by 1 +- ``shade`` and grained by fractal noise, in joints of
    colour ``joint``. Tiles seamlessly (whole stones per tile; the shifted rows wrap)."""
    cell = size // stones
    canvas = np.empty((size, size, 3), np.float32)
    canvas[:] = np.asarray(joint, np.float32)
    grain = fractal_noise(
        rng, size, (0.85, 0.85, 0.85), (1.15, 1.15, 1.15), octaves=5, base_cells=stones * 2
    )
    mask = np.zeros((size, size), np.uint8)
    gap = max(1, cell // 10)
    for row in range(stones):
        for col in range(stones):
            x0 = col * cell + (cell // 2 if row % 2 else 0) + gap
            y0 = row * cell + gap
            tone = np.asarray(color, np.float32) * float(rng.uniform(1 - shade, 1 + shade))
            for ox in (0, -size):  # the stone that leaves the tile on the right enters on the left
                stone = np.zeros_like(mask)
                cv2.rectangle(
                    stone, (x0 + ox, y0), (x0 + ox + cell - 2 * gap, y0 + cell - 2 * gap), 255, -1
                )
                stone = cv2.GaussianBlur(stone, (0, 0), cell / 8) > 150
                canvas[stone] = tone
                mask |= stone.astype(np.uint8)
    return np.clip(np.where(mask[..., None] > 0, canvas * grain, canvas), 0, 1).astype(np.float32)


def make_texture(spec: dict, rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """Build a texture from a material's ``texture`` spec (``kind`` plus keyword arguments)."""
    spec = dict(spec)
    kind = spec.pop("kind")
    if kind == "uniform":
        return uniform(8, spec["color"])
    if kind == "dead_leaves":
        return dead_leaves(rng, size, **spec)
    if kind == "fractal":
        return fractal_noise(rng, size, **spec)
    if kind == "cobblestone":
        return cobblestone(rng, size, **spec)
    raise ValueError(f"unknown texture kind {kind!r}")
