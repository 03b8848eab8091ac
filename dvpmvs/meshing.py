"""Surface meshes from a fused cloud: screened Poisson (Open3D's or COLMAP's) and COLMAP's
visibility-based Delaunay mesher.

``poisson`` (the default) is Open3D's screened Poisson reconstruction, trimmed by removing the
vertices whose sample density is in the lowest ``trim_quantile`` of the mesh: a share, so that
it means the same on any cloud. ``colmap_poisson`` is COLMAP's own (through pycolmap), trimmed
by COLMAP's absolute density value ``colmap_trim``: COLMAP's default of 10 removes every
vertex of a cloud of tens of thousands of points (measured on the embedded scene), so ours is
7. Against ground truth (``evaluation/experiments/mesh_quality.py``), surface samples of
``poisson`` score as well as ``colmap_poisson`` on the embedded scene and better on the
synthetic facade, in less time (docs/benchmarks.md, "Which mesher").

``delaunay`` is COLMAP's ``delaunay_mesher``, which also reads the views supporting each point
(``<cloud>.vis``, written by our fusion). pycolmap's wheels and Debian's ``colmap`` package are
built without CGAL, which it needs: it runs when the COLMAP program named by ``colmap_binary``
was built with CGAL, and the error says so otherwise.

Meshing is multi-threaded inside Poisson; with more than one thread, its output differs in
the last bits from run to run, so ``num_threads`` is 1 by default (the same cloud gives the
same bytes); 0 uses every core.
"""

from __future__ import annotations

import logging
import shutil
import subprocess
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from dvpmvs.digests import file_digest
from dvpmvs.errors import DvpmvsError
from dvpmvs.maps import atomic_path
from dvpmvs.options.meshing import MESHING_METHODS, MeshingOptions
from dvpmvs.pointcloud import PlyFormatError, ply_element_counts, read_cloud
from dvpmvs.provenance import CachedOutput, code_identity
from dvpmvs.validation import check_ply_output, resolve_threads

__all__ = [
    "MESHING_METHODS",
    "MIN_MESH_POINTS",
    "MeshReport",
    "MeshingError",
    "MeshingOptions",
    "default_mesh_path",
    "mesh_cloud",
    "mesh_record_path",
]

log = logging.getLogger(__name__)

# Fewer points carry no surface to speak of: Poisson closes them into a blob of thousands of
# triangles, Delaunay into a few tetrahedra's faces.
MIN_MESH_POINTS = 100
# A Poisson mesh reaching this share of the cloud's extent beyond the cloud's bounding box is
# surface the cloud does not support (an open scene closed by Poisson): untrimmed, the synthetic
# room's mesh reaches 0.24, trimmed by the default 0.05 quantile 0.045.
_OVERSHOOT_WARNING = 0.1


class MeshingError(DvpmvsError, RuntimeError):
    """A mesh cannot be made: the cloud or the mesher is missing or failed."""


@dataclass
class MeshReport:
    output: Path
    vertices: int
    triangles: int
    seconds: float
    reused: bool


def default_mesh_path(folder: str | Path, method: str) -> Path:
    """COLMAP's names: ``meshed-poisson.ply``, ``meshed-delaunay.ply`` (and ours for COLMAP's
    Poisson, ``meshed-colmap_poisson.ply``)."""
    return Path(folder) / f"meshed-{method}.ply"


def mesh_record_path(mesh: str | Path) -> Path:
    mesh = Path(mesh)
    return mesh.with_name(mesh.name + ".provenance.json")


