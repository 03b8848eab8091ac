"""The synthetic scene families: geometry, materials, light and camera paths.

Units are metres, world z points up. Each family is a function ``(rng, num_views) -> Scene``;
the randomness (object placement, colours, textures) comes only from ``rng``.

- ``room``: an indoor room with large uniform walls and ceiling, a textured floor, furniture
  casting shadows under a ceiling light, and a glossy ball and floor that show highlights.
- ``facade``: a building front with balconies, pillars and recessed glossy windows, a street and
  a second building far behind (depth range ~8 m to ~45 m), lit by a low sun.
- ``tabletop``: small boxes, balls and cylinders occluding each other on a wooden table in
  front of a plain wall, lit from above.
- ``courtyard``: a plain (paint fainter than the noise), evenly lit courtyard wall filling a third
  of each view behind textured
  crates, planters and a bench, with open sky above it and a textured tower and roof rising
  behind it: textureless surface at full resolution, and a plain region with no surface at all.
- ``street``: a cobblestone plaza photographed at eye level, running from about 2 m in front of
  the cameras (the bottom of each image, at grazing angles) to a facade 22 m away, with a kerbed
  pavement, bollards and a bench; the cameras walk sideways along it, as a photographer does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from dvpmvs.evaluation.geometry import look_at
from dvpmvs.evaluation.portable import norm

__all__ = ["Material", "Light", "Scene", "SCENES", "build_scene"]


@dataclass
class Material:
    """Surface appearance: a texture (see ``textures.make_texture``) and Blinn-Phong specularity.

    ``tile`` is the side of one texture tile in metres (textures repeat). ``plain``: a surface a
    photographer would call untextured (a painted wall: a texture, if any, fainter than the
    camera's noise); uniform textures are plain whatever it says. The ground truth's
    ``textureless`` masks show plain surfaces.
    """

    texture: dict
    tile: float = 1.0
    specular: float = 0.0
    shininess: float = 40.0
    plain: bool = False

    @property
    def is_plain(self) -> bool:
        return self.plain or self.texture.get("kind") == "uniform"


@dataclass
class Light:
    """A point light (``position``) or, with ``directional``, the sun shining along ``direction``."""

    position: np.ndarray | None = None
    direction: np.ndarray | None = None
    intensity: float = 1.0
    ambient: float = 0.25


@dataclass
class Scene:
    name: str
    meshes: list[tuple[o3d.geometry.TriangleMesh, str]]  # (mesh, material name)
    materials: dict[str, Material]
    light: Light
    cameras: list[tuple[np.ndarray, np.ndarray]]  # world -> camera (R, t)
    focal_factor: float = 0.8  # focal length / image width
    sky: tuple[float, float, float] | None = None  # colour where rays escape (None: closed scene)
    depth_hint: tuple[float, float] = (0.1, 100.0)
    extras: dict = field(default_factory=dict)


def _box(x0, y0, z0, x1, y1, z1) -> o3d.geometry.TriangleMesh:
    mesh = o3d.geometry.TriangleMesh.create_box(x1 - x0, y1 - y0, z1 - z0)
    mesh.translate((x0, y0, z0))
    return mesh


def _sphere(center, radius) -> o3d.geometry.TriangleMesh:
    mesh = o3d.geometry.TriangleMesh.create_sphere(radius, resolution=48)
    mesh.translate(center)
    return mesh


def _cylinder(center_bottom, radius, height) -> o3d.geometry.TriangleMesh:
    mesh = o3d.geometry.TriangleMesh.create_cylinder(radius, height, resolution=64, split=1)
    mesh.translate(np.asarray(center_bottom, float) + [0.0, 0.0, height / 2])
    return mesh


def _arc_cameras(center, radius, height, target, azimuths_deg, jitter, rng) -> list:
    """Cameras on a horizontal arc around ``center``, looking at ``target`` (up = world z)."""
    cams = []
    for az in azimuths_deg:
        a = np.deg2rad(az)
        pos = np.array(
            [center[0] + radius * math.sin(a), center[1] - radius * math.cos(a), height], float
        )
        pos += rng.uniform(-jitter, jitter, 3)
        tgt = np.asarray(target, float) + rng.uniform(-jitter, jitter, 3)
        cams.append(look_at(pos, tgt, up=(0.0, 0.0, 1.0)))
    return cams


def _pastel(rng, lo=0.65, hi=0.9):
    return tuple(float(v) for v in rng.uniform(lo, hi, 3))


def room(rng: np.random.Generator, num_views: int) -> Scene:
    W, D, H = 6.0, 5.0, 2.8
    wall = _pastel(rng, 0.7, 0.85)
    materials = {
        "wall": Material({"kind": "uniform", "color": wall}),
        "ceiling": Material({"kind": "uniform", "color": (0.88, 0.88, 0.86)}),
        "floor": Material(
            {
                "kind": "fractal",
                "color_a": (0.35, 0.22, 0.12),
                "color_b": (0.7, 0.5, 0.3),
                "stretch": 6.0,
            },
            tile=1.5,
            specular=0.35,
            shininess=60,
        ),
        "rug": Material(
            {
                "kind": "dead_leaves",
                "palette": [(0.6, 0.1, 0.1), (0.9, 0.8, 0.6), (0.2, 0.3, 0.5), (0.1, 0.1, 0.1)],
            },
            tile=1.2,
        ),
        "cabinet": Material(
            {
                "kind": "fractal",
                "color_a": (0.25, 0.15, 0.08),
                "color_b": (0.55, 0.38, 0.2),
                "stretch": 4.0,
            },
            tile=0.8,
        ),
        "table": Material(
            {"kind": "uniform", "color": (0.92, 0.92, 0.9)}, specular=0.5, shininess=80
        ),
        "picture": Material({"kind": "dead_leaves"}, tile=0.7),
        "sofa": Material(
            {
                "kind": "fractal",
                "color_a": (0.15, 0.25, 0.35),
                "color_b": (0.35, 0.5, 0.6),
                "octaves": 7,
                "base_cells": 16,
            },
            tile=0.6,
        ),
        "ball": Material(
            {"kind": "uniform", "color": (0.8, 0.15, 0.1)}, specular=0.8, shininess=120
        ),
    }
    meshes = [
        (_box(0, 0, -0.1, W, D, 0), "floor"),
        (_box(0, 0, H, W, D, H + 0.1), "ceiling"),
        (_box(-0.1, 0, 0, 0, D, H), "wall"),
        (_box(W, 0, 0, W + 0.1, D, H), "wall"),
        (_box(0, D, 0, W, D + 0.1, H), "wall"),
        (_box(0, -0.1, 0, W, 0, H), "wall"),
        (_box(1.6, 2.4, 0.0, 4.2, 4.0, 0.004), "rug"),
    ]
    cx = rng.uniform(0.6, 1.2)
    meshes.append((_box(cx, D - 0.55, 0, cx + 0.9, D, 1.9), "cabinet"))
    tx, ty = rng.uniform(2.4, 2.9), rng.uniform(2.8, 3.2)
    meshes.append((_box(tx, ty, 0.72, tx + 1.4, ty + 0.8, 0.76), "table"))
    for lx, ly in [
        (tx + 0.05, ty + 0.05),
        (tx + 1.3, ty + 0.05),
        (tx + 0.05, ty + 0.7),
        (tx + 1.3, ty + 0.7),
    ]:
        meshes.append((_box(lx, ly, 0, lx + 0.05, ly + 0.05, 0.72), "table"))
    meshes.append((_sphere((tx + 0.4, ty + 0.4, 0.76 + 0.15), 0.15), "ball"))
    px = rng.uniform(3.2, 4.0)
    meshes.append((_box(px, D - 0.03, 1.2, px + 1.1, D, 1.9), "picture"))
    meshes.append((_box(W - 1.0, 1.8, 0, W, 4.2, 0.45), "sofa"))
    meshes.append((_box(W - 0.25, 1.8, 0.45, W, 4.2, 0.9), "sofa"))
    light = Light(position=np.array([2.6, 2.2, 2.6]), intensity=1.0, ambient=0.3)
    span = 70.0
    azimuths = np.linspace(-span / 2, span / 2, num_views)
    cams = _arc_cameras((3.0, 3.4), 3.0, 1.55, (3.0, 4.2, 0.9), azimuths, 0.05, rng)
    return Scene("room", meshes, materials, light, cams, focal_factor=0.7, depth_hint=(0.3, 12.0))


def facade(rng: np.random.Generator, num_views: int) -> Scene:
    materials = {
        "street": Material(
            {
                "kind": "fractal",
                "color_a": (0.25, 0.25, 0.27),
                "color_b": (0.55, 0.55, 0.55),
                "octaves": 7,
                "base_cells": 8,
            },
            tile=4.0,
        ),
        "plaster": Material({"kind": "uniform", "color": _pastel(rng, 0.75, 0.9)}),
        "stone": Material(
            {
                "kind": "fractal",
                "color_a": (0.45, 0.4, 0.33),
                "color_b": (0.8, 0.75, 0.65),
                "octaves": 7,
                "base_cells": 6,
            },
            tile=3.0,
        ),
        "window": Material(
            {"kind": "uniform", "color": (0.12, 0.15, 0.2)}, specular=0.9, shininess=150
        ),
        "balcony": Material(
            {
                "kind": "dead_leaves",
                "palette": [(0.5, 0.5, 0.5), (0.7, 0.7, 0.7), (0.3, 0.3, 0.35)],
            },
            tile=2.0,
        ),
        "far": Material(
            {"kind": "fractal", "color_a": (0.5, 0.35, 0.3), "color_b": (0.8, 0.6, 0.5)}, tile=6.0
        ),
    }
    fy = 12.0  # the facade's front plane (y = fy); windows are recessed 0.3 m behind it
    windows_x = [(-10.5, -8.9), (-7.0, -5.4), (-2.5, -0.9), (1.0, 2.6), (5.5, 7.1), (8.8, 10.4)]
    windows_z = [(3.6, 5.6), (7.0, 9.0), (10.4, 12.4)]
    meshes = [
        (_box(-40, -10, -0.2, 40, 60, 0), "street"),
        (_box(-12, fy + 0.3, 0, 12, fy + 8, 14), "plaster"),  # the wall behind the recesses
        (_box(16, 30, 0, 40, 36, 24), "far"),  # a taller building behind, to the right
    ]
    for x0, x1 in windows_x:
        for z0, z1 in windows_z:
            meshes.append((_box(x0, fy + 0.25, z0, x1, fy + 0.3, z1), "window"))
    # The facade's front: horizontal bands between the window rows and vertical strips between
    # the window columns; their sides form the window reveals.
    bands = (
        [(0.0, windows_z[0][0])]
        + [(a[1], b[0]) for a, b in zip(windows_z, windows_z[1:])]
        + [(windows_z[-1][1], 14.0)]
    )
    for z0, z1 in bands:
        meshes.append((_box(-12, fy, z0, 12, fy + 0.3, z1), "plaster"))
    edges = [-12.0] + [v for w in windows_x for v in w] + [12.0]
    for x0, x1 in zip(edges[0::2], edges[1::2]):
        meshes.append((_box(x0, fy, 0, x1, fy + 0.3, 14), "plaster"))
    meshes.append((_box(-12, fy - 0.05, 0, 12, fy, 3.2), "stone"))  # ground-floor cladding
    for x in (-12.0, -4.2, 3.6, 11.4):
        meshes.append((_box(x, fy - 0.6, 0, x + 0.6, fy, 14), "stone"))  # pillars
    for z0, _ in windows_z:
        bx = rng.uniform(-3.0, -1.5)
        meshes.append((_box(bx, fy - 1.2, z0 - 0.2, bx + 4.0, fy, z0), "balcony"))
        meshes.append((_box(bx, fy - 1.2, z0, bx + 4.0, fy - 1.1, z0 + 1.0), "balcony"))
    sun = np.array([0.45, 0.8, -0.55])
    light = Light(direction=sun / norm(sun), intensity=1.1, ambient=0.3)
    azimuths = np.linspace(-28, 28, num_views)
    cams = _arc_cameras((0.0, fy), 15.0, 1.7, (0.0, fy, 5.5), azimuths, 0.15, rng)
    return Scene(
        "facade",
        meshes,
        materials,
        light,
        cams,
        focal_factor=0.75,
        sky=(0.62, 0.75, 0.92),
        depth_hint=(1.0, 80.0),
    )


def tabletop(rng: np.random.Generator, num_views: int) -> Scene:
    materials = {
        "table": Material(
            {
                "kind": "fractal",
                "color_a": (0.4, 0.25, 0.12),
                "color_b": (0.75, 0.55, 0.35),
                "stretch": 8.0,
            },
            tile=0.5,
            specular=0.3,
            shininess=50,
        ),
        "wall": Material({"kind": "uniform", "color": (0.82, 0.84, 0.8)}),
        "box_dl": Material({"kind": "dead_leaves"}, tile=0.15),
        "box_fr": Material(
            {
                "kind": "fractal",
                "color_a": (0.1, 0.3, 0.1),
                "color_b": (0.6, 0.9, 0.5),
                "base_cells": 12,
            },
            tile=0.2,
        ),
        "white": Material(
            {"kind": "uniform", "color": (0.9, 0.9, 0.92)}, specular=0.7, shininess=90
        ),
        "red": Material(
            {"kind": "uniform", "color": (0.75, 0.1, 0.1)}, specular=0.8, shininess=120
        ),
        "can": Material(
            {"kind": "dead_leaves", "palette": [(0.9, 0.8, 0.1), (0.1, 0.2, 0.6), (0.9, 0.9, 0.9)]},
            tile=0.1,
            specular=0.5,
            shininess=80,
        ),
    }
    meshes = [
        (_box(-0.6, -0.4, -0.03, 0.6, 0.45, 0.0), "table"),
        (_box(-3.0, 0.45, -0.8, 3.0, 0.5, 2.5), "wall"),
        (_box(-3.0, -3.0, -0.85, 3.0, 0.5, -0.8), "wall"),  # floor under the table
    ]
    placed = []

    def spot(radius):
        for _ in range(100):
            p = rng.uniform([-0.3, -0.2], [0.3, 0.3])
            if all(np.hypot(*(p - q)) > radius + r + 0.01 for q, r in placed):
                placed.append((p, radius))
                return p
        placed.append((p, radius))
        return p

    for mat in ("box_dl", "box_fr", "white"):
        s = rng.uniform(0.06, 0.14, 3)
        p = spot(0.6 * max(s[0], s[1]))
        meshes.append(
            (
                _box(
                    p[0] - s[0] / 2,
                    p[1] - s[1] / 2,
                    0,
                    p[0] + s[0] / 2,
                    p[1] + s[1] / 2,
                    s[2] * 1.3,
                ),
                mat,
            )
        )
    for mat in ("red", "white"):
        r = rng.uniform(0.03, 0.06)
        p = spot(r)
        meshes.append((_sphere((p[0], p[1], r), r), mat))
    r, h = rng.uniform(0.03, 0.045), rng.uniform(0.1, 0.16)
    p = spot(r)
    meshes.append((_cylinder((p[0], p[1], 0.0), r, h), "can"))
    light = Light(position=np.array([0.25, -0.35, 1.1]), intensity=1.0, ambient=0.3)
    azimuths = np.linspace(-40, 40, num_views)
    cams = _arc_cameras((0.0, 0.05), 0.75, 0.45, (0.0, 0.05, 0.04), azimuths, 0.01, rng)
    return Scene(
        "tabletop", meshes, materials, light, cams, focal_factor=0.85, depth_hint=(0.05, 5.0)
    )


def street(rng: np.random.Generator, num_views: int) -> Scene:
    materials = {
        "cobble": Material(
            {"kind": "cobblestone", "stones": 8, "color": _pastel(rng, 0.45, 0.6)},
            tile=1.6,
            specular=0.1,
            shininess=30,
        ),
        "slab": Material(
            {
                "kind": "fractal",
                "color_a": (0.5, 0.5, 0.48),
                "color_b": (0.75, 0.74, 0.7),
                "octaves": 7,
                "base_cells": 8,
            },
            tile=2.0,
        ),
        "kerb": Material(
            {
                "kind": "fractal",
                "color_a": (0.55, 0.55, 0.55),
                "color_b": (0.85, 0.85, 0.82),
                "stretch": 6.0,
            },
            tile=1.0,
        ),
        "plaster": Material({"kind": "uniform", "color": _pastel(rng, 0.7, 0.88)}),
        "stone": Material(
            {
                "kind": "fractal",
                "color_a": (0.45, 0.4, 0.33),
                "color_b": (0.8, 0.75, 0.65),
                "octaves": 7,
                "base_cells": 6,
            },
            tile=3.0,
        ),
        "window": Material(
            {"kind": "uniform", "color": (0.12, 0.15, 0.2)}, specular=0.9, shininess=150
        ),
        "metal": Material(
            {"kind": "uniform", "color": (0.2, 0.2, 0.22)}, specular=0.6, shininess=90
        ),
        "wood": Material(
            {
                "kind": "fractal",
                "color_a": (0.35, 0.22, 0.12),
                "color_b": (0.65, 0.45, 0.28),
                "stretch": 8.0,
            },
            tile=1.0,
        ),
    }
    fy = 22.0  # the facade's front plane (y = fy)
    meshes = [
        (_box(-30, -10, -0.2, 30, fy - 3.0, 0), "cobble"),  # the plaza, from behind the cameras on
        (_box(-30, fy - 3.0, -0.2, 30, fy, 0.12), "slab"),  # the pavement along the facade
        (_box(-30, fy - 3.2, -0.2, 30, fy - 3.0, 0.12), "kerb"),
        (_box(-16, fy, 0, 16, fy + 10, 9.5), "plaster"),
        (_box(-16, fy - 0.05, 0, 16, fy, 1.0), "stone"),  # plinth
    ]
    for x0 in (-13.0, -8.5, -4.0, 0.5, 5.0, 9.5):
        for z0 in (3.0, 6.2):
            meshes.append((_box(x0, fy - 0.02, z0, x0 + 1.6, fy, z0 + 2.0), "window"))
    meshes.append((_box(-1.2, fy - 0.02, 0.12, 0.6, fy, 2.4), "wood"))  # the door
    for _ in range(4):  # bollards between the cameras and the facade
        x, y = rng.uniform(-7, 7), rng.uniform(7, 15)
        meshes.append((_cylinder((x, y, 0.0), 0.12, 0.9), "metal"))
    bx, by = rng.uniform(-5, 2), rng.uniform(10, 14)
    meshes.append((_box(bx, by, 0.42, bx + 1.8, by + 0.45, 0.48), "wood"))  # a bench
    meshes.append((_box(bx, by + 0.4, 0.48, bx + 1.8, by + 0.45, 0.9), "wood"))
    for lx in (bx + 0.1, bx + 1.6):
        meshes.append((_box(lx, by, 0, lx + 0.1, by + 0.45, 0.42), "metal"))
    sun = np.array([-0.4, 0.7, -0.6])
    light = Light(direction=sun / norm(sun), intensity=1.1, ambient=0.3)
    # Eye level, pitched so that the bottom of the image sees the ground about 2 m ahead; the
    # cameras walk 6 m sideways, each turned slightly toward the middle of the facade.
    cams = []
    for x in np.linspace(-3.0, 3.0, num_views):
        pos = np.array([x, 0.0, 1.6]) + rng.uniform(-0.05, 0.05, 3)
        target = np.array([0.35 * x, fy, -0.7]) + rng.uniform(-0.1, 0.1, 3)
        cams.append(look_at(pos, target, up=(0.0, 0.0, 1.0)))
    return Scene(
        "street",
        meshes,
        materials,
        light,
        cams,
        focal_factor=0.75,
        sky=(0.62, 0.75, 0.92),
        depth_hint=(0.5, 80.0),
    )


def corridor(rng: np.random.Generator, num_views: int) -> Scene:
    step, W, H = 0.3, 2.4, 2.7  # walk per view, corridor width and height (m)
    L = step * (num_views - 1) + 8.0  # the walk, and 4 m beyond each end
    materials = {
        "wall": Material(
            {
                "kind": "fractal",
                "color_a": _pastel(rng, 0.45, 0.6),
                "color_b": _pastel(rng, 0.75, 0.9),
                "octaves": 7,
                "base_cells": 6,
            },
            tile=2.0,
        ),
        "floor": Material(
            {"kind": "cobblestone", "stones": 6, "color": _pastel(rng, 0.45, 0.6)},
            tile=1.2,
            specular=0.2,
            shininess=50,
        ),
        "ceiling": Material({"kind": "uniform", "color": (0.88, 0.88, 0.86)}),
        "door": Material(
            {
                "kind": "fractal",
                "color_a": (0.3, 0.18, 0.1),
                "color_b": (0.6, 0.42, 0.25),
                "stretch": 6.0,
            },
            tile=1.0,
        ),
        "poster": Material({"kind": "dead_leaves"}, tile=0.8),
        "cabinet": Material(
            {
                "kind": "fractal",
                "color_a": (0.2, 0.25, 0.3),
                "color_b": (0.5, 0.55, 0.6),
                "stretch": 3.0,
            },
            tile=0.8,
        ),
    }
    meshes = [
        (_box(-4.0, 0, -0.1, L - 4.0, W, 0), "floor"),
        (_box(-4.0, 0, H, L - 4.0, W, H + 0.1), "ceiling"),
        (_box(-4.0, -0.1, 0, L - 4.0, 0, H), "wall"),
        (_box(-4.0, W, 0, L - 4.0, W + 0.1, H), "wall"),
        (_box(-4.1, 0, 0, -4.0, W, H), "wall"),
        (_box(L - 4.0, 0, 0, L - 3.9, W, H), "wall"),
    ]
    # Along the wall the cameras look at, every 1.5-3 m: a recessed door, a cabinet or a poster.
    x = -3.0
    while x < L - 6.0:
        kind = rng.integers(3)
        if kind == 0:
            meshes.append((_box(x, W - 0.02, 0, x + 0.9, W, 2.1), "door"))
        elif kind == 1:
            meshes.append((_box(x, W - 0.45, 0, x + 1.0, W, rng.uniform(0.8, 1.8)), "cabinet"))
        else:
            meshes.append((_box(x, W - 0.02, 1.1, x + 0.7, W, 1.9), "poster"))
        x += rng.uniform(1.5, 3.0)
    light = Light(
        direction=np.array([0.3, 0.4, -1.0]) / norm([0.3, 0.4, -1.0]), intensity=0.8, ambient=0.35
    )
    cams = []
    for i in range(num_views):
        pos = np.array([step * i, 0.7, 1.5]) + rng.uniform(-0.03, 0.03, 3)
        target = pos + np.array([1.2, 1.4, -0.35]) + rng.uniform(-0.05, 0.05, 3)
        cams.append(look_at(pos, target, up=(0.0, 0.0, 1.0)))
    return Scene(
        "corridor", meshes, materials, light, cams, focal_factor=0.7, depth_hint=(0.3, 20.0)
    )


def courtyard(rng: np.random.Generator, num_views: int) -> Scene:
    """A plain courtyard wall behind textured objects, with open sky above it and a textured
    tower and roof rising behind it (the textureless case at full resolution, and a plain region
    with no surface at all beside it)."""
    paint = np.asarray(_pastel(rng, 0.7, 0.8))
    materials = {
        "ground": Material(
            {"kind": "cobblestone", "stones": 8, "color": _pastel(rng, 0.45, 0.6)}, tile=1.6
        ),
        # Plain and evenly lit: paint whose unevenness (2 % either way, in patches of decimetres to
        # metres) is fainter than the sensor's noise pixel by pixel, the point light's slow fall-off
        # across it as shading. Averaged over a few pixels (a coarser level) the unevenness shows.
        "wall": Material(
            {
                "kind": "fractal",
                "color_a": tuple(paint * 0.98),
                "color_b": tuple(paint * 1.02),
                "octaves": 5,
                "base_cells": 4,
            },
            tile=3.0,
            plain=True,
        ),
        "tower": Material(
            {
                "kind": "fractal",
                "color_a": (0.45, 0.4, 0.33),
                "color_b": (0.8, 0.75, 0.65),
                "octaves": 7,
                "base_cells": 6,
            },
            tile=3.0,
        ),
        "roof": Material(
            {
                "kind": "dead_leaves",
                "palette": [(0.55, 0.25, 0.15), (0.7, 0.35, 0.2), (0.4, 0.2, 0.15)],
            },
            tile=2.0,
        ),
        "crate": Material({"kind": "dead_leaves"}, tile=0.6),
        "planter": Material(
            {
                "kind": "fractal",
                "color_a": (0.1, 0.3, 0.1),
                "color_b": (0.5, 0.75, 0.35),
                "base_cells": 12,
            },
            tile=0.5,
        ),
        "wood": Material(
            {
                "kind": "fractal",
                "color_a": (0.35, 0.22, 0.12),
                "color_b": (0.65, 0.45, 0.28),
                "stretch": 8.0,
            },
            tile=1.0,
        ),
    }
    wy, wh = 7.0, 3.2  # the wall's front plane (y = wy) and height
    meshes = [
        (_box(-30, -10, -0.2, 30, 30, 0), "ground"),
        (_box(-14, wy, 0, 14, wy + 0.3, wh), "wall"),
        (_box(1.2, wy + 2.5, 0, 4.0, wy + 5.0, 11.0), "tower"),  # rises far above the wall
        (_box(-14, wy + 3.0, 0, -2.5, wy + 9.0, 5.4), "roof"),  # a roof line above the wall, left
    ]
    # Textured objects in front of the wall, occluding parts of it.
    for x in rng.uniform(-4.5, 4.5, 3):
        size = rng.uniform(0.6, 1.0)
        y = rng.uniform(wy - 2.5, wy - 1.0)
        meshes.append((_box(x, y, 0, x + size, y + size, size * rng.uniform(0.8, 1.4)), "crate"))
    for x in rng.uniform(-5.0, 5.0, 2):
        meshes.append((_cylinder((x, wy - 0.6, 0.0), 0.35, 0.8), "planter"))
    bx = rng.uniform(-3.0, 1.0)
    meshes.append((_box(bx, wy - 0.9, 0.42, bx + 2.0, wy - 0.45, 0.5), "wood"))  # a bench
    meshes.append((_box(bx, wy - 0.5, 0.5, bx + 2.0, wy - 0.45, 0.95), "wood"))
    for lx in (bx + 0.1, bx + 1.8):
        meshes.append((_box(lx, wy - 0.9, 0, lx + 0.1, wy - 0.45, 0.42), "wood"))
    light = Light(position=np.array([-6.0, -4.0, 14.0]), intensity=0.8, ambient=0.35)
    azimuths = np.linspace(-22, 22, num_views)
    cams = _arc_cameras((0.0, wy), 8.5, 1.6, (0.0, wy, 2.9), azimuths, 0.08, rng)
    return Scene(
        "courtyard",
        meshes,
        materials,
        light,
        cams,
        focal_factor=0.75,
        sky=(0.86, 0.91, 0.98),
        depth_hint=(1.0, 60.0),
    )


SCENES = {
    "room": room,
    "facade": facade,
    "tabletop": tabletop,
    "street": street,
    "corridor": corridor,
    "courtyard": courtyard,
}


def build_scene(name: str, rng: np.random.Generator, num_views: int) -> Scene:
    if name not in SCENES:
        raise KeyError(name)
    return SCENES[name](rng, num_views)
