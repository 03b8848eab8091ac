"""The Python API, with pycolmap's names and argument order where pycolmap has the function.

Options come either as the options objects (:class:`~dvpmvs.pipeline.DenseOptions`,
:class:`~dvpmvs.fusion.FusionOptions`, :class:`~dvpmvs.meshing.MeshingOptions`) or as
``overrides``: the ``key=value`` / ``group=option`` strings of the command line (presets such as
``quality=fast`` or ``method=paper``, plugins such as ``depth_prior=file``), composed exactly as
``dvpmvs <command>`` composes them, so that a script and a command with the same overrides
compute the same maps. Workspace keys (``max_image_size=...``) are always read from
``overrides``; when an options object is given, it replaces the rest.

    import dvpmvs

    summary = dvpmvs.patch_match_stereo("/data/ws", overrides=["quality=medium"])
    fusion = dvpmvs.stereo_fusion("/data/ws/fused.ply", "/data/ws")
    mesh = dvpmvs.poisson_meshing("/data/ws/fused.ply", "/data/ws/meshed-poisson.ply")
    project = dvpmvs.reconstruct("/data/photos", "/data/project", overrides=["quality=fast"])
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from dvpmvs import config

__all__ = ["delaunay_meshing", "dense_options", "patch_match_stereo", "poisson_meshing", "reconstruct",
           "stereo_fusion"]


def dense_options(overrides: Sequence[str] = ()):
    """The :class:`~dvpmvs.pipeline.DenseOptions` that ``dvpmvs dense <overrides>`` runs with."""
    return config.dense_options(config.compose("dense", overrides))


def _workspace(workspace_path, cfg):
    from dvpmvs.workspace import Workspace

    return Workspace.open(Path(workspace_path).expanduser(), config.workspace_options(cfg))


def patch_match_stereo(workspace_path: str | Path, options=None, overrides: Sequence[str] = (),
                       output_path: str | Path | None = None, progress: bool = False):
    """Depth and normal maps of every view of the COLMAP dense workspace ``workspace_path``, in
    COLMAP's format under ``<output_path or workspace>/stereo`` (as ``pycolmap.patch_match_stereo``:
    maps only, no fusion). Returns the :class:`~dvpmvs.pipeline.DenseSummary`; views whose maps
    the same inputs made are reused."""
    from dvpmvs.pipeline import run_dense

    cfg = config.compose("dense", overrides)
    options = config.dense_options(cfg) if options is None else options
    return run_dense(_workspace(workspace_path, cfg), replace(options, fuse=False), progress=progress,
                     out=output_path)


def stereo_fusion(output_path: str | Path, workspace_path: str | Path, input_type: str = "geometric",
                  options=None, overrides: Sequence[str] = (), backend: str = "dvpmvs"):
    """Fuse the workspace's ``input_type`` maps into the PLY ``output_path`` and its ``.vis`` (as
    ``pycolmap.stereo_fusion``); ``backend="colmap"`` runs COLMAP's own fusion on them. Returns
    the :class:`~dvpmvs.pipeline.FusionReport` (points, seconds, whether an identical cloud was
    reused)."""
    from dvpmvs.pipeline import fuse_workspace

    cfg = config.compose("fuse", [*overrides, f"input_type={input_type}"])
    options = config.fusion_options(cfg, input_type) if options is None else replace(options, input_type=input_type)
    return fuse_workspace(_workspace(workspace_path, cfg), options, backend, Path(output_path).expanduser(),
                          progress=False)


def poisson_meshing(input_path: str | Path, output_path: str | Path, options=None):
    """A screened Poisson mesh of the cloud ``input_path`` (as ``pycolmap.poisson_meshing``;
    ``options.method`` ``poisson``, Open3D's, or ``colmap_poisson``). Returns the
    :class:`~dvpmvs.meshing.MeshReport`."""
    from dvpmvs.meshing import MeshingOptions, mesh_cloud

    options = options or MeshingOptions()
    if options.method == "delaunay":
        raise ValueError("poisson_meshing takes method poisson or colmap_poisson; use delaunay_meshing")
    return mesh_cloud(input_path, output_path, options)


def delaunay_meshing(input_path: str | Path, output_path: str | Path, options=None):
    """COLMAP's visibility-based Delaunay mesh of the dense workspace ``input_path`` (its
    ``fused.ply``, ``fused.ply.vis`` and sparse model; as ``pycolmap.delaunay_meshing`` with
    ``input_type="dense"``), through a COLMAP program built with CGAL
    (``options.colmap_binary``)."""
    from dvpmvs.meshing import MeshingOptions, mesh_cloud
    from dvpmvs.workspace import Workspace

    options = replace(options or MeshingOptions(), method="delaunay")
    workspace = Workspace.open(Path(input_path).expanduser())
    return mesh_cloud(workspace.root / "fused.ply", output_path, options, model_dir=workspace.model_dir)


def reconstruct(image_path: str | Path, workspace_path: str | Path, overrides: Sequence[str] = (),
                sparse_path: str | Path | None = None, progress: bool = False):
    """``dvpmvs reconstruct images=<image_path> out=<workspace_path> <overrides>``: structure
    from motion, undistortion, dense stage, fusion and mesh (``mesh=false`` skips the mesh);
    finished stages are reused. Returns the
    :class:`~dvpmvs.reconstruction.ReconstructSummary`."""
    from dvpmvs.reconstruction import reconstruct as run

    cfg = config.compose("reconstruct", overrides)
    return run(image_path, workspace_path, sfm=config.sfm_options(cfg),
               workspace_options=config.workspace_options(cfg), dense_options=config.dense_options(cfg),
               meshing_options=config.meshing_options(cfg) if cfg.mesh else None, sparse=sparse_path,
               max_image_size=config.typed(cfg, "max_image_size", int), progress=progress,
               overwrite=config.typed(cfg, "overwrite", bool), recursive=config.typed(cfg, "recursive", bool))