def mesh_cloud(
    cloud: str | Path,
    output: str | Path,
    options: MeshingOptions | None = None,
    model_dir: str | Path | None = None,
    reuse: bool = True,
) -> MeshReport:
    """Mesh the PLY ``cloud`` into ``output`` (binary PLY, written atomically). ``delaunay``
    also needs the cloud's ``.vis`` and the sparse model ``model_dir`` its image numbers refer
    to. With ``reuse``, a mesh whose record names the same cloud (by content), options and code
    is kept. Speed-only options (num_threads) are part of the record: more threads change the
    bytes."""
    options = options or MeshingOptions()
    cloud, output = Path(cloud).expanduser(), Path(output).expanduser()
    if not cloud.is_file():
        raise MeshingError(
            f"the point cloud {cloud} does not exist; run `dvpmvs dense` or `dvpmvs fuse` first"
        )
    check_ply_output(output, "meshes", "meshed-poisson.ply")
    count = _cloud_points(cloud)
    if count < MIN_MESH_POINTS:
        raise MeshingError(
            f"the point cloud {cloud} has {count:,} point(s); meshing needs at least "
            f"{MIN_MESH_POINTS} (fewer give a closed blob, not a surface): fuse more views, or lower "
            f"fusion_options.min_consistent_views"
        )
    visibility = cloud.with_name(cloud.name + ".vis")
    if options.method == "delaunay":
        if not visibility.is_file():
            raise MeshingError(
                f"meshing.method=delaunay reads which views support each point from {visibility}, "
                f"which is missing: fuse again with `dvpmvs fuse` (it writes it)"
            )
        if model_dir is None or not Path(model_dir).is_dir():
            raise MeshingError(
                "meshing.method=delaunay needs the workspace's sparse model (give workspace=WS)"
            )
    inputs = {"cloud": file_digest(cloud), "meshing": asdict(options), "code": code_identity()}
    if options.method == "delaunay":
        inputs["visibility"] = file_digest(visibility)
    cached = CachedOutput.check(mesh_record_path(output), inputs, output.parent, [output])
    if reuse and cached.current is not None:
        log.info("meshing: the mesh %s is current (same cloud and options): reused", output)
        stats = cached.current.stats
        return MeshReport(
            output,
            int(stats.get("vertices", 0)),
            int(stats.get("triangles", 0)),
            float(stats.get("seconds", 0.0)),
            True,
        )
    start = time.perf_counter()
    with cached.making(overwrite=not reuse):
        overshoot = None
        if options.method == "poisson":
            vertices, triangles, overshoot = _open3d_poisson(cloud, output, options)
        elif options.method == "colmap_poisson":
            vertices, triangles, overshoot = _colmap_poisson(cloud, output, options)
        else:
            vertices, triangles = _colmap_delaunay(
                cloud, visibility, Path(model_dir), output, options
            )
    seconds = time.perf_counter() - start
    if not triangles:
        log.warning(
            "meshing kept no triangle of %s (method %s); a smaller trim keeps more",
            cloud,
            options.method,
        )
    else:
        _warn_overshoot(output, options, overshoot)
    cached.complete(
        {"mesh": output}, {"vertices": vertices, "triangles": triangles, "seconds": seconds}
    )
    return MeshReport(output, vertices, triangles, seconds, False)


def _cloud_points(cloud: Path) -> int:
    """The points of a cloud file: a PLY's header count, or what Open3D reads of other formats."""
    with open(cloud, "rb") as f:
        is_ply = f.read(3) == b"ply"
    if is_ply:
        return ply_element_counts(cloud)[0]
    return len(read_cloud(cloud).points)


def _overshoot(points: np.ndarray, vertices: np.ndarray) -> tuple[float, float, float] | None:
    """How far a mesh's ``vertices`` reach beyond the bounding box of its cloud's ``points``:
    (reach, the cloud's extent, the share of vertices more than 1 % of the extent outside); None
    for an empty cloud or mesh."""
    if not len(points) or not len(vertices):
        return None
    lo, hi = points.min(axis=0), points.max(axis=0)
    extent = float(np.linalg.norm(hi - lo))
    beyond = np.maximum(lo - vertices, vertices - hi).max(axis=1)  # per vertex, outside the box
    return float(beyond.max()), extent, float((beyond > 0.01 * extent).mean())


