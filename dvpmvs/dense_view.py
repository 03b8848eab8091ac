"""One view's maps of one pass, the dense stage's task: its problem (images, the neighbours'
maps in the geometric pass, priors and segmentation labels), the estimator, the maps written
with their record; and the task graph of a run (:mod:`dvpmvs.executor` runs it, locally or on a
Dask cluster), with the per-process state its tasks share (:class:`_RunState`)."""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, replace
from functools import partial
from pathlib import Path

import numpy as np

from dvpmvs.dense_plan import (
    DenseOptions,
    ViewReport,
    _preview_files,
    _sources,
    _uses_labels,
    _ViewPlan,
)
from dvpmvs.executor import Task
from dvpmvs.highlight import HighlightStage, highlight_config
from dvpmvs.maps import (
    MapFormatError,
    map_path,
    read_depth_map,
    read_extra_map,
    read_normal_map,
    write_depth_map,
    write_extra_map,
    write_normal_map,
)
from dvpmvs.mask_store import MaskStore
from dvpmvs.passes import Pass
from dvpmvs.patchmatch import PatchMatchOptions, Problem, ViewData, estimate
from dvpmvs.patchmatch.low_resolution import low_resolution_depth
from dvpmvs.preview import colorize_cost, colorize_depth, colorize_normals, write_png
from dvpmvs.priors import PriorContext, PriorProviders, compute_priors
from dvpmvs.provenance import MapCache, Record, record_path, stamp_files, write_record
from dvpmvs.segmentation import colorize_labels, segment
from dvpmvs.view import View
from dvpmvs.workspace import Workspace, WorkspaceOptions

log = logging.getLogger(__name__)


# -- one view ---------------------------------------------------------------------------------------


def _view_data(
    view: View,
    depth: np.ndarray | None = None,
    cost: np.ndarray | None = None,
    highlights: HighlightStage | None = None,
    refined: bool = False,
) -> ViewData:
    maps = None
    if highlights is not None:
        maps = highlights.load_refined(view.name) if refined else highlights.load(view.name)
    return ViewData(
        view.name,
        view.load_grey(),
        view.K,
        view.R,
        view.t,
        depth,
        cost,
        None if maps is None else maps.corrected,
        None if maps is None else maps.mask,
    )


def _read_map_or(
    stereo: Path, view: View, kind: str, pass_: Pass, missing: float, consequence: str
) -> np.ndarray:
    """The view's one-channel ``kind`` map of ``pass_`` (H, W); where the view has none, ``missing``
    everywhere, with a warning that says the ``consequence``."""
    path = map_path(stereo, view.name, kind, pass_)
    if not path.is_file():
        log.warning("source %s has no %s %s map; %s", view.name, pass_.value, kind, consequence)
        return np.full((view.height, view.width), missing, np.float32)
    data = read_depth_map(path) if kind == "depth" else read_extra_map(path)
    if data.shape[:2] != (view.height, view.width) or data.size != view.height * view.width:
        raise MapFormatError(
            f"{path} holds a {data.shape} map; the view needs ({view.height}, {view.width})"
        )
    return data.reshape(view.height, view.width)


def _read_depth_or_empty(stereo: Path, view: View, pass_: Pass) -> np.ndarray:
    return _read_map_or(stereo, view, "depth", pass_, 0.0, "it gives no geometric constraint")


def _read_cost_or_unknown(stereo: Path, view: View, pass_: Pass) -> np.ndarray:
    """Infinite (unknown: never the lowest) where the view has no cost map."""
    return _read_map_or(
        stereo, view, "cost", pass_, np.inf, "its visibility is restored through its own depths"
    )


