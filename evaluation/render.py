"""Ray-cast rendering of a synthetic scene with exact depth and normals (Open3D).

Pixel convention: pixel ``[row, col]`` shows the image point ``(col, row)`` of the PINHOLE
camera, the convention of COLMAP's dense stage (PatchMatch and fusion back-project ``(col, row)``
with the depth stored at ``[row, col]``), so the ground-truth maps are directly comparable with
COLMAP-format depth maps.

Shading: textured albedo, ambient + Lambert light with cast shadows (shadow rays), and a
Blinn-Phong specular lobe (view-dependent highlights, which break photo-consistency on purpose).
Colours are 2x2 supersampled; depth and normals come from the pixel-centre ray. The specular
term is also returned on its own (the ground truth of highlight detection).

What differs between machines is kept out of the pixels: the ray caster (Embree, with kernels
per CPU) only says which triangle a ray hits; the hit's distance and normal are computed here in
float64 from that triangle, as is all shading, and rounded once at the end. Float32 results of
the caster or of numpy's transcendental functions (whose SIMD variants differ in the last bits)
never reach an image or a ground-truth map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from dvpmvs.evaluation.portable import inverse_intrinsics, matmul, power, transposed_matvec
from dvpmvs.evaluation.synthetic_scenes import Scene

__all__ = ["Rendering", "SceneRenderer"]

_SUBPIXEL = ((-0.25, -0.25), (0.25, -0.25), (-0.25, 0.25), (0.25, 0.25))


@dataclass
class Rendering:
    image: np.ndarray  # (H, W, 3) float32 in [0, 1], before sensor noise
    depth: np.ndarray  # (H, W) float32, z in the camera frame; 0 where a ray escapes
    normal: np.ndarray  # (H, W, 3) float32, camera frame, facing the camera; 0 where no surface
    # (H, W) float32: the specular term (the same in every channel)
    specular: np.ndarray | None = None
    # (H, W, 3) float32 in [0, 1]: the image without its specular term
    diffuse: np.ndarray | None = None
    textureless: np.ndarray | None = None  # (H, W) bool: the pixel-centre ray hits a plain material


class SceneRenderer:
    """Holds the ray-casting scene and the textures; renders any PINHOLE view of it."""

    def __init__(self, scene: Scene, textures: dict[str, np.ndarray]):
        self.scene = scene
        self._raycaster = o3d.t.geometry.RaycastingScene()
        self._material_of_geometry = []
        names = sorted(scene.materials)
        self._materials = [scene.materials[n] for n in names]
        self._textures = [textures[n] for n in names]
        index = {n: i for i, n in enumerate(names)}
        corners = []  # per geometry: (T, 3, 3) float64, each triangle's vertices
        for mesh, material in scene.meshes:
            gid = self._raycaster.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
            assert gid == len(self._material_of_geometry)
            self._material_of_geometry.append(index[material])
            corners.append(
                np.asarray(mesh.vertices, np.float64)[np.asarray(mesh.triangles, np.int64)]
            )
        self._material_of_geometry = np.asarray(self._material_of_geometry, np.int64)
        # All triangles in one table, a geometry's first triangle at its offset.
        self._offsets = np.cumsum([0] + [len(c) for c in corners[:-1]]).astype(np.int64)
        self._triangles = np.concatenate(corners) if corners else np.zeros((0, 3, 3))

    def _cast(self, origin: np.ndarray, dirs: np.ndarray) -> dict:
        """Which triangle each ray (float64 ``origin``, ``dirs`` (..., 3)) hits, from the ray caster,
        and where: ``t_hit`` (inf: none) and the triangle's unit normal, both in float64 from the
        triangle's vertices (:func:`_ray_triangle`)."""
        rays = np.concatenate([np.broadcast_to(origin, dirs.shape), dirs], axis=-1).astype(
            np.float32
        )
        out = self._raycaster.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays)))
        geometry = out["geometry_ids"].numpy().astype(np.int64)
        hit = np.isfinite(out["t_hit"].numpy())
        t_hit = np.full(hit.shape, np.inf)
        normals = np.zeros(hit.shape + (3,))
        triangles = self._triangles[
            self._offsets[geometry[hit]] + out["primitive_ids"].numpy()[hit].astype(np.int64)
        ]
        origins = np.broadcast_to(np.asarray(origin, np.float64), dirs.shape)[hit]
        t_hit[hit], normals[hit] = _ray_triangle(
            origins, np.asarray(dirs, np.float64)[hit], triangles
        )
        return {"t_hit": t_hit, "geometry_ids": geometry, "primitive_normals": normals}

    def _albedo(
        self, material_index: np.ndarray, points: np.ndarray, normals: np.ndarray
    ) -> np.ndarray:
        """Texture lookup, projected along each point's dominant normal axis (tiles repeat)."""
        albedo = np.zeros(points.shape, np.float32)
        axis = np.argmax(np.abs(normals), axis=1)
        # The two in-plane world axes for a normal along x, y or z.
        plane_axes = np.array([[1, 2], [0, 2], [0, 1]])
        for m in np.unique(material_index):
            sel = material_index == m
            material, texture = self._materials[m], self._textures[m]
            ax = plane_axes[axis[sel]]
            u = np.take_along_axis(points[sel], ax[:, :1], axis=1)[:, 0] / material.tile
            v = np.take_along_axis(points[sel], ax[:, 1:], axis=1)[:, 0] / material.tile
            albedo[sel] = _sample_wrapped(texture, u, v)
        return albedo

    def render(
        self, K: np.ndarray, R: np.ndarray, t: np.ndarray, width: int, height: int
    ) -> Rendering:
        center = transposed_matvec(-R, t)
        Kinv = inverse_intrinsics(K)
        cols, rows = np.meshgrid(
            np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64)
        )

        def directions(dx, dy):
            pix = np.stack([cols + dx, rows + dy, np.ones_like(cols)], axis=-1)
            # Camera-frame direction with z = 1, so a hit's ray parameter is its depth.
            return matmul(matmul(pix, Kinv.T), R)

        d0 = directions(0.0, 0.0)
        centre_hits = self._cast(center, d0)
        t_hit = centre_hits["t_hit"]
        hit = np.isfinite(t_hit)
        depth = np.where(hit, t_hit, 0).astype(np.float32)
        normal_world = centre_hits["primitive_normals"].astype(np.float64)
        flip = np.sum(normal_world * d0, axis=-1) > 0
        normal_world[flip] *= -1
        normal = matmul(normal_world, R.T).astype(np.float32)
        normal[~hit] = 0
        uniform = np.array([m.is_plain for m in self._materials])
        textureless = np.zeros(hit.shape, bool)
        textureless[hit] = uniform[self._material_of_geometry[centre_hits["geometry_ids"][hit]]]

        color = np.zeros((height, width, 3), np.float64)
        specular = np.zeros((height, width), np.float64)
        for dx, dy in _SUBPIXEL:
            shaded, lobe = self._shade(center, directions(dx, dy))
            color += shaded
            specular += lobe
        color /= len(_SUBPIXEL)
        specular /= len(_SUBPIXEL)
        diffuse = np.clip(color - specular[..., None], 0, 1).astype(np.float32)
        return Rendering(
            np.clip(color, 0, 1).astype(np.float32),
            depth,
            normal,
            specular.astype(np.float32),
            diffuse,
            textureless,
        )

    def _shade(self, center: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Colours (..., 3) of the rays and their specular term (...) (white light: the same in
        every channel)."""
        shape = dirs.shape[:-1]
        dirs = dirs.reshape(-1, 3)
        hits = self._cast(center, dirs)
        t_hit = hits["t_hit"].reshape(-1)
        hit = np.isfinite(t_hit)
        color = np.zeros((len(dirs), 3))
        lobe = np.zeros(len(dirs))
        if self.scene.sky is not None:
            # A faint vertical gradient, brighter towards the horizon.
            up = dirs[:, 2] / np.linalg.norm(dirs, axis=1)
            color[:] = np.asarray(self.scene.sky) * (1.0 - 0.25 * np.clip(up, 0, 1))[:, None]
        if not np.any(hit):
            return color.reshape(*shape, 3), lobe.reshape(shape)
        d = dirs[hit]
        p = center + d * t_hit[hit, None]
        n = hits["primitive_normals"].reshape(-1, 3)[hit].astype(np.float64)
        n[np.sum(n * d, axis=1) > 0] *= -1
        material = self._material_of_geometry[hits["geometry_ids"].reshape(-1)[hit]]
        albedo = self._albedo(material, p, n)

        light = self.scene.light
        if light.position is not None:
            to_light = light.position - p  # ray parameter 1 reaches the light
        else:
            to_light = np.broadcast_to(-light.direction * 1e4, p.shape)
        scale = np.linalg.norm(p - center, axis=1, keepdims=True)
        origins = p + n * (1e-4 * scale + 1e-6)
        shadow_rays = np.concatenate([origins, to_light], axis=1).astype(np.float32)
        occluded = (
            self._raycaster.test_occlusions(
                o3d.core.Tensor(np.ascontiguousarray(shadow_rays)), tnear=1e-5, tfar=1.0
            )
            .numpy()
            .astype(bool)
        )
        lit = (~occluded).astype(np.float64)[:, None]
        l_dir = to_light / np.linalg.norm(to_light, axis=1, keepdims=True)
        v_dir = -d / np.linalg.norm(d, axis=1, keepdims=True)
        lambert = np.clip(np.sum(n * l_dir, axis=1, keepdims=True), 0, None)
        half = l_dir + v_dir
        half /= np.linalg.norm(half, axis=1, keepdims=True)
        specular_coef = np.array([m.specular for m in self._materials])[material][:, None]
        shininess = np.array([m.shininess for m in self._materials])[material][:, None]
        highlight = power(np.clip(np.sum(n * half, axis=1, keepdims=True), 0, None), shininess)
        shaded = albedo * (light.ambient + light.intensity * lambert * lit)
        specular = specular_coef * light.intensity * highlight * lit * (lambert > 0)
        shaded += specular
        color[hit] = shaded
        lobe[hit] = specular[:, 0]
        return color.reshape(*shape, 3), lobe.reshape(shape)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot product of (N, 3) arrays, summed in one fixed order."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _ray_triangle(
    origins: np.ndarray, dirs: np.ndarray, triangles: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The ray parameter where each ray meets the plane of its triangle (Moller-Trumbore) and
    the triangle's unit normal (the winding's), in float64: (N,) and (N, 3)."""
    v0, v1, v2 = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    e1, e2 = v1 - v0, v2 - v0
    p = np.cross(dirs, e2)
    q = np.cross(origins - v0, e1)
    t = _dot(e2, q) / _dot(e1, p)
    normal = np.cross(e1, e2)
    normal /= np.sqrt(_dot(normal, normal))[:, None]
    return t, normal


def _sample_wrapped(texture: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a tiling texture at texture coordinates (u, v) in tiles."""
    h, w = texture.shape[:2]
    x = np.mod(u, 1.0) * w - 0.5
    y = np.mod(v, 1.0) * h - 0.5
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    fx = (x - x0)[:, None]
    fy = (y - y0)[:, None]
    x0 %= w
    y0 %= h
    x1 = (x0 + 1) % w
    y1 = (y0 + 1) % h
    top = texture[y0, x0] * (1 - fx) + texture[y0, x1] * fx
    bottom = texture[y1, x0] * (1 - fx) + texture[y1, x1] * fx
    return (top * (1 - fy) + bottom * fy).astype(np.float32)