def _warn_overshoot(
    mesh_path: Path, options: MeshingOptions, overshoot: tuple[float, float, float] | None
) -> None:
    """Warn when a Poisson mesh reaches far beyond its cloud's bounding box (how far, and the
    trim that keeps it closer); ``overshoot``: ``_overshoot``'s figures, None for none (a
    Delaunay mesh, an empty cloud or mesh)."""
    if overshoot is None:
        return
    reach, extent, outside = overshoot
    if extent > 0 and reach > _OVERSHOOT_WARNING * extent:
        trim = "meshing.trim_quantile" if options.method == "poisson" else "meshing.colmap_trim"
        log.warning(
            "the mesh %s reaches %.3g beyond the bounding box of its cloud (%.0f %% of the cloud's extent "
            "%.3g; %.1f %% of its vertices lie outside the box): Poisson closed the surface where the cloud "
            "has no points; a larger %s trims it",
            mesh_path,
            reach,
            100 * reach / extent,
            extent,
            100 * outside,
            trim,
        )


def _threads(options: MeshingOptions) -> int:
    return resolve_threads(options.num_threads)


def _open3d_poisson(
    cloud: Path, output: Path, options: MeshingOptions
) -> tuple[int, int, tuple[float, float, float] | None]:
    from dvpmvs.stage_progress import in_child_process

    # In a child process: Open3D holds the GIL until the mesh is made, and the meshing step's
    # heartbeat would say nothing for that long.
    with atomic_path(output, suffix=".tmp.ply") as tmp:
        return in_child_process(_poisson_mesh_file, cloud, tmp, options)


def _poisson_mesh_file(
    cloud: Path, output: Path, options: MeshingOptions
) -> tuple[int, int, tuple[float, float, float] | None]:
    """Open3D's screened Poisson mesh of ``cloud``, trimmed, written to ``output``: its
    vertices, its triangles and how far it reaches beyond the cloud (``_overshoot``, measured
    here, where cloud and mesh are in memory)."""
    import open3d as o3d

    try:
        points = read_cloud(cloud)
    except PlyFormatError as exc:
        raise MeshingError(str(exc)) from None
    if len(points.points) == 0:
        raise MeshingError(f"the point cloud {cloud} has no points: nothing to mesh")
    if not points.has_normals():
        # A cloud without normals (not one of ours or COLMAP's): Poisson needs them.
        points.estimate_normals()
        points.orient_normals_towards_camera_location(
            points.get_center() + np.array([0.0, 0.0, -1e6])
        )
    mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
        points, depth=options.depth, n_threads=_threads(options)
    )
    density = np.asarray(density)
    if options.trim_quantile > 0 and len(density):
        mesh.remove_vertices_by_mask(density < np.quantile(density, options.trim_quantile))
    mesh.remove_unreferenced_vertices()
    if mesh.has_vertex_colors():
        # Poisson's interpolated colours overshoot [0, 1] near edges.
        mesh.vertex_colors = o3d.utility.Vector3dVector(
            np.clip(np.asarray(mesh.vertex_colors), 0.0, 1.0)
        )
    if not o3d.io.write_triangle_mesh(str(output), mesh, write_ascii=False):
        raise MeshingError(f"could not write the mesh {output}")
    overshoot = _overshoot(np.asarray(points.points), np.asarray(mesh.vertices))
    return len(mesh.vertices), len(mesh.triangles), overshoot