def _problem(
    workspace: Workspace,
    view: View,
    pass_: Pass,
    options: PatchMatchOptions,
    stereo: Path | None = None,
    highlights: HighlightStage | None = None,
) -> Problem:
    """The estimator's problem for ``view``; the geometric pass reads the photometric maps
    from ``stereo`` (default: the workspace's); ``highlights``: the views' highlight outputs."""
    stereo = workspace.stereo_dir if stereo is None else stereo
    names = view.sources[: options.max_sources]
    if pass_ is Pass.PHOTOMETRIC:
        return Problem(
            _view_data(view, highlights=highlights),
            [_view_data(workspace[n], highlights=highlights) for n in names],
            view.depth_range,
            sparse_points=workspace.observed_points(view.name) if options.sparse_seed else None,
        )
    previous = Pass.PHOTOMETRIC
    initial = (
        _read_depth_or_empty(stereo, view, previous),
        read_normal_map(map_path(stereo, view.name, "normal", previous)),
    )
    # The sources' costs are read only where the geometric pass deforms with restored visibility.
    restore = (
        options.deformable
        and options.geom_deformable
        and options.anchor_visibility
        and options.visibility_restoration
    )
    refined = options.highlight_multiview
    sources = [
        _view_data(
            workspace[n],
            _read_depth_or_empty(stereo, workspace[n], previous),
            _read_cost_or_unknown(stereo, workspace[n], previous) if restore else None,
            highlights,
            refined,
        )
        for n in names
    ]
    return Problem(
        _view_data(view, highlights=highlights, refined=refined),
        sources,
        view.depth_range,
        initial=initial,
    )


def _labels(
    workspace: Workspace,
    stereo: Path,
    view: View,
    problem: Problem,
    pass_: Pass,
    options: DenseOptions,
    providers: PriorProviders | None,
) -> tuple[np.ndarray, float]:
    """The view's region labels and the seconds spent: in the photometric pass priors ->
    segmentation, saved as an extra map with previews; the geometric pass reads them back (they
    belong to the photometric maps it starts from)."""
    path = map_path(stereo, view.name, "labels", Pass.PHOTOMETRIC)
    if pass_ is Pass.GEOMETRIC:
        try:
            labels = read_extra_map(path)
            if labels.shape == (view.height, view.width):
                return labels.astype(np.int32), 0.0
        except MapFormatError:
            pass
        log.warning(
            "view %s has no region labels beside its photometric maps; segmenting again", view.name
        )
    start = time.perf_counter()
    ctx = PriorContext(
        view.name,
        problem.reference.image,
        view.K,
        view.depth_range,
        workspace.sparse_points(view.name),
        rgb_loader=view.load_rgb,
        root=workspace.root,
        low_resolution_depth=partial(
            low_resolution_depth,
            problem,
            options.patch_match,
            size_scale=workspace.resolution_scale(view),
        ),
    )
    priors = compute_priors(ctx, providers)
    if priors.edges is None or priors.depth is None:
        raise ValueError(
            "the aligned prior needs an edge detector and a depth prior; set edge= and depth_prior=, "
            "or segmentation=null (method=w_o_agn) to deform without regions"
        )
    result = segment(
        priors.edges,
        priors.depth,
        priors.normal,
        view.K,
        view.depth_range,
        options.segmentation,
        priors.depth_valid,
        priors.normal_from_depth,
    )
    if pass_ is Pass.PHOTOMETRIC:
        write_extra_map(path, result.labels)
        if options.previews:
            previews = _preview_files(stereo, view.name, pass_, True)
            write_png(previews[f"{view.name}.labels.png"], colorize_labels(result.labels))
            write_png(previews[f"{view.name}.edges.png"], (priors.edges * 255).astype(np.uint8))
            lo, hi = view.depth_range
            write_png(
                previews[f"{view.name}.depth_prior.png"], colorize_depth(priors.depth, lo, hi)
            )
            if priors.normal is not None:
                write_png(
                    previews[f"{view.name}.normal_prior.png"], colorize_normals(priors.normal)
                )
    log.debug(
        "view %s: %d regions, %d splits, %d merges, %d pixels filtered",
        view.name,
        int(result.labels.max()),
        result.splits,
        result.merges,
        result.filtered,
    )
    return result.labels, time.perf_counter() - start


