"""The Python API, with pycolmap's names and argument order where pycolmap has the function.

Options come either as the options objects (:class:`~dvpmvs.dense.DenseOptions`,
:class:`~dvpmvs.fusion.FusionOptions`, :class:`~dvpmvs.meshing.MeshingOptions`) or as
``overrides``: the ``key=value`` / ``group=option`` strings of the command line (presets such as
``quality=fast`` or ``method=paper``, plugins such as ``depth_prior=file``), composed exactly as
``dvpmvs <command>`` composes them, so that a script and a command with the same overrides
compute the same maps. Workspace keys (``max_image_size=...``) are always read from
``overrides``; when an options object is given, it replaces the rest.

The functions may be called from several threads at once (each composes its configuration under
a lock; runs into the same output folder wait for each other's writer lock). Open3D's meshing (and
the report's mesh) run in a child process that re-runs the main script first, as
``multiprocessing``'s spawn does: a script calls them under ``if __name__ == "__main__":``.

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

__all__ = [
    "delaunay_meshing",
    "dense_options",
    "patch_match_stereo",
    "poisson_meshing",
    "reconstruct",
    "stereo_fusion",
]


def dense_options(overrides: Sequence[str] = ()):
    """The options ``dvpmvs dense <overrides>`` runs with.

    Parameters
    ----------
    overrides : sequence of str
        ``key=value`` and ``group=option`` strings as on the command line.

    Returns
    -------
    dvpmvs.dense.DenseOptions
    """
    return config.dense_options(config.compose("dense", overrides))


def _check_options(options, kind: type, function: str) -> None:
    """``options`` must be None or a ``kind`` (a dict of settings is passed as overrides)."""
    if options is not None and not isinstance(options, kind):
        raise TypeError(
            f"{function}: options must be a {kind.__module__}.{kind.__name__} or None, got "
            f"{type(options).__name__}; settings as key=value strings go in overrides=[...] (e.g. "
            f"overrides=['patch_match.num_iterations=2'])"
        )


def _workspace(workspace_path, cfg):
    from dvpmvs.workspace import Workspace

    return Workspace.open(Path(workspace_path).expanduser(), config.workspace_options(cfg))


def patch_match_stereo(
    workspace_path: str | Path,
    options=None,
    overrides: Sequence[str] = (),
    output_path: str | Path | None = None,
    progress: bool = False,
):
    """Depth and normal maps of every view of a COLMAP dense workspace, in COLMAP's format (as
    ``pycolmap.patch_match_stereo``: maps only, no fusion); views whose maps the same inputs made
    are reused.

    Parameters
    ----------
    workspace_path : str or Path
        The workspace (``images/``, ``sparse/``, ``stereo/``), as ``colmap image_undistorter``
        writes it.
    options : dvpmvs.dense.DenseOptions, optional
        Replaces the options composed from ``overrides`` (workspace keys are still read there).
    overrides : sequence of str
        Command-line overrides (``quality=fast``, ``depth_prior=file`` ...).
    output_path : str or Path, optional
        Where the maps go (``<output_path>/stereo``); by default the workspace itself.
    progress : bool
        Progress bars on standard error.

    Returns
    -------
    dvpmvs.dense.DenseSummary
        Per view and pass: computed or reused, seconds, the estimator's work.
    """
    from dvpmvs.dense import DenseOptions, run_dense

    _check_options(options, DenseOptions, "patch_match_stereo")
    cfg = config.compose("dense", overrides)
    options = config.dense_options(cfg) if options is None else options
    return run_dense(
        _workspace(workspace_path, cfg),
        replace(options, fuse=False),
        progress=progress,
        out=output_path,
    )


def stereo_fusion(
    output_path: str | Path,
    workspace_path: str | Path,
    input_type: str = "geometric",
    options=None,
    overrides: Sequence[str] = (),
    backend: str = "dvpmvs",
):
    """Fuse a workspace's maps into a PLY cloud and its ``.vis`` (as ``pycolmap.stereo_fusion``).

    Parameters
    ----------
    output_path : str or Path
        The cloud to write (``.ply``).
    workspace_path : str or Path
        The dense workspace whose ``stereo/`` holds the maps.
    input_type : {"geometric", "photometric"}
        Which pass's maps.
    options : dvpmvs.fusion.FusionOptions, optional
        Replaces the options composed from ``overrides``.
    overrides : sequence of str
        ``dvpmvs fuse`` overrides (``fusion_options.min_consistent_views=3`` ...; ``overwrite=true``
        replaces a cloud dvpmvs did not write).
    backend : {"dvpmvs", "colmap"}
        ``colmap`` runs COLMAP's own fusion on the same maps.

    Returns
    -------
    dvpmvs.dense.FusionReport
        Points, seconds, and whether an identical cloud was reused.
    """
    from dvpmvs.dense import fuse_workspace
    from dvpmvs.fusion import FusionOptions

    _check_options(options, FusionOptions, "stereo_fusion")
    cfg = config.compose("fuse", [*config.checked_overrides(overrides), f"input_type={input_type}"])
    options = (
        config.fusion_options(cfg, input_type)
        if options is None
        else replace(options, input_type=input_type)
    )
    return fuse_workspace(
        _workspace(workspace_path, cfg),
        options,
        backend,
        Path(output_path).expanduser(),
        progress=False,
        overwrite=config.typed(cfg, "overwrite", bool),
    )


def poisson_meshing(input_path: str | Path, output_path: str | Path, options=None):
    """A screened Poisson mesh of a cloud (as ``pycolmap.poisson_meshing``).

    Parameters
    ----------
    input_path : str or Path
        The cloud (a PLY with normals).
    output_path : str or Path
        The mesh to write (``.ply``).
    options : dvpmvs.meshing.MeshingOptions, optional
        ``method`` ``poisson`` (Open3D's, the default) or ``colmap_poisson``.

    Returns
    -------
    dvpmvs.meshing.MeshReport
        Vertices, triangles, seconds, and whether an identical mesh was reused.
    """
    from dvpmvs.meshing import MeshingOptions, mesh_cloud

    _check_options(options, MeshingOptions, "poisson_meshing")
    options = options or MeshingOptions()
    if options.method == "delaunay":
        raise ValueError(
            "poisson_meshing takes method poisson or colmap_poisson; use delaunay_meshing"
        )
    return mesh_cloud(input_path, output_path, options)


def delaunay_meshing(input_path: str | Path, output_path: str | Path, options=None):
    """COLMAP's visibility-based Delaunay mesh of a dense workspace (as
    ``pycolmap.delaunay_meshing`` with ``input_type="dense"``), through a COLMAP program built
    with CGAL.

    Parameters
    ----------
    input_path : str or Path
        The dense workspace: its ``fused.ply``, ``fused.ply.vis`` and sparse model are read.
    output_path : str or Path
        The mesh to write (``.ply``).
    options : dvpmvs.meshing.MeshingOptions, optional
        ``colmap_binary`` names the COLMAP program.

    Returns
    -------
    dvpmvs.meshing.MeshReport
    """
    from dvpmvs.meshing import MeshingOptions, mesh_cloud
    from dvpmvs.workspace import Workspace

    _check_options(options, MeshingOptions, "delaunay_meshing")
    options = replace(options or MeshingOptions(), method="delaunay")
    workspace = Workspace.open(Path(input_path).expanduser())
    return mesh_cloud(
        workspace.root / "fused.ply", output_path, options, model_dir=workspace.model_dir
    )


def reconstruct(
    image_path: str | Path,
    workspace_path: str | Path,
    overrides: Sequence[str] = (),
    sparse_path: str | Path | None = None,
    progress: bool = False,
):
    """From photos to a cloud and a mesh, as ``dvpmvs reconstruct images=<image_path>
    out=<workspace_path> <overrides>``: structure from motion, undistortion, dense stage, fusion
    and mesh; finished stages are reused.

    Parameters
    ----------
    image_path : str or Path
        The folder of photos (outside ``workspace_path``).
    workspace_path : str or Path
        The project folder (``sparse/``, ``dense/`` ...).
    overrides : sequence of str
        ``dvpmvs reconstruct`` overrides (``mesh=false``, ``quality=fast`` ...).
    sparse_path : str or Path, optional
        A COLMAP model of the photos to use instead of running structure from motion.
    progress : bool
        Progress bars on standard error.

    Returns
    -------
    dvpmvs.reconstruction.ReconstructSummary
        Per stage: reused or run, seconds, a one-line summary.
    """
    from dvpmvs.reconstruction import reconstruct as run

    cfg = config.compose("reconstruct", overrides)
    return run(
        image_path,
        workspace_path,
        sfm=config.sfm_options(cfg),
        workspace_options=config.workspace_options(cfg),
        dense_options=config.dense_options(cfg),
        meshing_options=config.meshing_options(cfg) if cfg.mesh else None,
        sparse=sparse_path,
        max_image_size=config.typed(cfg, "max_image_size", int),
        progress=progress,
        overwrite=config.typed(cfg, "overwrite", bool),
        recursive=config.typed(cfg, "recursive", bool),
    )