def _colmap_poisson(
    cloud: Path, output: Path, options: MeshingOptions
) -> tuple[int, int, tuple[float, float, float] | None]:
    """COLMAP's Poisson mesh of ``cloud`` written to ``output``: its vertices, its triangles and
    how far it reaches beyond the cloud (``_overshoot``, from the files COLMAP read and wrote)."""
    import open3d as o3d
    import pycolmap

    if not _has_normals(cloud):
        # COLMAP's mesher then logs an error and writes nothing, without raising.
        raise MeshingError(
            f"meshing.method=colmap_poisson needs a cloud with normals (nx, ny, nz); {cloud} has none: "
            f"use meshing.method=poisson, which estimates them"
        )
    colmap_options = pycolmap.PoissonMeshingOptions()
    colmap_options.depth = options.depth
    colmap_options.trim = options.colmap_trim
    colmap_options.num_threads = options.num_threads or -1
    with atomic_path(output, suffix=".tmp.ply") as tmp:
        try:
            pycolmap.poisson_meshing(cloud, tmp, colmap_options)
        except (RuntimeError, ValueError) as exc:
            raise MeshingError(f"COLMAP's Poisson mesher failed on {cloud}: {exc}") from None
        if not tmp.is_file() or not tmp.read_bytes()[:3] == b"ply":
            raise MeshingError(
                f"COLMAP's Poisson mesher wrote no mesh for {cloud} (its log says why; verbose=true "
                f"shows it)"
            )
        overshoot = _overshoot(
            np.asarray(read_cloud(cloud).points),
            np.asarray(o3d.io.read_triangle_mesh(str(tmp)).vertices),
        )
        return (*ply_element_counts(tmp), overshoot)


def _has_normals(cloud: Path) -> bool:
    """Whether a PLY's vertices carry nx, ny, nz (other formats: whatever Open3D reads)."""
    with open(cloud, "rb") as f:
        head = f.read(65536)
    if head[:3] == b"ply" and b"end_header" in head:
        names = {
            line.split()[-1]
            for line in head[: head.index(b"end_header")].split(b"\n")
            if line.startswith(b"property")
        }
        return {b"nx", b"ny", b"nz"} <= names
    return read_cloud(cloud).has_normals()


def _colmap_delaunay(
    cloud: Path, visibility: Path, model_dir: Path, output: Path, options: MeshingOptions
) -> tuple[int, int]:
    binary = shutil.which(options.colmap_binary)
    if binary is None:
        raise MeshingError(
            f"meshing.method=delaunay runs COLMAP's delaunay_mesher, and no program "
            f"{options.colmap_binary!r} was found; install COLMAP built with CGAL and give its path "
            f"as meshing.colmap_binary=..., or use meshing.method=poisson"
        )
    # COLMAP's mesher reads DIR/sparse, DIR/fused.ply and DIR/fused.ply.vis: a folder of links.
    with tempfile.TemporaryDirectory(prefix=".dvpmvs-delaunay-", dir=output.parent) as folder:
        folder = Path(folder)
        (folder / "sparse").symlink_to(model_dir.resolve(), target_is_directory=True)
        (folder / "fused.ply").symlink_to(cloud.resolve())
        (folder / "fused.ply.vis").symlink_to(visibility.resolve())
        with atomic_path(output, suffix=".tmp.ply") as tmp:
            run = subprocess.run(
                [
                    binary,
                    "delaunay_mesher",
                    "--input_path",
                    str(folder),
                    "--input_type",
                    "dense",
                    "--output_path",
                    str(tmp),
                    "--DelaunayMeshing.num_threads",
                    str(options.num_threads or -1),
                ],
                capture_output=True,
                text=True,
            )
            text = run.stdout + run.stderr
            if "requires CGAL" in text:
                raise MeshingError(
                    f"the COLMAP program {binary} was built without CGAL, which its delaunay_mesher "
                    f"needs (pycolmap's wheels and Debian's colmap package are); give a COLMAP built "
                    f"with CGAL as meshing.colmap_binary=..., or use meshing.method=poisson"
                )
            if run.returncode != 0 or not tmp.stat().st_size:
                raise MeshingError(
                    f"COLMAP's delaunay_mesher failed on {cloud} (exit {run.returncode}): "
                    f"{text.strip()[-1500:]}"
                )
            return ply_element_counts(tmp)
