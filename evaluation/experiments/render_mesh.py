"""A mesh seen from one of the workspace's cameras, beside that camera's photo.

Ray casting (Open3D's ``RaycastingScene``, CPU) through every pixel of the view's pinhole
camera: the panels are the photo, the mesh shaded by its normals (a headlight: the geometry
as it is, without colour to hide it) and the mesh in its vertex colours. Pixels whose ray hits
nothing are black.

    python -m dvpmvs.evaluation.experiments.render_mesh WORKSPACE MESH --view 0000.jpg \\
        --out docs/images/fountain_mesh_0000.jpg [--panel-width 512]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from dvpmvs.workspace import Workspace


def render_view(
    mesh_path: Path, K: np.ndarray, R: np.ndarray, t: np.ndarray, width: int, height: int
):
    """(shaded, coloured) uint8 RGB images of the mesh from the camera x = K (R X + t)."""
    import open3d as o3d

    legacy = o3d.io.read_triangle_mesh(str(mesh_path))
    if not len(legacy.triangles):
        raise ValueError(f"{mesh_path} has no triangles")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(legacy))
    extrinsic = np.eye(4)
    extrinsic[:3, :3], extrinsic[:3, 3] = R, t
    rays = scene.create_rays_pinhole(o3d.core.Tensor(K), o3d.core.Tensor(extrinsic), width, height)
    hits = scene.cast_rays(rays)
    hit = np.isfinite(hits["t_hit"].numpy())
    normals = hits["primitive_normals"].numpy()
    directions = rays.numpy()[..., 3:]
    directions = directions / np.linalg.norm(directions, axis=-1, keepdims=True)
    lambert = np.abs((normals * directions).sum(axis=-1))
    shaded = np.where(hit, 40 + 200 * lambert, 0).astype(np.uint8)
    shaded = np.repeat(shaded[..., None], 3, axis=-1)
    coloured = np.zeros((height, width, 3), np.uint8)
    if legacy.has_vertex_colors():
        triangles = np.asarray(legacy.triangles)
        colours = np.asarray(legacy.vertex_colors)
        ids = hits["primitive_ids"].numpy()[hit].astype(np.int64)
        uv = hits["primitive_uvs"].numpy()[hit]
        corners = colours[triangles[ids]]  # (n, 3 vertices, rgb)
        weights = np.stack([1 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
        coloured[hit] = np.clip(
            np.round(255 * (weights[..., None] * corners).sum(axis=1)), 0, 255
        ).astype(np.uint8)
    return shaded, coloured


def render_beside_photo(
    workspace: Path, mesh: Path, view_name: str, out: Path, panel_width: int = 512
) -> Path:
    ws = Workspace.open(workspace)
    view = ws[view_name]
    shaded, coloured = render_view(mesh, view.K, view.R, view.t, view.width, view.height)
    photo = np.clip(np.round(view.load_rgb() * 255), 0, 255).astype(np.uint8)
    panel_height = round(view.height * panel_width / view.width)
    panels = [
        cv2.resize(p, (panel_width, panel_height), interpolation=cv2.INTER_AREA)
        for p in (photo, shaded, coloured)
    ]
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(
        str(out), cv2.cvtColor(np.hstack(panels), cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 88]
    )
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("workspace", type=Path)
    parser.add_argument("mesh", type=Path)
    parser.add_argument("--view", required=True, help="the image name of the camera to render from")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--panel-width", type=int, default=512)
    args = parser.parse_args(argv)
    print(render_beside_photo(args.workspace, args.mesh, args.view, args.out, args.panel_width))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