def _write_maps(stereo: Path, view: View, pass_: Pass, result, previews: bool) -> None:
    write_extra_map(map_path(stereo, view.name, "visibility", pass_), result.visibility)
    write_extra_map(map_path(stereo, view.name, "cost", pass_), result.cost)
    write_normal_map(map_path(stereo, view.name, "normal", pass_), result.normal)
    valid = result.depth[result.depth > 0]
    depth_range = (float(valid.min()), float(valid.max())) if valid.size else None
    write_depth_map(map_path(stereo, view.name, "depth", pass_), result.depth, depth_range)
    if previews:
        files = _preview_files(stereo, view.name, pass_, False)
        lo, hi = view.depth_range
        prefix = f"{view.name}.{pass_.value}"
        write_png(files[f"{prefix}.depth.png"], colorize_depth(result.depth, lo, hi))
        write_png(files[f"{prefix}.normal.png"], colorize_normals(result.normal))
        write_png(files[f"{prefix}.cost.png"], colorize_cost(result.cost))


def write_missing_previews(stereo: Path, plans: list[_ViewPlan], pass_: Pass) -> int:
    """The depth, normal and cost previews (and the labels' where their map is kept) of views
    whose maps were reused, where a file is missing (the maps came from a run with
    ``previews=false``), drawn from the maps on disk. Returns how many were written."""
    written = 0
    for plan in plans:
        view = plan.view
        prefix = f"{view.name}.{pass_.value}"
        files = _preview_files(stereo, view.name, pass_, True)
        makers = {
            f"{prefix}.depth.png": lambda: colorize_depth(
                read_depth_map(map_path(stereo, view.name, "depth", pass_)), *view.depth_range
            ),
            f"{prefix}.normal.png": lambda: colorize_normals(
                read_normal_map(map_path(stereo, view.name, "normal", pass_))
            ),
            f"{prefix}.cost.png": lambda: colorize_cost(
                read_extra_map(map_path(stereo, view.name, "cost", pass_))
            ),
        }
        if "labels" in plan.files:
            makers[f"{view.name}.labels.png"] = lambda: colorize_labels(
                read_extra_map(plan.files["labels"]).astype(np.int32)
            )
        for name, make in makers.items():
            if not files[name].is_file():
                try:
                    image = make()
                except (OSError, MapFormatError) as exc:
                    log.warning("no preview %s: %s", files[name], exc)
                    continue
                write_png(files[name], image)
                written += 1
    return written


def _compute_view(
    workspace: Workspace,
    stereo: Path,
    plan: _ViewPlan,
    pass_: Pass,
    options: DenseOptions,
    providers: PriorProviders | None,
    progress: bool,
    highlights: HighlightStage | None,
    masks: MaskStore,
) -> Record:
    from tqdm import tqdm

    view = plan.view
    path = record_path(stereo, view.name, pass_.value)
    # Pending first: a run cut off while writing leaves maps that read as interrupted, not finished.
    write_record(path, Record(plan.fingerprint, plan.inputs))
    # A per-view seed keeps views independent of the order they are computed in.
    pm = replace(options.patch_match, seed=options.patch_match.seed * 1_000_003 + view.image_id)
    problem = _problem(workspace, view, pass_, pm, stereo, highlights)
    problem.mask = masks.load(view)
    prior_seconds = 0.0
    if _uses_labels(options):
        problem.labels, prior_seconds = _labels(
            workspace, stereo, view, problem, pass_, options, providers
        )
    with tqdm(
        total=1,
        desc=f"  {view.name}",
        unit="sweep",
        leave=False,
        disable=not progress,
        dynamic_ncols=True,
    ) as inner:

        def on_sweep(done: int, total: int) -> None:
            inner.total = total
            inner.n = done
            inner.refresh()

        result = estimate(problem, pm, pass_, on_sweep=on_sweep)
    del problem  # release the images before writing
    _write_maps(stereo, view, pass_, result, options.previews)
    previews = _preview_files(stereo, view.name, pass_, _uses_labels(options))
    record = Record(
        plan.fingerprint,
        plan.inputs,
        complete=True,
        files=stamp_files(stereo, plan.files),
        extras=[p.relative_to(stereo).as_posix() for p in previews.values() if p.is_file()],
        stats={
            "seconds": result.seconds + prior_seconds,
            "prior_seconds": prior_seconds,
            "evaluations": result.hypothesis_evaluations,
            "work": [asdict(level) for level in result.work],
            "valid_fraction": float((result.depth > 0).mean()),
        },
    )
    write_record(path, record)
    return record


