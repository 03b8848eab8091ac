"""A dense run: its output folder checked and locked, its plan (:mod:`dvpmvs.dense.plan`) made
and checked before anything is computed, the tasks run by the executor, the reports, and the
fused cloud (:mod:`dvpmvs.dense.cloud`)."""

from __future__ import annotations

import logging
import os
import time
import uuid
from dataclasses import replace
from pathlib import Path

from dvpmvs.dense.cloud import (
    check_cloud_path,
    check_space,
    cloud_bytes,
    make_cloud,
    no_sources_error,
)
from dvpmvs.dense.inputs import PASS_MAPS, view_sources
from dvpmvs.dense.plan import DensePlan, plan_dense
from dvpmvs.dense.previews import write_missing_previews
from dvpmvs.dense.products import REGIONS
from dvpmvs.dense.report import DenseSummary, view_report
from dvpmvs.dense.state import RunSpec, new_state, serving
from dvpmvs.executor import ExecutorOptions, run_tasks
from dvpmvs.highlight import HIGHLIGHT_DIR
from dvpmvs.maps import MAP_KINDS, remove_temporaries
from dvpmvs.options.dense import DenseOptions
from dvpmvs.passes import Pass
from dvpmvs.provenance import PROVENANCE_DIR, MapCache
from dvpmvs.validation import check_writable
from dvpmvs.workspace import Workspace
from dvpmvs.writer_lock import writer_lock

__all__ = ["run_dense"]

log = logging.getLogger(__name__)


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
    spec = RunSpec(
        uuid.uuid4().hex,
        workspace.root,
        workspace.options,
        stereo,
        options,
        cache.root if cache is not None else None,
    )
    state = new_state(spec, workspace, cache)
    # Every product is planned before any is made: maps without a record stop the run before it
    # has written anything.
    plan = plan_dense(workspace, stereo, options, state, output)
    if not plan.passes[Pass.PHOTOMETRIC]:
        raise no_sources_error(workspace)
    if not options.overwrite:
        plan.refuse_foreign(stereo)
    _check_outputs(stereo, plan, options, output, workspace, state.highlights is not None)
    # The masks made and stored (checked: missing, unreadable, another aspect ratio) before any
    # view is computed; a network's only for the first view (MaskStore.prepare).
    state.masks.prepare(workspace.reference_views())
    if on_start is not None:
        on_start()
    for line in plan.explain():
        log.info(line)
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
    tasks = plan.tasks(spec, progress and executor.name == "local")
    start = time.perf_counter()
    with serving(spec, state):
        results = run_tasks(tasks, executor, progress)
    wall = time.perf_counter() - start
    if executor.name != "local":  # what a worker killed mid-write left
        remove_temporaries(stereo)
    summary = _summary(plan, options, stereo, tasks, results, wall)
    if plan.cloud is None:
        return summary
    # The cloud is made here, after the maps it fuses: in the process that holds the run's
    # writer lock, which a worker elsewhere cannot take.
    report = make_cloud(
        workspace,
        plan.cloud,
        stereo,
        out,
        progress,
        reuse=not options.overwrite,
        overwrite=options.overwrite,
        masks=state.masks,
    )
    summary.output, summary.num_points, summary.fusion_seconds = (
        report.output,
        report.points,
        report.seconds,
    )
    summary.fusion_reused, summary.fusion_fingerprint = report.reused, report.fingerprint
    summary.fusion_views_without_maps = report.views_without_maps
    return summary


def _summary(
    plan: DensePlan,
    options: DenseOptions,
    stereo: Path,
    tasks: list,
    results: dict,
    wall: float,
) -> DenseSummary:
    """The run's reports: per view and pass, its maps computed here (the task's report) or
    reused (from their record), the photometric pass's with the seconds of the view's region
    labels (from their record); the highlight stage's seconds per view it computed."""
    if options.previews:
        # Reused products from a run without previews get theirs, drawn from their files.
        for what, products in [("region labels", plan.regions.values())] + [
            (f"{pass_.value} pass", plan.passes[pass_]) for pass_ in options.passes
        ]:
            written = write_missing_previews(
                stereo, [p for p in products if results.get(p.key) is None]
            )
            if written:
                log.info("%s: %d preview(s) of reused outputs written", what, written)
    reports, pass_seconds = [], {}
    for pass_ in options.passes:
        pass_seconds[pass_.value] = 0.0
        for product in plan.passes[pass_]:
            done = results.get(product.key)
            if done is None:
                report = view_report(product, product.record, "reused")
            else:
                report = done[0]
                pass_seconds[pass_.value] += done[1]
            regions = plan.regions.get(product.view.name)
            if pass_ is Pass.PHOTOMETRIC and regions is not None:
                made = results.get(regions.key)
                record = made[0] if made is not None else regions.record
                report.prior_seconds = float(record.stats.get("seconds", 0.0)) if record else 0.0
                report.seconds += report.prior_seconds
                pass_seconds[pass_.value] += made[1] if made is not None else 0.0
            reports.append(report)
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
    return DenseSummary(
        reports,
        pass_seconds,
        stereo_dir=stereo,
        highlight_seconds=highlight_seconds,
        wall_seconds=wall,
    )


_RECORD_BYTES = 64 << 10  # a view pass's provenance record (its inputs are a few kilobytes)


def _check_outputs(
    stereo: Path,
    plan: DensePlan,
    options: DenseOptions,
    output: Path,
    workspace: Workspace,
    highlights: bool,
) -> None:
    """Before any view is computed: every folder the run writes can be written (a read-only
    ``depth_maps/`` would otherwise be found after the first view), and the disks holding the
    maps and the cloud have room for them (the cloud estimated from above; a disk that fills
    anyway stops the run with the folder named, nothing half-written)."""
    todo = [p for pass_ in options.passes for p in plan.wanted(pass_)] + plan.wanted_regions()
    if todo:
        hint = "give out=DIR (a folder you can write) for the maps and the cloud"
        kinds = set(PASS_MAPS) | ({"labels"} if plan.regions else set())
        folders = [stereo / MAP_KINDS[kind] for kind in sorted(kinds)] + [stereo / PROVENANCE_DIR]
        folders += [stereo / "previews"] if options.previews else []
        folders += [stereo / HIGHLIGHT_DIR] if highlights else []
        for folder in folders:
            check_writable(folder, "the maps' folder", hint)
    maps = 0
    for product in todo:
        pixels = product.view.width * product.view.height
        # depth, normal, cost, visibility (one channel per source); or the labels
        channels = (
            1 + 3 + 1 + len(view_sources(product.view, options))
            if product.kind
            in (
                Pass.PHOTOMETRIC.value,
                Pass.GEOMETRIC.value,
            )
            else 1
        )
        maps += 4 * channels * pixels + _RECORD_BYTES + (4 * pixels if options.previews else 0)
    cloud = cloud_bytes(workspace) if options.fuse else 0
    views = sum(p.kind != REGIONS for p in todo)
    what = f"the maps of {views} view pass(es), about {maps / 2**20:,.1f} MB"
    if cloud and os.stat(stereo).st_dev == os.stat(output.parent).st_dev:
        check_space(
            stereo,
            maps + cloud,
            f"{what}, and the fused cloud, at most about {cloud / 2**20:,.1f} MB",
            "give out=DIR on another disk (or output=PATH for the cloud)",
        )
    else:
        check_space(stereo, maps, what, "give out=DIR on another disk")
        if cloud:
            check_space(
                output.parent,
                cloud,
                f"the fused cloud, at most about {cloud / 2**20:,.1f} MB",
                "give output=PATH on another disk",
            )
