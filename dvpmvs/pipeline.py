"""The dense stage: views -> estimator passes -> maps on disk -> fusion.

A photometric pass over every reference view, then (optionally) a geometric-consistency pass
that reads the neighbours' photometric maps, then fusion. Outputs go to an output folder
(``out``: the workspace itself by default, as COLMAP does; any other folder is made a COLMAP
workspace over the same images and model, :meth:`Workspace.link_output`).

Per view and pass the estimator writes, in COLMAP's format and naming:
``stereo/depth_maps/<image>.<pass>.bin``, ``stereo/normal_maps/...`` (camera-frame normals),
``stereo/cost_maps/...`` (final matching cost), ``stereo/visibility_maps/...`` (one channel per
source view, in the order of ``patch-match.cfg``: the view-selection weights), PNG previews
under ``stereo/previews/``, and its provenance record (:mod:`dvpmvs.provenance`). Every file is
written atomically. A rerun reuses a view's maps only when their record carries the fingerprint
this run would give them (the same options, inputs and code), recomputes the others and says
why in one line per pass; maps without a record (COLMAP's, an older dvpmvs's) are neither
reused nor overwritten unless ``overwrite``. The fused cloud carries a record too, so a rerun
with a new fusion option fuses again and nothing else.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
import uuid
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from dvpmvs.dense_plan import (
    _MAP_KINDS,
    _SPEED_ONLY_FUSION_OPTIONS,
    GEOMETRIC_ONLY_OPTIONS,
    DenseError,
    DenseOptions,
    DenseSummary,
    ViewReport,
    _explain,
    _plan_pass,
    _refuse_foreign,
    _sources,
    _uses_labels,
    _ViewPlan,
    map_files,
    pass_inputs,
)
from dvpmvs.dense_view import (
    _dense_tasks,
    _new_state,
    _report,
    _RunSpec,
    _serving,
    _task_key,
    write_missing_previews,
)
from dvpmvs.digests import file_digest, matches_stamp
from dvpmvs.executor import ExecutorOptions, run_tasks
from dvpmvs.fusion import (
    FusionOptions,
    empty_cloud_message,
    fuse_to_ply,
    fuse_with_colmap,
    missing_maps_hint,
    visibility_path,
)
from dvpmvs.highlight import HIGHLIGHT_DIR
from dvpmvs.maps import MAP_KINDS, map_path, remove_temporaries
from dvpmvs.mask_store import MaskStore
from dvpmvs.options.dense import FUSION_BACKENDS
from dvpmvs.passes import Pass
from dvpmvs.provenance import (
    PROVENANCE_DIR,
    CachedOutput,
    MapCache,
    code_identity,
    read_record,
    record_path,
)
from dvpmvs.validation import check_ply_output, check_writable
from dvpmvs.workspace import Workspace
from dvpmvs.writer_lock import writer_lock

__all__ = [
    "DenseOptions",
    "DenseError",
    "ViewReport",
    "DenseSummary",
    "FusionReport",
    "pass_inputs",
    "map_files",
    "run_dense",
    "fuse_workspace",
    "fuse_to_file",
    "cloud_record_path",
    "FUSION_BACKENDS",
    "GEOMETRIC_ONLY_OPTIONS",
]

log = logging.getLogger(__name__)


# -- the whole stage --------------------------------------------------------------------------------


MISSING_MAPS = "missing"  # a view with sources but no maps, in a cloud's inputs (a partial cloud)
NO_SOURCES = "no sources"  # a view the dense stage gives no maps (no source view)


def _no_sources_error(workspace: Workspace) -> DenseError:
    views = workspace.reference_views()
    return DenseError(
        f"none of the {len(views)} view(s) of {workspace.root} has a source view, so no depth can be computed: "
        f"multi-view stereo needs each view to overlap others. Check the source lists of "
        f"{workspace.stereo_dir / 'patch-match.cfg'} and the sparse model (a model with one registered image, or "
        f"views that share no sparse point, give none)"
    )


def _fused_maps(workspace: Workspace, stereo: Path, pass_: Pass) -> dict[str, object]:
    """Per reference view, what fusion reads of it, as the cloud's record must describe it: the
    fingerprint of its maps where their record is complete and the depth and normal maps are the
    files it stamped; else (maps without a record, COLMAP's; or changed since written) the
    digests of the two files; :data:`MISSING_MAPS` where a view with sources has none;
    :data:`NO_SOURCES` where a view without sources has none."""
    maps: dict[str, object] = {}
    for view in workspace.fusion_views(stereo):
        depth, normal = (map_path(stereo, view.name, kind, pass_) for kind in ("depth", "normal"))
        if not (depth.is_file() and normal.is_file()):
            maps[view.name] = MISSING_MAPS if view.sources else NO_SOURCES
            continue
        record = read_record(record_path(stereo, view.name, pass_.value))
        stamps = record.files if record is not None and record.complete else {}
        if all(
            kind in stamps
            and (stereo / stamps[kind]["path"]) == path
            and matches_stamp(path, stamps[kind])
            for kind, path in (("depth", depth), ("normal", normal))
        ):
            maps[view.name] = record.fingerprint
        else:
            maps[view.name] = {
                "depth": file_digest(depth),
                "normal": file_digest(normal),
                "image": file_digest(view.path),
            }
    return maps


def _fusion_inputs(fusion: FusionOptions, backend: str, maps: dict[str, object]) -> dict:
    """What shapes a fused cloud: the fusion options and backend, the code, and the maps fused
    (:func:`_fused_maps`)."""
    options = {k: v for k, v in asdict(fusion).items() if k not in _SPEED_ONLY_FUSION_OPTIONS}
    return {"fusion": options, "backend": backend, "code": code_identity(), "maps": maps}


def cloud_record_path(cloud: str | Path) -> Path:
    """The provenance record beside a fused cloud: ``<cloud>.provenance.json``."""
    cloud = Path(cloud)
    return cloud.with_name(cloud.name + ".provenance.json")


@dataclass
class FusionReport:
    output: Path
    points: int
    seconds: float
    reused: bool
    fingerprint: str
    views_without_maps: list[str] = field(
        default_factory=list
    )  # fused without them (allow_missing)


def fuse_workspace(
    workspace: Workspace,
    fusion: FusionOptions,
    backend: str,
    output: str | Path,
    stereo_dir: str | Path | None = None,
    colmap_root: str | Path | None = None,
    reuse: bool = True,
    progress: bool = True,
    overwrite: bool = False,
) -> FusionReport:
    """Fuse the maps in ``stereo_dir`` (default the workspace's) into ``output`` and record what
    made the cloud beside it (``<cloud>.provenance.json``). With ``reuse``, a cloud whose record
    carries the same fingerprint (the same maps, fusion options and code) is kept as it is. A
    file at ``output`` that dvpmvs did not write (no record: COLMAP's ``fused.ply``) is replaced
    only with ``overwrite`` (else :class:`dvpmvs.provenance.ForeignOutputError`)."""
    output = Path(output).expanduser()
    stereo = workspace.stereo_dir if stereo_dir is None else Path(stereo_dir)
    check_cloud_path(output)
    # The maps' folder is locked: a dense run writing maps there would change them under fusion
    # (a folder this process cannot write, nobody's dense run here can write either).
    maps_folder = stereo.parent
    with writer_lock(maps_folder) if os.access(maps_folder, os.W_OK) else nullcontext():
        if output.parent.resolve() == stereo.parent.resolve():
            remove_temporaries(output.parent, recursive=False)
        return _fuse_workspace_locked(
            workspace, fusion, backend, output, stereo, colmap_root, reuse, progress, overwrite
        )


def _fuse_workspace_locked(
    workspace: Workspace,
    fusion: FusionOptions,
    backend: str,
    output: Path,
    stereo: Path,
    colmap_root,
    reuse: bool,
    progress: bool,
    overwrite: bool,
) -> FusionReport:
    maps = _fused_maps(workspace, stereo, Pass(fusion.input_type))
    if all(value == NO_SOURCES for value in maps.values()):
        raise _no_sources_error(workspace)
    missing = [name for name, value in maps.items() if value == MISSING_MAPS]
    if missing and all(value in (MISSING_MAPS, NO_SOURCES) for value in maps.values()):
        raise DenseError(
            f"no {fusion.input_type} maps in {stereo}: "
            f"{missing_maps_hint(workspace, stereo, Pass(fusion.input_type), missing)}"
        )
    if missing and not fusion.allow_missing:
        raise DenseError(
            f"{len(missing)} of {len(maps)} views have no {fusion.input_type} maps in {stereo} (e.g. "
            f"{map_path(stereo, missing[0], 'depth', Pass(fusion.input_type))}): a cloud without them would lack "
            f"their part of the scene. Compute them (`dvpmvs dense`, which recomputes only what is missing), or "
            f"give fusion_options.allow_missing=true for a partial cloud"
        )
    if missing and backend == "colmap":
        raise DenseError(
            f"fusion_options.allow_missing=true is for fusion=dvpmvs: COLMAP's fusion needs the maps "
            f"of every view of stereo/fusion.cfg ({len(missing)} missing, e.g. {missing[0]})"
        )
    if missing:
        log.warning(
            "fusion: %d view(s) have no %s maps and add no points: %s (allow_missing=true: a partial "
            "cloud)",
            len(missing),
            fusion.input_type,
            ", ".join(missing),
        )
    inputs = _fusion_inputs(fusion, backend, maps)
    if fusion.mask is not None:
        # The masks' files: a changed mask changes the cloud even where the maps are not ours.
        masks = MaskStore.from_config(fusion.mask, stereo, workspace.root).masks
        inputs["masks"] = {name: masks.provenance(name, workspace.root) for name in maps}
    cached = CachedOutput.check(cloud_record_path(output), inputs, output.parent, [output])
    if reuse and cached.current is not None:
        log.info("fusion: the cloud %s is current (same maps and fusion options): reused", output)
        stats = cached.current.stats
        return FusionReport(
            output,
            int(stats.get("points", 0)),
            float(stats.get("seconds", 0.0)),
            True,
            cached.fingerprint,
            missing,
        )
    _check_space(
        output.parent,
        _cloud_bytes(workspace),
        f"the fused cloud, at most about {_cloud_bytes(workspace) / 2**20:,.1f} MB",
        "give output=PATH on another disk",
    )
    start = time.perf_counter()
    with cached.making(overwrite):
        points = fuse_to_file(
            workspace, fusion, backend, output, progress, stereo_dir=stereo, colmap_root=colmap_root
        )
    seconds = time.perf_counter() - start
    # The visibility file is part of the cloud (COLMAP's meshers read both): without it the cloud
    # is not current.
    files = {"cloud": output}
    if visibility_path(output).is_file():
        files["visibility"] = visibility_path(output)
    cached.complete(files, {"points": points, "seconds": seconds, "views_without_maps": missing})
    return FusionReport(output, points, seconds, False, cached.fingerprint, missing)


def run_dense(
    workspace: Workspace,
    options: DenseOptions | None = None,
    output: str | Path | None = None,
    progress: bool = True,
    out: str | Path | None = None,
    cache: MapCache | None = None,
    on_start=None,
    executor: ExecutorOptions | None = None,
) -> DenseSummary:
    """Every pass, then fusion into ``output`` (default ``OUT/fused.ply``).

    ``out``: the output folder (default the workspace): maps in ``OUT/stereo``; any other
    folder is made a COLMAP workspace over the workspace's images and model. ``cache``: a
    :class:`MapCache` shared with other runs (the jobs of a sweep). ``on_start``: called once
    every check has passed, before the first map is computed. ``executor``: where the views' tasks
    run (:mod:`dvpmvs.executor`; default this process, one after another); the maps are the same
    bytes whatever it is.

    Before anything is computed: the output folders must be writable, and the run takes the
    output folder's writer lock (:mod:`dvpmvs.writer_lock`; another run writing there stops this
    one with its holder named) and removes the temporaries an interrupted run left there."""
    options = options or DenseOptions()
    if executor is not None and executor.name != "local" and not workspace.root.is_absolute():
        # Workers elsewhere have other working folders: every path a task gets is absolute.
        workspace = Workspace.open(workspace.root.resolve(), workspace.options)
    out = Path(out).expanduser() if out is not None else workspace.root
    if executor is not None and executor.name != "local":
        out = out.resolve()
    output = Path(output).expanduser() if output is not None else out / "fused.ply"
    # Where this run writes, checked before anything is computed; then one writer at a time.
    check_writable(
        out, "the output folder", "give out=DIR (a folder you can write) for the maps and the cloud"
    )
    if options.fuse:
        check_cloud_path(output)
    with writer_lock(out):
        return _run_dense_locked(
            workspace, options, output, progress, out, cache, on_start, executor
        )


def check_cloud_path(output: Path) -> None:
    """The fused cloud's path must name a PLY file in a folder this process can write."""
    check_ply_output(output, "fused clouds", "fused.ply")


def _run_dense_locked(
    workspace: Workspace,
    options: DenseOptions,
    output: Path,
    progress: bool,
    out: Path,
    cache: MapCache | None,
    on_start,
    executor: ExecutorOptions | None,
) -> DenseSummary:
    stereo = out / "stereo"
    leftovers = remove_temporaries(out, recursive=False) + remove_temporaries(stereo)
    if leftovers:
        log.info(
            "removed %d temporary file(s) of an interrupted run (e.g. %s)",
            len(leftovers),
            leftovers[0],
        )
    if out.resolve() != workspace.root.resolve():
        workspace.link_output(out)
    check_writable(
        stereo,
        "the maps' folder",
        "give out=DIR (a folder you can write) for the maps and the cloud",
    )
    if options.fuse:
        workspace.fusion_views(stereo)  # a wrong fusion.cfg is named before any view is computed
    # Every pass is planned before any is run: maps without a record stop the run before it
    # has written anything.
    spec = _RunSpec(
        uuid.uuid4().hex,
        workspace.root,
        workspace.options,
        stereo,
        options,
        cache.root if cache is not None else None,
    )
    state = _new_state(spec, workspace, cache)
    plans: dict[Pass, list[_ViewPlan]] = {}
    upstream: dict[str, str | None] = {}
    for pass_ in options.passes:
        plans[pass_] = _plan_pass(
            workspace,
            stereo,
            pass_,
            options,
            state.providers,
            upstream,
            state.highlights,
            state.masks.masks,
        )
        upstream = {p.view.name: p.fingerprint for p in plans[pass_]}
    if not plans[Pass.PHOTOMETRIC]:
        raise _no_sources_error(workspace)
    if not options.overwrite:
        _refuse_foreign(((pass_, p) for pass_ in options.passes for p in plans[pass_]), stereo)
        if options.fuse and output.exists() and not cloud_record_path(output).is_file():
            raise DenseError(
                f"{output} exists and carries no dvpmvs provenance record (written by COLMAP or an "
                f"older dvpmvs); dvpmvs does not overwrite it unasked: rerun with overwrite=true, or "
                f"give another output=PATH or out=DIR"
            )
    todo = {
        pass_: [p for p in plans[pass_] if options.overwrite or not p.status.reusable]
        for pass_ in plans
    }
    _check_outputs(stereo, todo, options, output, workspace, state.highlights is not None)
    # The masks made and stored (checked: missing, unreadable, another aspect ratio) before any
    # view is computed; a network's only for the first view (MaskStore.prepare).
    state.masks.prepare(workspace.reference_views())
    if on_start is not None:
        on_start()
    for pass_ in options.passes:
        log.info(_explain(plans[pass_], pass_, options.overwrite))
    multiview = (
        state.highlights is not None
        and options.geometric
        and options.patch_match.highlight_multiview
    )
    executor = executor or ExecutorOptions()
    if executor.name != "local":
        # Workers build the run's state from the spec; their kernels use the executor's threads.
        spec = replace(
            spec,
            options=replace(
                options,
                patch_match=replace(options.patch_match, num_threads=executor.kernel_threads()),
            ),
        )
    tasks = _dense_tasks(
        spec,
        workspace,
        plans,
        multiview,
        state.highlights is not None,
        progress and executor.name == "local",
    )
    start = time.perf_counter()
    with _serving(spec, state):
        results = run_tasks(tasks, executor, progress)
    wall = time.perf_counter() - start
    if executor.name != "local":  # what a worker killed mid-write left
        remove_temporaries(stereo)
    if options.previews:
        # Reused maps from a run without previews get theirs, drawn from the maps.
        for pass_ in options.passes:
            reused = [
                plan
                for plan in plans[pass_]
                if results.get(_task_key(pass_.value, plan.view.name)) is None
            ]
            written = write_missing_previews(stereo, reused, pass_)
            if written:
                log.info("%s pass: %d preview(s) of reused maps written", pass_.value, written)
    reports, pass_seconds = [], {}
    for pass_ in options.passes:
        pass_seconds[pass_.value] = 0.0
        for plan in plans[pass_]:
            done = results.get(_task_key(pass_.value, plan.view.name))
            if done is None:
                reports.append(_report(plan, pass_, plan.record, "reused"))
            else:
                reports.append(done[0])
                pass_seconds[pass_.value] += done[1]
    highlight_seconds: dict[str, float] = {}
    for task in tasks:
        if task.stage.startswith("highlights") and results[task.key][0] is not None:
            name = task.key.rpartition(":")[2]
            highlight_seconds[name] = highlight_seconds.get(name, 0.0) + results[task.key][1]
    for stage in ("highlights", "highlights (multi-view)"):
        made = [
            results[t.key][1] for t in tasks if t.stage == stage and results[t.key][0] is not None
        ]
        if made:
            log.info(
                "%s: %d view(s) computed, %.2f s per view", stage, len(made), sum(made) / len(made)
            )
    summary = DenseSummary(
        reports,
        pass_seconds,
        stereo_dir=stereo,
        highlight_seconds=highlight_seconds,
        wall_seconds=wall,
    )
    if not options.fuse:
        return summary
    fusion = replace(options.fusion, input_type=options.final_pass.value)
    report = fuse_workspace(
        workspace,
        fusion,
        options.fusion_backend,
        output,
        stereo,
        out,
        reuse=not options.overwrite,
        progress=progress,
        overwrite=options.overwrite,
    )
    summary.output, summary.num_points, summary.fusion_seconds = (
        report.output,
        report.points,
        report.seconds,
    )
    summary.fusion_reused, summary.fusion_fingerprint = report.reused, report.fingerprint
    summary.fusion_views_without_maps = report.views_without_maps
    return summary


# Bytes per pixel of a fused cloud, at most: a point is 27 bytes and its visibility record about
# 16; a fused cloud has 0.1-0.4 points per pixel of its views (the suite's scenes), so 0.5 is an
# upper bound.
_CLOUD_BYTES_PER_PIXEL = 0.5 * (27 + 16)
_RECORD_BYTES = 64 << 10  # a view pass's provenance record (its inputs are a few kilobytes)


def _check_outputs(
    stereo: Path,
    todo: dict[Pass, list[_ViewPlan]],
    options: DenseOptions,
    output: Path,
    workspace: Workspace,
    highlights: bool,
) -> None:
    """Before any view is computed: every folder the run writes can be written (a read-only
    ``depth_maps/`` would otherwise be found after the first view), and the disks holding the
    maps and the cloud have room for them (the cloud estimated from above; a disk that fills
    anyway stops the run with the folder named, nothing half-written)."""
    if any(todo.values()):
        hint = "give out=DIR (a folder you can write) for the maps and the cloud"
        kinds = set(_MAP_KINDS) | ({"labels"} if _uses_labels(options) else set())
        folders = [stereo / MAP_KINDS[kind] for kind in sorted(kinds)] + [stereo / PROVENANCE_DIR]
        folders += [stereo / "previews"] if options.previews else []
        folders += [stereo / HIGHLIGHT_DIR] if highlights else []
        for folder in folders:
            check_writable(folder, "the maps' folder", hint)
    maps = 0
    for plans in todo.values():
        for plan in plans:
            pixels = plan.view.width * plan.view.height
            channels = (
                1 + 3 + 1 + len(_sources(plan.view, options))
            )  # depth, normal, cost, visibility
            channels += 1 if "labels" in plan.files else 0
            maps += 4 * channels * pixels + _RECORD_BYTES + (4 * pixels if options.previews else 0)
    cloud = _cloud_bytes(workspace) if options.fuse else 0
    views = sum(map(len, todo.values()))
    what = f"the maps of {views} view pass(es), about {maps / 2**20:,.1f} MB"
    if cloud and os.stat(stereo).st_dev == os.stat(output.parent).st_dev:
        _check_space(
            stereo,
            maps + cloud,
            f"{what}, and the fused cloud, at most about {cloud / 2**20:,.1f} MB",
            "give out=DIR on another disk (or output=PATH for the cloud)",
        )
    else:
        _check_space(stereo, maps, what, "give out=DIR on another disk")
        if cloud:
            _check_space(
                output.parent,
                cloud,
                f"the fused cloud, at most about {cloud / 2**20:,.1f} MB",
                "give output=PATH on another disk",
            )


def _cloud_bytes(workspace: Workspace) -> int:
    """An upper bound of the fused cloud's size on disk (with its ``.vis``)."""
    return int(
        _CLOUD_BYTES_PER_PIXEL * sum(v.width * v.height for v in workspace.reference_views())
    )


def _check_space(folder: Path, needed: int, what: str, hint: str) -> None:
    free = shutil.disk_usage(folder).free
    if needed > free:
        raise DenseError(
            f"{folder} is on a disk with {free / 2**20:,.1f} MB free; this run writes {what}: free some "
            f"space there, or {hint}"
        )


def fuse_to_file(
    workspace: Workspace,
    fusion: FusionOptions,
    backend: str,
    output: str | Path,
    progress: bool = True,
    stereo_dir: str | Path | None = None,
    colmap_root: str | Path | None = None,
) -> int:
    """Fuse the maps in ``stereo_dir`` (default the workspace's) with ``backend`` (``dvpmvs`` or
    ``colmap``; COLMAP reads the workspace ``colmap_root``, default the workspace itself) into
    the PLY ``output``; returns the number of points."""
    from tqdm import tqdm

    if backend not in FUSION_BACKENDS:
        raise ValueError(
            f"unknown fusion backend {backend!r}; choose {' or '.join(FUSION_BACKENDS)}"
        )
    if backend == "colmap":
        return fuse_with_colmap(workspace, output, fusion, root=colmap_root)
    views = workspace.fusion_views(stereo_dir)
    with tqdm(
        total=len(views), desc="fusion", unit="view", disable=not progress, dynamic_ncols=True
    ) as bar:
        per_view = fuse_to_ply(
            workspace,
            output,
            fusion,
            stereo_dir=stereo_dir,
            progress=lambda name: (bar.set_postfix_str(name), bar.update()),
        )
    points = sum(per_view.values())
    if not points:
        log.warning(empty_cloud_message(fusion))
    return points