def _report(plan: _ViewPlan, pass_: Pass, record: Record, action: str) -> ViewReport:
    stats = record.stats
    return ViewReport(
        plan.view.name,
        pass_,
        plan.status,
        action,
        seconds=float(stats.get("seconds", 0.0)),
        evaluations=int(stats.get("evaluations", 0)),
        prior_seconds=float(stats.get("prior_seconds", 0.0)),
        valid_fraction=float(stats.get("valid_fraction", 0.0)),
        width=plan.view.width,
        height=plan.view.height,
        fingerprint=plan.fingerprint,
        work=list(stats.get("work", [])),
    )


def _make_view_pass(spec: _RunSpec, pass_: Pass, plan: _ViewPlan, progress: bool) -> ViewReport:
    """One view's maps of one pass: linked from the map cache where it holds them, else computed
    (priors and segmentation included); the task of a view and pass, in any process."""
    state = _run_state(spec)
    options, stereo, cache = spec.options, spec.stereo, state.cache
    previews = (
        _preview_files(stereo, plan.view.name, pass_, _uses_labels(options))
        if options.previews
        else {}
    )
    if cache is not None and not options.overwrite:
        record = cache.fetch(pass_.value, plan.fingerprint, stereo, plan.files, previews)
        if record is not None:
            write_record(record_path(stereo, plan.view.name, pass_.value), record)
            return _report(plan, pass_, record, "cached")
    record = _compute_view(
        state.workspace,
        stereo,
        plan,
        pass_,
        options,
        state.providers,
        progress,
        state.highlights,
        state.masks,
    )
    if cache is not None:
        cache.store(pass_.value, record, stereo, previews)
    return _report(plan, pass_, record, "computed")


def _prepare_highlight(spec: _RunSpec, name: str) -> float | None:
    """The highlight provider's outputs of one view, unless current (the task)."""
    return _run_state(spec).highlights.prepare_view(
        name, spec.options.overwrite, spec.options.previews
    )


def _refine_highlight(
    spec: _RunSpec, name: str, sources: tuple[str, ...], photometric: dict[str, str | None]
) -> float | None:
    """The multi-view refinement of one view's highlight outputs from the photometric maps of the
    view and its sources, unless current (the task)."""
    state = _run_state(spec)
    return state.highlights.refine_view(
        name,
        sources,
        photometric,
        lambda n: _read_depth_or_empty(spec.stereo, state.workspace[n], Pass.PHOTOMETRIC),
        spec.options.overwrite,
        spec.options.previews,
    )


# -- the run's tasks --------------------------------------------------------------------------------


@dataclass(frozen=True)
class _RunSpec:
    """What a task needs to rebuild the run's state in any process that sees the same files:
    the workspace (folder and read options), the maps' folder, the options, the map cache."""

    token: str
    root: Path
    workspace_options: WorkspaceOptions
    stereo: Path
    options: DenseOptions
    cache: Path | None


@dataclass
class _RunState:
    workspace: Workspace
    providers: PriorProviders | None
    highlights: HighlightStage | None
    cache: MapCache | None
    # One provider per process and run (a network's session is loaded once); its masks stored.
    masks: MaskStore


# The runs' states in this process, by token: built once per worker process and run, not per task.
_states: dict[str, _RunState] = {}


def _new_state(
    spec: _RunSpec, workspace: Workspace | None = None, cache: MapCache | None = None
) -> _RunState:
    workspace = (
        workspace if workspace is not None else Workspace.open(spec.root, spec.workspace_options)
    )
    options = spec.options
    highlight = highlight_config(options.priors.get("highlight"))
    return _RunState(
        workspace,
        PriorProviders.from_configs(options.priors) if _uses_labels(options) else None,
        HighlightStage(workspace, spec.stereo, highlight) if highlight is not None else None,
        cache if cache is not None else MapCache(spec.cache) if spec.cache is not None else None,
        MaskStore.from_config(options.mask, spec.stereo, workspace.root, options.overwrite),
    )


def _run_state(spec: _RunSpec) -> _RunState:
    state = _states.get(spec.token)
    if state is None:
        import cv2

        if (
            spec.options.patch_match.num_threads > 0
        ):  # OpenCV reads 0 as "no threads", not "every core"
            cv2.setNumThreads(spec.options.patch_match.num_threads)
        while len(_states) >= 2:  # a worker serves one run at a time; keep the last ones only
            _states.pop(next(iter(_states)))
        state = _states[spec.token] = _new_state(spec)
    return state


@contextmanager
def _serving(spec: _RunSpec, state: _RunState) -> Iterator[None]:
    """While the block runs, tasks of ``spec`` run in this process use ``state`` (the driver's,
    already built) instead of building their own."""
    _states[spec.token] = state
    try:
        yield
    finally:
        _states.pop(spec.token, None)


def _task_key(stage: str, name: str) -> str:
    return f"{stage}:{name}"


def _dense_tasks(
    spec: _RunSpec,
    workspace: Workspace,
    plans: dict[Pass, list[_ViewPlan]],
    multiview: bool,
    highlights: bool,
    progress: bool,
) -> list[Task]:
    """The run's tasks, each after the tasks whose outputs it reads (tasks of views whose outputs
    are current are not made, their files are read as they are): the highlight provider per
    view; the photometric maps of a view after the highlights of the view and its sources; the
    multi-view refinement of a view's highlights after the photometric maps of the view and its
    sources; the geometric maps after the photometric maps (and refined highlights) of the view
    and its sources."""
    options = spec.options
    todo = {
        pass_: [p for p in plans[pass_] if options.overwrite or not p.status.reusable]
        for pass_ in plans
    }
    names = lambda plan: (plan.view.name, *_sources(plan.view, options))  # noqa: E731
    tasks: list[Task] = []
    single, refined = "highlights", "highlights-geometric"  # the highlight tasks' kinds
    if highlights:
        needed = [
            n for pass_ in options.passes for plan in todo[pass_] for n in plan.inputs["highlights"]
        ]
        refine = (
            list(
                dict.fromkeys(
                    n for plan in todo.get(Pass.GEOMETRIC, []) for n in plan.inputs["highlights"]
                )
            )
            if multiview
            else []
        )
        needed += [n for name in refine for n in (name, *_sources(workspace[name], options))]
        tasks += [
            Task(_task_key(single, n), "highlights", _prepare_highlight, (spec, n))
            for n in dict.fromkeys(needed)
        ]
    for plan in todo[Pass.PHOTOMETRIC]:
        after = tuple(_task_key(single, n) for n in names(plan)) if highlights else ()
        tasks.append(
            Task(
                _task_key(Pass.PHOTOMETRIC.value, plan.view.name),
                "photometric pass",
                _make_view_pass,
                (spec, Pass.PHOTOMETRIC, plan, progress),
                after,
            )
        )
    if Pass.GEOMETRIC not in todo:
        return tasks
    photometric = {p.view.name: p.fingerprint for p in plans[Pass.PHOTOMETRIC]}
    if multiview:
        for name in refine:
            sources = _sources(workspace[name], options)
            after = tuple(
                _task_key(kind, n)
                for n in (name, *sources)
                for kind in (single, Pass.PHOTOMETRIC.value)
            )
            tasks.append(
                Task(
                    _task_key(refined, name),
                    "highlights (multi-view)",
                    _refine_highlight,
                    (spec, name, sources, photometric),
                    after,
                )
            )
    for plan in todo[Pass.GEOMETRIC]:
        kinds = (Pass.PHOTOMETRIC.value,) + (
            ((refined if multiview else single),) if highlights else ()
        )
        after = tuple(_task_key(kind, n) for n in names(plan) for kind in kinds)
        tasks.append(
            Task(
                _task_key(Pass.GEOMETRIC.value, plan.view.name),
                "geometric pass",
                _make_view_pass,
                (spec, Pass.GEOMETRIC, plan, progress),
                after,
            )
        )
    return tasks
