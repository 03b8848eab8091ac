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

import hashlib
import logging
import os
import shutil
import time
import uuid
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Iterable

import numpy as np

from dvpmvs.errors import DvpmvsError
from dvpmvs.executor import ExecutorOptions, Task, run_tasks
from dvpmvs.fusion import FusionOptions, empty_cloud_message, fuse_to_ply, fuse_with_colmap, visibility_path
from dvpmvs.maps import MAP_KINDS, MapFormatError, map_path, read_depth_map, read_extra_map, read_normal_map, \
    remove_temporaries, write_depth_map, write_extra_map, write_normal_map
from dvpmvs.passes import Pass
from dvpmvs.patchmatch import PatchMatchOptions, Problem, ViewData, estimate
from dvpmvs.patchmatch.low_resolution import low_resolution_depth
from dvpmvs.preview import colorize_cost, colorize_depth, colorize_normals, write_png
from dvpmvs.highlight import HIGHLIGHT_DIR, HighlightStage, highlight_config
from dvpmvs.priors import PriorContext, PriorProviders, compute_priors
from dvpmvs.digests import differences, file_digest, fingerprint, matches_stamp
from dvpmvs.provenance import (PROVENANCE_DIR, CachedOutput, MapCache, Record, Status, code_identity, read_record,
                               record_path, stamp_files, status, write_record)
from dvpmvs.segmentation import SegmentationOptions, colorize_labels, segment
from dvpmvs.validation import check_field_types, check_ply_output, check_writable
from dvpmvs.view import View
from dvpmvs.workspace import Workspace, WorkspaceOptions
from dvpmvs.writer_lock import writer_lock

__all__ = ["DenseOptions", "DenseError", "ViewReport", "DenseSummary", "FusionReport", "pass_inputs", "map_files",
           "run_dense", "fuse_workspace", "fuse_to_file", "cloud_record_path", "FUSION_BACKENDS",
           "GEOMETRIC_ONLY_OPTIONS"]

log = logging.getLogger(__name__)

FUSION_BACKENDS = ("dvpmvs", "colmap")
_MAP_KINDS = ("visibility", "cost", "normal", "depth")  # write order: depth last

# Estimator options the photometric pass never reads (tests check its maps do not move with
# them), so that runs differing only in these share their photometric maps.
GEOMETRIC_ONLY_OPTIONS = frozenset({"geom_iterations", "geom_weight", "geom_max_error", "geom_deformable",
                                    "visibility_max_error", "visibility_restore_radius", "visibility_restoration",
                                    "highlight_multiview", "highlight_multiview_excess",
                                    "highlight_multiview_tolerance", "flat_noise_factor", "flat_min_consistent",
                                    "flat_max_error"})
# Options that change how fast outputs are made, never what they hold.
_SPEED_ONLY_OPTIONS = frozenset({"num_threads"})
# Fusion options that never change a cloud's points: the cloud's record lists the views fused
# without maps, and a missing view stops the run unless allowed, whatever the record says.
_SPEED_ONLY_FUSION_OPTIONS = frozenset({"num_threads", "cache_views", "allow_missing"})


class DenseError(DvpmvsError, RuntimeError):
    """The dense stage cannot run as asked (for example, the output folder holds maps that dvpmvs
    did not write); the message says what to do."""


@dataclass(frozen=True)
class DenseOptions:
    """patch_match: estimator options. geometric: run the geometric-consistency pass.
    overwrite: recompute every view, whatever the maps found (also maps without a record).
    fusion / fusion_backend: how the maps are fused (``dvpmvs`` or ``colmap``); fuse=False stops
    after the maps. previews: write PNG previews. priors: the provider configs
    ``{"depth_prior": ..., "normal_prior": ..., "edge": ..., "highlight": ...}`` (highlight:
    :mod:`dvpmvs.highlight`, absent or ``none`` for none); segmentation: the
    depth-normal-edge aligned prior's options, None to let deformable PatchMatch's anchors go
    anywhere (the paper's ``w/o Agn``)."""

    patch_match: PatchMatchOptions = field(default_factory=PatchMatchOptions)
    priors: dict = field(default_factory=lambda: {"depth_prior": {"name": "coarse_mvs"},
                                                  "normal_prior": {"name": "from_depth"},
                                                  "edge": {"name": "roberts"}})
    segmentation: SegmentationOptions | None = field(default_factory=SegmentationOptions)
    geometric: bool = True
    overwrite: bool = False
    fuse: bool = True
    fusion: FusionOptions = field(default_factory=FusionOptions)
    fusion_backend: str = "dvpmvs"
    previews: bool = True

    def __post_init__(self):
        check_field_types(self)
        if self.fusion_backend not in FUSION_BACKENDS:
            raise ValueError(f"unknown fusion backend {self.fusion_backend!r}; choose {' or '.join(FUSION_BACKENDS)}")

    @property
    def final_pass(self) -> Pass:
        return Pass.GEOMETRIC if self.geometric else Pass.PHOTOMETRIC

    @property
    def passes(self) -> list[Pass]:
        return [Pass.PHOTOMETRIC] + ([Pass.GEOMETRIC] if self.geometric else [])


@dataclass
class ViewReport:
    """One view's maps of one pass. ``status``: what the run found (:class:`Status`);
    ``action``: ``computed``, ``reused`` (current maps in place) or ``cached`` (linked from the
    map cache). The figures are those of the computation that made the maps, in this run or an
    earlier one (from their record)."""

    name: str
    pass_: Pass
    status: Status = Status.MISSING
    action: str = "computed"
    seconds: float = 0.0
    evaluations: int = 0
    prior_seconds: float = 0.0  # priors + segmentation (part of ``seconds``)
    valid_fraction: float = 0.0
    width: int = 0
    height: int = 0
    fingerprint: str = ""
    work: list[dict] = field(default_factory=list)  # per pyramid level: what the estimator matched

    @property
    def skipped(self) -> bool:
        """Not computed by this run."""
        return self.action != "computed"

    def as_dict(self) -> dict:
        return {"name": self.name, "pass": self.pass_.value, "status": self.status.value, "action": self.action,
                "seconds": self.seconds, "evaluations": self.evaluations, "prior_seconds": self.prior_seconds,
                "valid_fraction": self.valid_fraction, "size": [self.width, self.height],
                "fingerprint": self.fingerprint, "work": self.work}


@dataclass
class DenseSummary:
    """A run's reports. ``pass_seconds``: per pass, the seconds its tasks took (one after another
    with the local executor: the pass's wall time; on a cluster the sum over the workers);
    ``wall_seconds``: the tasks' wall time, all passes."""

    reports: list[ViewReport]
    pass_seconds: dict[str, float]
    fusion_seconds: float = 0.0
    num_points: int = 0
    output: Path | None = None
    stereo_dir: Path | None = None
    fusion_reused: bool = False
    fusion_fingerprint: str = ""
    highlight_seconds: dict[str, float] = field(default_factory=dict)  # per view the highlight stage computed
    wall_seconds: float = 0.0
    fusion_views_without_maps: list[str] = field(default_factory=list)  # a partial cloud (allow_missing)

    def computed(self, pass_: Pass) -> list[ViewReport]:
        return [r for r in self.reports if r.pass_ is pass_ and not r.skipped]

    def of_pass(self, pass_: Pass) -> list[ViewReport]:
        return [r for r in self.reports if r.pass_ is pass_]

    def seconds_per_view(self) -> float:
        """The cost of the maps and the cloud per reference view: every pass's per-view seconds
        (priors included, from the records of reused maps) and fusion, over the views."""
        views = {r.name for r in self.reports}
        return (sum(r.seconds for r in self.reports) + self.fusion_seconds) / max(len(views), 1)

    def work_per_pixel(self, pass_: Pass) -> list[dict]:
        """Per pyramid level of ``pass_``, the hypotheses, windows and samples the estimator
        matched per pixel of that level, over the views whose maps this run has (computed here or,
        from their records, earlier); the level's size is the first view's."""
        levels: dict[int, dict] = {}
        for report in self.of_pass(pass_):
            for level in report.work:
                total = levels.setdefault(level["level"], {"level": level["level"], "size": [level["width"],
                                          level["height"]], "pixels": 0, "hypotheses": 0, "windows": 0, "samples": 0})
                total["pixels"] += level["width"] * level["height"]
                for key in ("hypotheses", "windows", "samples"):
                    total[key] += level[key]
        return [{"level": t["level"], "size": t["size"],
                 **{key: t[key] / max(t["pixels"], 1) for key in ("hypotheses", "windows", "samples")}}
                for _, t in sorted(levels.items())]

    def as_dict(self) -> dict:
        passes = {}
        for pass_value, seconds in self.pass_seconds.items():
            reports = self.of_pass(Pass(pass_value))
            passes[pass_value] = {
                "task_seconds": seconds, "views": len(reports),
                "computed": sum(r.action == "computed" for r in reports),
                "reused": sum(r.action == "reused" for r in reports),
                "cached": sum(r.action == "cached" for r in reports),
                "seconds": sum(r.seconds for r in reports), "prior_seconds": sum(r.prior_seconds for r in reports),
                "hypothesis_evaluations": sum(r.evaluations for r in reports),
                "work_per_pixel": self.work_per_pixel(Pass(pass_value)),
                "valid_fraction": float(np.mean([r.valid_fraction for r in reports])) if reports else 0.0,
                "view_reports": [r.as_dict() for r in reports]}
        return {"passes": passes, "seconds_per_view": self.seconds_per_view(), "wall_seconds": self.wall_seconds,
                "highlights": {"computed": len(self.highlight_seconds),
                               "seconds": sum(self.highlight_seconds.values())},
                "fusion": {"seconds": self.fusion_seconds, "points": self.num_points, "reused": self.fusion_reused,
                           "views_without_maps": self.fusion_views_without_maps,
                           "output": None if self.output is None else str(self.output),
                           "fingerprint": self.fusion_fingerprint},
                "stereo_dir": None if self.stereo_dir is None else str(self.stereo_dir)}


# -- what shapes a view's maps ---------------------------------------------------------------------


def _uses_labels(options: DenseOptions) -> bool:
    return options.patch_match.deformable and options.segmentation is not None


def _camera(view: View) -> dict:
    return {"name": view.name, "image": file_digest(view.path), "size": [view.width, view.height],
            "K": view.K, "R": view.R, "t": view.t}


def _sources(view: View, options: DenseOptions) -> tuple[str, ...]:
    return view.sources[: options.patch_match.max_sources]


def pass_inputs(workspace: Workspace, view: View, pass_: Pass, options: DenseOptions,
                providers: PriorProviders | None, photometric: dict[str, str | None],
                highlights: HighlightStage | None = None) -> dict:
    """Everything that shapes ``view``'s maps of ``pass_``, as a tree for :func:`fingerprint`:
    the code, the pass's estimator options, the reference's and the sources' images (digests),
    calibration and the reference's depth range; for the photometric pass with the sparse seeding
    the sparse points that seed it, and with the aligned prior its providers (configs, plugins, the
    files they read) and segmentation options and the sparse points they align to; for the
    geometric pass the fingerprints of the photometric maps it reads (``photometric``: view name
    -> fingerprint, None for none); with highlight perception (``highlights``) the fingerprints
    of the reference's and the sources' highlight outputs."""
    pm = {key: value for key, value in options.patch_match.as_dict().items()
          if key not in _SPEED_ONLY_OPTIONS and not (pass_ is Pass.PHOTOMETRIC and key in GEOMETRIC_ONLY_OPTIONS)}
    sources = _sources(view, options)
    inputs = {"pass": pass_.value, "code": code_identity(), "patch_match": pm,
              "reference": {**_camera(view), "image_id": view.image_id, "depth_range": list(view.depth_range)},
              "sources": [_camera(workspace[name]) for name in sources]}
    if options.patch_match.sparse_seed and pass_ is Pass.PHOTOMETRIC:
        seeds = np.ascontiguousarray(workspace.observed_points(view.name), np.float64)
        inputs["sparse_seed_points"] = hashlib.sha256(seeds.tobytes()).hexdigest()
    if _uses_labels(options) and pass_ is Pass.PHOTOMETRIC:
        sparse = np.ascontiguousarray(workspace.sparse_points(view.name), np.float64)
        inputs["aligned_prior"] = {
            "segmentation": asdict(options.segmentation),
            "providers": providers.provenance(view.name, workspace.root) if providers is not None else None,
            "sparse_points": hashlib.sha256(sparse.tobytes()).hexdigest()}
    if pass_ is Pass.GEOMETRIC:
        inputs["photometric"] = {name: photometric.get(name) for name in (view.name, *sources)}
    if highlights is not None:
        if pass_ is Pass.GEOMETRIC and options.patch_match.highlight_multiview:
            inputs["highlights"] = {name: highlights.refined_fingerprint(
                name, _sources(workspace[name], options), photometric, _multiview_settings(options))
                for name in (view.name, *sources)}
        else:
            inputs["highlights"] = {name: highlights.fingerprint(name) for name in (view.name, *sources)}
    return inputs


def _multiview_settings(options: DenseOptions) -> dict:
    pm = options.patch_match
    return {"min_excess": pm.highlight_multiview_excess, "depth_tolerance": pm.highlight_multiview_tolerance}


def map_files(stereo: Path, view_name: str, pass_: Pass, labels: bool) -> dict[str, Path]:
    """The map files a pass writes for a view (labels: the photometric pass's region labels)."""
    kinds = (("labels",) if labels and pass_ is Pass.PHOTOMETRIC else ()) + _MAP_KINDS
    return {kind: map_path(stereo, view_name, kind, pass_) for kind in kinds}


def _preview_files(stereo: Path, view_name: str, pass_: Pass, labels: bool) -> dict[str, Path]:
    folder = stereo / "previews"
    names = [f"{view_name}.{pass_.value}.{kind}.png" for kind in ("depth", "normal", "cost")]
    if labels and pass_ is Pass.PHOTOMETRIC:
        names += [f"{view_name}.{kind}.png" for kind in ("labels", "edges", "depth_prior", "normal_prior")]
    return {name: folder / name for name in names}


@dataclass
class _ViewPlan:
    view: View
    inputs: dict
    fingerprint: str
    record: Record | None
    status: Status
    files: dict[str, Path]


def _plan_pass(workspace: Workspace, stereo: Path, pass_: Pass, options: DenseOptions,
               providers: PriorProviders | None, photometric: dict[str, str | None],
               highlights: HighlightStage | None = None) -> list[_ViewPlan]:
    plans = []
    labels = _uses_labels(options)
    for view in workspace.reference_views():
        if not view.sources:
            continue
        inputs = pass_inputs(workspace, view, pass_, options, providers, photometric, highlights)
        fp = fingerprint(inputs)
        record = read_record(record_path(stereo, view.name, pass_.value))
        files = map_files(stereo, view.name, pass_, labels)
        plans.append(_ViewPlan(view, inputs, fp, record, status(record, fp, stereo, files.values()), files))
    return plans


def _short(value) -> str:
    text = str(value)
    return text if len(text) <= 24 else text[:21] + "..."


def _explain(plans: list[_ViewPlan], pass_: Pass, overwrite: bool) -> str:
    """One line: how many views this pass computes and why."""
    total = len(plans)
    if overwrite:
        return f"{pass_.value} pass: computing all {total} views (overwrite=true)"
    todo = [p for p in plans if not p.status.reusable]
    if not todo:
        return f"{pass_.value} pass: the maps of all {total} views are current (same inputs): reused"
    counts: dict[Status, int] = {}
    for plan in todo:
        counts[plan.status] = counts.get(plan.status, 0) + 1
    parts = []
    if Status.STALE in counts:
        changed: dict[str, str] = {}
        for plan in todo:
            if plan.status is Status.STALE:
                for key, old, new in differences(plan.record.inputs, plan.inputs):
                    if key.startswith("photometric."):  # one entry, not a digest per source
                        changed.setdefault("photometric", "the photometric maps they read")
                    else:
                        changed.setdefault(key, f"{key}: {_short(old)} -> {_short(new)}")
        shown = list(changed.values())[:3]
        more = f", +{len(changed) - 3} more" if len(changed) > 3 else ""
        parts.append(f"{counts[Status.STALE]} made from other inputs ({'; '.join(shown)}{more})")
    wording = {Status.MISSING: "not computed yet", Status.INTERRUPTED: "interrupted",
               Status.MODIFIED: "changed on disk since they were written", Status.FOREIGN: "without a record"}
    parts += [f"{counts[s]} {text}" for s, text in wording.items() if s in counts]
    reused = total - len(todo)
    return (f"{pass_.value} pass: computing {len(todo)} of {total} views"
            + (f" ({reused} current, reused)" if reused else "") + ": " + ", ".join(parts))


def _refuse_foreign(plans: Iterable[tuple[Pass, _ViewPlan]], stereo: Path) -> None:
    foreign = [(pass_, plan) for pass_, plan in plans if plan.status is Status.FOREIGN]
    if not foreign:
        return
    pass_, first = foreign[0]
    example = next(p for kind, p in sorted(first.files.items(), key=lambda item: item[0] != "depth") if p.exists())
    raise DenseError(
        f"{stereo} holds maps that carry no dvpmvs provenance record ({len(foreign)} view pass(es), e.g. "
        f"{example}): written by COLMAP or by an older dvpmvs, so dvpmvs can neither reuse them nor tell "
        f"what made them. It does not overwrite them unasked: rerun with overwrite=true to replace them, or "
        f"with out=DIR to write this run's maps and cloud elsewhere")


# -- one view ---------------------------------------------------------------------------------------


def _view_data(view: View, depth: np.ndarray | None = None, cost: np.ndarray | None = None,
               highlights: HighlightStage | None = None, refined: bool = False) -> ViewData:
    maps = None
    if highlights is not None:
        maps = highlights.load_refined(view.name) if refined else highlights.load(view.name)
    return ViewData(view.name, view.load_grey(), view.K, view.R, view.t, depth, cost,
                    None if maps is None else maps.corrected, None if maps is None else maps.mask)


def _read_map_or(stereo: Path, view: View, kind: str, pass_: Pass, missing: float, consequence: str) -> np.ndarray:
    """The view's one-channel ``kind`` map of ``pass_`` (H, W); where the view has none, ``missing``
    everywhere, with a warning that says the ``consequence``."""
    path = map_path(stereo, view.name, kind, pass_)
    if not path.is_file():
        log.warning("source %s has no %s %s map; %s", view.name, pass_.value, kind, consequence)
        return np.full((view.height, view.width), missing, np.float32)
    data = read_depth_map(path) if kind == "depth" else read_extra_map(path)
    if data.shape[:2] != (view.height, view.width) or data.size != view.height * view.width:
        raise MapFormatError(f"{path} holds a {data.shape} map; the view needs ({view.height}, {view.width})")
    return data.reshape(view.height, view.width)


def _read_depth_or_empty(stereo: Path, view: View, pass_: Pass) -> np.ndarray:
    return _read_map_or(stereo, view, "depth", pass_, 0.0, "it gives no geometric constraint")


def _read_cost_or_unknown(stereo: Path, view: View, pass_: Pass) -> np.ndarray:
    """Infinite (unknown: never the lowest) where the view has no cost map."""
    return _read_map_or(stereo, view, "cost", pass_, np.inf, "its visibility is restored through its own depths")


def _problem(workspace: Workspace, view: View, pass_: Pass, options: PatchMatchOptions,
             stereo: Path | None = None, highlights: HighlightStage | None = None) -> Problem:
    """The estimator's problem for ``view``; the geometric pass reads the photometric maps
    from ``stereo`` (default: the workspace's); ``highlights``: the views' highlight outputs."""
    stereo = workspace.stereo_dir if stereo is None else stereo
    names = view.sources[: options.max_sources]
    if pass_ is Pass.PHOTOMETRIC:
        return Problem(_view_data(view, highlights=highlights),
                       [_view_data(workspace[n], highlights=highlights) for n in names], view.depth_range,
                       sparse_points=workspace.observed_points(view.name) if options.sparse_seed else None)
    previous = Pass.PHOTOMETRIC
    initial = (_read_depth_or_empty(stereo, view, previous),
               read_normal_map(map_path(stereo, view.name, "normal", previous)))
    restore = (options.deformable and options.anchor_visibility and options.visibility_restoration
               and options.visibility_restore_radius > 0)
    refined = options.highlight_multiview
    sources = [_view_data(workspace[n], _read_depth_or_empty(stereo, workspace[n], previous),
                          _read_cost_or_unknown(stereo, workspace[n], previous) if restore else None, highlights,
                          refined)
               for n in names]
    return Problem(_view_data(view, highlights=highlights, refined=refined), sources, view.depth_range,
                   initial=initial)


def _labels(workspace: Workspace, stereo: Path, view: View, problem: Problem, pass_: Pass, options: DenseOptions,
            providers: PriorProviders | None) -> tuple[np.ndarray, float]:
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
        log.warning("view %s has no region labels beside its photometric maps; segmenting again", view.name)
    start = time.perf_counter()
    ctx = PriorContext(view.name, problem.reference.image, view.K, view.depth_range,
                       workspace.sparse_points(view.name), rgb_loader=view.load_rgb, root=workspace.root,
                       low_resolution_depth=partial(low_resolution_depth, problem, options.patch_match))
    priors = compute_priors(ctx, providers)
    if priors.edges is None or priors.depth is None:
        raise ValueError("the aligned prior needs an edge detector and a depth prior; set edge= and depth_prior=, "
                         "or segmentation=null (method=w_o_agn) to deform without regions")
    result = segment(priors.edges, priors.depth, priors.normal, view.K, view.depth_range, options.segmentation,
                     priors.depth_valid, priors.normal_from_depth)
    if pass_ is Pass.PHOTOMETRIC:
        write_extra_map(path, result.labels)
        if options.previews:
            previews = _preview_files(stereo, view.name, pass_, True)
            write_png(previews[f"{view.name}.labels.png"], colorize_labels(result.labels))
            write_png(previews[f"{view.name}.edges.png"], (priors.edges * 255).astype(np.uint8))
            lo, hi = view.depth_range
            write_png(previews[f"{view.name}.depth_prior.png"], colorize_depth(priors.depth, lo, hi))
            if priors.normal is not None:
                write_png(previews[f"{view.name}.normal_prior.png"], colorize_normals(priors.normal))
    log.debug("view %s: %d regions, %d splits, %d merges, %d pixels filtered", view.name,
              int(result.labels.max()), result.splits, result.merges, result.filtered)
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


def _compute_view(workspace: Workspace, stereo: Path, plan: _ViewPlan, pass_: Pass, options: DenseOptions,
                  providers: PriorProviders | None, progress: bool, highlights: HighlightStage | None = None) -> Record:
    from tqdm import tqdm

    view = plan.view
    path = record_path(stereo, view.name, pass_.value)
    # Pending first: a run cut off while writing leaves maps that read as interrupted, not finished.
    write_record(path, Record(plan.fingerprint, plan.inputs))
    # A per-view seed keeps views independent of the order they are computed in.
    pm = replace(options.patch_match, seed=options.patch_match.seed * 1_000_003 + view.image_id)
    problem = _problem(workspace, view, pass_, pm, stereo, highlights)
    prior_seconds = 0.0
    if _uses_labels(options):
        problem.labels, prior_seconds = _labels(workspace, stereo, view, problem, pass_, options, providers)
    with tqdm(total=1, desc=f"  {view.name}", unit="sweep", leave=False, disable=not progress,
              dynamic_ncols=True) as inner:
        def on_sweep(done: int, total: int) -> None:
            inner.total = total
            inner.n = done
            inner.refresh()

        result = estimate(problem, pm, pass_, on_sweep=on_sweep)
    del problem  # release the images before writing
    _write_maps(stereo, view, pass_, result, options.previews)
    previews = _preview_files(stereo, view.name, pass_, _uses_labels(options))
    record = Record(plan.fingerprint, plan.inputs, complete=True, files=stamp_files(stereo, plan.files),
                    extras=[p.relative_to(stereo).as_posix() for p in previews.values() if p.is_file()],
                    stats={"seconds": result.seconds + prior_seconds, "prior_seconds": prior_seconds,
                           "evaluations": result.hypothesis_evaluations,
                           "work": [asdict(level) for level in result.work],
                           "valid_fraction": float((result.depth > 0).mean())})
    write_record(path, record)
    return record


def _report(plan: _ViewPlan, pass_: Pass, record: Record, action: str) -> ViewReport:
    stats = record.stats
    return ViewReport(plan.view.name, pass_, plan.status, action, seconds=float(stats.get("seconds", 0.0)),
                      evaluations=int(stats.get("evaluations", 0)), prior_seconds=float(stats.get("prior_seconds", 0.0)),
                      valid_fraction=float(stats.get("valid_fraction", 0.0)), width=plan.view.width,
                      height=plan.view.height, fingerprint=plan.fingerprint, work=list(stats.get("work", [])))


def _make_view_pass(spec: _RunSpec, pass_: Pass, plan: _ViewPlan, progress: bool) -> ViewReport:
    """One view's maps of one pass: linked from the map cache where it holds them, else computed
    (priors and segmentation included); the task of a view and pass, in any process."""
    state = _run_state(spec)
    options, stereo, cache = spec.options, spec.stereo, state.cache
    previews = _preview_files(stereo, plan.view.name, pass_, _uses_labels(options)) if options.previews else {}
    if cache is not None and not options.overwrite:
        record = cache.fetch(pass_.value, plan.fingerprint, stereo, plan.files, previews)
        if record is not None:
            write_record(record_path(stereo, plan.view.name, pass_.value), record)
            return _report(plan, pass_, record, "cached")
    record = _compute_view(state.workspace, stereo, plan, pass_, options, state.providers, progress,
                           state.highlights)
    if cache is not None:
        cache.store(pass_.value, record, stereo, previews)
    return _report(plan, pass_, record, "computed")


def _prepare_highlight(spec: _RunSpec, name: str) -> float | None:
    """The highlight provider's outputs of one view, unless current (the task)."""
    return _run_state(spec).highlights.prepare_view(name, spec.options.overwrite, spec.options.previews)


def _refine_highlight(spec: _RunSpec, name: str, sources: tuple[str, ...], photometric: dict[str, str | None]) \
        -> float | None:
    """The multi-view refinement of one view's highlight outputs from the photometric maps of the
    view and its sources, unless current (the task)."""
    state = _run_state(spec)
    return state.highlights.refine_view(
        name, sources, photometric, _multiview_settings(spec.options),
        lambda n: _read_depth_or_empty(spec.stereo, state.workspace[n], Pass.PHOTOMETRIC), spec.options.overwrite,
        spec.options.previews)


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


# The runs' states in this process, by token: built once per worker process and run, not per task.
_states: dict[str, _RunState] = {}


def _new_state(spec: _RunSpec, workspace: Workspace | None = None, cache: MapCache | None = None) -> _RunState:
    workspace = workspace if workspace is not None else Workspace.open(spec.root, spec.workspace_options)
    options = spec.options
    highlight = highlight_config(options.priors.get("highlight"))
    return _RunState(workspace,
                     PriorProviders.from_configs(options.priors) if _uses_labels(options) else None,
                     HighlightStage(workspace, spec.stereo, highlight) if highlight is not None else None,
                     cache if cache is not None else MapCache(spec.cache) if spec.cache is not None else None)


def _run_state(spec: _RunSpec) -> _RunState:
    state = _states.get(spec.token)
    if state is None:
        import cv2

        if spec.options.patch_match.num_threads > 0:  # OpenCV reads 0 as "no threads", not "every core"
            cv2.setNumThreads(spec.options.patch_match.num_threads)
        while len(_states) >= 2:  # a worker serves one run at a time; keep the last ones only
            _states.pop(next(iter(_states)))
        state = _states[spec.token] = _new_state(spec)
    return state


def _task_key(stage: str, name: str) -> str:
    return f"{stage}:{name}"


def _dense_tasks(spec: _RunSpec, workspace: Workspace, plans: dict[Pass, list[_ViewPlan]], multiview: bool,
                 highlights: bool, progress: bool) -> list[Task]:
    """The run's tasks, each after the tasks whose outputs it reads (tasks of views whose outputs
    are current are not made, their files are read as they are): the highlight provider per
    view; the photometric maps of a view after the highlights of the view and its sources; the
    multi-view refinement of a view's highlights after the photometric maps of the view and its
    sources; the geometric maps after the photometric maps (and refined highlights) of the view
    and its sources."""
    options = spec.options
    todo = {pass_: [p for p in plans[pass_] if options.overwrite or not p.status.reusable] for pass_ in plans}
    names = lambda plan: (plan.view.name, *_sources(plan.view, options))  # noqa: E731
    tasks: list[Task] = []
    single, refined = "highlights", "highlights-geometric"  # the highlight tasks' kinds
    if highlights:
        needed = [n for pass_ in options.passes for plan in todo[pass_] for n in plan.inputs["highlights"]]
        refine = list(dict.fromkeys(n for plan in todo.get(Pass.GEOMETRIC, []) for n in plan.inputs["highlights"])) \
            if multiview else []
        needed += [n for name in refine for n in (name, *_sources(workspace[name], options))]
        tasks += [Task(_task_key(single, n), "highlights", _prepare_highlight, (spec, n))
                  for n in dict.fromkeys(needed)]
    for plan in todo[Pass.PHOTOMETRIC]:
        after = tuple(_task_key(single, n) for n in names(plan)) if highlights else ()
        tasks.append(Task(_task_key(Pass.PHOTOMETRIC.value, plan.view.name), "photometric pass", _make_view_pass,
                          (spec, Pass.PHOTOMETRIC, plan, progress), after))
    if Pass.GEOMETRIC not in todo:
        return tasks
    photometric = {p.view.name: p.fingerprint for p in plans[Pass.PHOTOMETRIC]}
    if multiview:
        for name in refine:
            sources = _sources(workspace[name], options)
            after = tuple(_task_key(kind, n) for n in (name, *sources) for kind in (single, Pass.PHOTOMETRIC.value))
            tasks.append(Task(_task_key(refined, name), "highlights (multi-view)", _refine_highlight,
                              (spec, name, sources, photometric), after))
    for plan in todo[Pass.GEOMETRIC]:
        kinds = (Pass.PHOTOMETRIC.value,) + (((refined if multiview else single),) if highlights else ())
        after = tuple(_task_key(kind, n) for n in names(plan) for kind in kinds)
        tasks.append(Task(_task_key(Pass.GEOMETRIC.value, plan.view.name), "geometric pass", _make_view_pass,
                          (spec, Pass.GEOMETRIC, plan, progress), after))
    return tasks


# -- the whole stage --------------------------------------------------------------------------------


MISSING_MAPS = "missing"  # a view with sources but no maps, in a cloud's inputs (a partial cloud)
NO_SOURCES = "no sources"  # a view the dense stage gives no maps (no source view)


def _no_sources_error(workspace: Workspace) -> DenseError:
    views = workspace.reference_views()
    return DenseError(
        f"none of the {len(views)} view(s) of {workspace.root} has a source view, so no depth can be computed: "
        f"multi-view stereo needs each view to overlap others. Check the source lists of "
        f"{workspace.stereo_dir / 'patch-match.cfg'} and the sparse model (a model with one registered image, or "
        f"views that share no sparse point, give none)")


def _fused_maps(workspace: Workspace, stereo: Path, pass_: Pass) -> dict[str, object]:
    """Per reference view, what fusion reads of it, as the cloud's record must describe it: the
    fingerprint of its maps where their record is complete and the depth and normal maps are the
    files it stamped; else (maps without a record, COLMAP's; or changed since written) the
    digests of the two files; :data:`MISSING_MAPS` where a view with sources has none;
    :data:`NO_SOURCES` where a view without sources has none."""
    maps: dict[str, object] = {}
    for view in workspace.reference_views():
        depth, normal = (map_path(stereo, view.name, kind, pass_) for kind in ("depth", "normal"))
        if not (depth.is_file() and normal.is_file()):
            maps[view.name] = MISSING_MAPS if view.sources else NO_SOURCES
            continue
        record = read_record(record_path(stereo, view.name, pass_.value))
        stamps = record.files if record is not None and record.complete else {}
        if all(kind in stamps and (stereo / stamps[kind]["path"]) == path and matches_stamp(path, stamps[kind])
               for kind, path in (("depth", depth), ("normal", normal))):
            maps[view.name] = record.fingerprint
        else:
            maps[view.name] = {"depth": file_digest(depth), "normal": file_digest(normal),
                               "image": file_digest(view.path)}
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
    views_without_maps: list[str] = field(default_factory=list)  # fused without them (allow_missing)


def fuse_workspace(workspace: Workspace, fusion: FusionOptions, backend: str, output: str | Path,
                   stereo_dir: str | Path | None = None, colmap_root: str | Path | None = None,
                   reuse: bool = True, progress: bool = True) -> FusionReport:
    """Fuse the maps in ``stereo_dir`` (default the workspace's) into ``output`` and record what
    made the cloud beside it (``<cloud>.provenance.json``). With ``reuse``, a cloud whose record
    carries the same fingerprint (the same maps, fusion options and code) is kept as it is."""
    output = Path(output).expanduser()
    stereo = workspace.stereo_dir if stereo_dir is None else Path(stereo_dir)
    check_cloud_path(output)
    # The maps' folder is locked: a dense run writing maps there would change them under fusion
    # (a folder this process cannot write, nobody's dense run here can write either).
    maps_folder = stereo.parent
    with writer_lock(maps_folder) if os.access(maps_folder, os.W_OK) else nullcontext():
        if output.parent.resolve() == stereo.parent.resolve():
            remove_temporaries(output.parent, recursive=False)
        return _fuse_workspace_locked(workspace, fusion, backend, output, stereo, colmap_root, reuse, progress)


def _fuse_workspace_locked(workspace: Workspace, fusion: FusionOptions, backend: str, output: Path, stereo: Path,
                           colmap_root, reuse: bool, progress: bool) -> FusionReport:
    maps = _fused_maps(workspace, stereo, Pass(fusion.input_type))
    if all(value == NO_SOURCES for value in maps.values()):
        raise _no_sources_error(workspace)
    missing = [name for name, value in maps.items() if value == MISSING_MAPS]
    if missing and all(value in (MISSING_MAPS, NO_SOURCES) for value in maps.values()):
        raise DenseError(f"no {fusion.input_type} maps in {stereo}: run `dvpmvs dense workspace={workspace.root}` "
                         f"first")
    if missing and not fusion.allow_missing:
        raise DenseError(
            f"{len(missing)} of {len(maps)} views have no {fusion.input_type} maps in {stereo} (e.g. "
            f"{map_path(stereo, missing[0], 'depth', Pass(fusion.input_type))}): a cloud without them would lack "
            f"their part of the scene. Compute them (`dvpmvs dense`, which recomputes only what is missing), or "
            f"give fusion_options.allow_missing=true for a partial cloud")
    if missing and backend == "colmap":
        raise DenseError(f"fusion_options.allow_missing=true is for fusion=dvpmvs: COLMAP's fusion needs the maps "
                         f"of every view of stereo/fusion.cfg ({len(missing)} missing, e.g. {missing[0]})")
    if missing:
        log.warning("fusion: %d view(s) have no %s maps and add no points: %s (allow_missing=true: a partial "
                    "cloud)", len(missing), fusion.input_type, ", ".join(missing))
    inputs = _fusion_inputs(fusion, backend, maps)
    cached = CachedOutput.check(cloud_record_path(output), inputs, output.parent, [output])
    if reuse and cached.current is not None:
        log.info("fusion: the cloud %s is current (same maps and fusion options): reused", output)
        stats = cached.current.stats
        return FusionReport(output, int(stats.get("points", 0)), float(stats.get("seconds", 0.0)), True,
                            cached.fingerprint, missing)
    _check_space(output.parent, _cloud_bytes(workspace),
                 f"the fused cloud, at most about {_cloud_bytes(workspace) / 2**20:,.1f} MB",
                 "give output=PATH on another disk")
    start = time.perf_counter()
    with cached.making():
        points = fuse_to_file(workspace, fusion, backend, output, progress, stereo_dir=stereo, colmap_root=colmap_root)
    seconds = time.perf_counter() - start
    # The visibility file is part of the cloud (COLMAP's meshers read both): without it the cloud
    # is not current.
    files = {"cloud": output}
    if visibility_path(output).is_file():
        files["visibility"] = visibility_path(output)
    cached.complete(files, {"points": points, "seconds": seconds, "views_without_maps": missing})
    return FusionReport(output, points, seconds, False, cached.fingerprint, missing)


def run_dense(workspace: Workspace, options: DenseOptions | None = None, output: str | Path | None = None,
              progress: bool = True, out: str | Path | None = None, cache: MapCache | None = None,
              on_start=None, executor: ExecutorOptions | None = None) -> DenseSummary:
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
    check_writable(out, "the output folder", "give out=DIR (a folder you can write) for the maps and the cloud")
    if options.fuse:
        check_cloud_path(output)
    with writer_lock(out):
        return _run_dense_locked(workspace, options, output, progress, out, cache, on_start, executor)


def check_cloud_path(output: Path) -> None:
    """The fused cloud's path must name a PLY file in a folder this process can write."""
    check_ply_output(output, "fused clouds", "fused.ply")


def _run_dense_locked(workspace: Workspace, options: DenseOptions, output: Path, progress: bool, out: Path,
                      cache: MapCache | None, on_start, executor: ExecutorOptions | None) -> DenseSummary:
    stereo = out / "stereo"
    leftovers = remove_temporaries(out, recursive=False) + remove_temporaries(stereo)
    if leftovers:
        log.info("removed %d temporary file(s) of an interrupted run (e.g. %s)", len(leftovers), leftovers[0])
    if out.resolve() != workspace.root.resolve():
        workspace.link_output(out)
    check_writable(stereo, "the maps' folder", "give out=DIR (a folder you can write) for the maps and the cloud")
    # Every pass is planned before any is run: maps without a record stop the run before it
    # has written anything.
    spec = _RunSpec(uuid.uuid4().hex, workspace.root, workspace.options, stereo, options,
                    cache.root if cache is not None else None)
    state = _new_state(spec, workspace, cache)
    plans: dict[Pass, list[_ViewPlan]] = {}
    upstream: dict[str, str | None] = {}
    for pass_ in options.passes:
        plans[pass_] = _plan_pass(workspace, stereo, pass_, options, state.providers, upstream, state.highlights)
        upstream = {p.view.name: p.fingerprint for p in plans[pass_]}
    if not plans[Pass.PHOTOMETRIC]:
        raise _no_sources_error(workspace)
    if not options.overwrite:
        _refuse_foreign(((pass_, p) for pass_ in options.passes for p in plans[pass_]), stereo)
        if options.fuse and output.exists() and not cloud_record_path(output).is_file():
            raise DenseError(f"{output} exists and carries no dvpmvs provenance record (written by COLMAP or an "
                             f"older dvpmvs); dvpmvs does not overwrite it unasked: rerun with overwrite=true, or "
                             f"give another output=PATH or out=DIR")
    todo = {pass_: [p for p in plans[pass_] if options.overwrite or not p.status.reusable] for pass_ in plans}
    _check_outputs(stereo, todo, options, output, workspace, state.highlights is not None)
    if on_start is not None:
        on_start()
    for pass_ in options.passes:
        log.info(_explain(plans[pass_], pass_, options.overwrite))
    multiview = state.highlights is not None and options.geometric and options.patch_match.highlight_multiview
    executor = executor or ExecutorOptions()
    if executor.name != "local":
        # Workers build the run's state from the spec; their kernels use the executor's threads.
        spec = replace(spec, options=replace(options, patch_match=replace(options.patch_match,
                                                                          num_threads=executor.kernel_threads())))
    tasks = _dense_tasks(spec, workspace, plans, multiview, state.highlights is not None,
                         progress and executor.name == "local")
    _states[spec.token] = state
    start = time.perf_counter()
    try:
        results = run_tasks(tasks, executor, progress)
    finally:
        _states.pop(spec.token, None)
    wall = time.perf_counter() - start
    if executor.name != "local":  # what a worker killed mid-write left
        remove_temporaries(stereo)
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
        made = [results[t.key][1] for t in tasks if t.stage == stage and results[t.key][0] is not None]
        if made:
            log.info("%s: %d view(s) computed, %.2f s per view", stage, len(made), sum(made) / len(made))
    summary = DenseSummary(reports, pass_seconds, stereo_dir=stereo, highlight_seconds=highlight_seconds,
                           wall_seconds=wall)
    if not options.fuse:
        return summary
    fusion = replace(options.fusion, input_type=options.final_pass.value)
    report = fuse_workspace(workspace, fusion, options.fusion_backend, output, stereo, out,
                            reuse=not options.overwrite, progress=progress)
    summary.output, summary.num_points, summary.fusion_seconds = report.output, report.points, report.seconds
    summary.fusion_reused, summary.fusion_fingerprint = report.reused, report.fingerprint
    summary.fusion_views_without_maps = report.views_without_maps
    return summary


# Bytes per pixel of a fused cloud, at most: a point is 27 bytes and its visibility record about
# 16; a fused cloud has 0.1-0.4 points per pixel of its views (the suite's scenes), so 0.5 is an
# upper bound.
_CLOUD_BYTES_PER_PIXEL = 0.5 * (27 + 16)
_RECORD_BYTES = 64 << 10  # a view pass's provenance record (its inputs are a few kilobytes)


def _check_outputs(stereo: Path, todo: dict[Pass, list[_ViewPlan]], options: DenseOptions, output: Path,
                   workspace: Workspace, highlights: bool) -> None:
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
            channels = 1 + 3 + 1 + len(_sources(plan.view, options))  # depth, normal, cost, visibility
            channels += 1 if "labels" in plan.files else 0
            maps += 4 * channels * pixels + _RECORD_BYTES + (4 * pixels if options.previews else 0)
    cloud = _cloud_bytes(workspace) if options.fuse else 0
    views = sum(map(len, todo.values()))
    what = f"the maps of {views} view pass(es), about {maps / 2**20:,.1f} MB"
    if cloud and os.stat(stereo).st_dev == os.stat(output.parent).st_dev:
        _check_space(stereo, maps + cloud, f"{what}, and the fused cloud, at most about {cloud / 2**20:,.1f} MB",
                     "give out=DIR on another disk (or output=PATH for the cloud)")
    else:
        _check_space(stereo, maps, what, "give out=DIR on another disk")
        if cloud:
            _check_space(output.parent, cloud, f"the fused cloud, at most about {cloud / 2**20:,.1f} MB",
                         "give output=PATH on another disk")


def _cloud_bytes(workspace: Workspace) -> int:
    """An upper bound of the fused cloud's size on disk (with its ``.vis``)."""
    return int(_CLOUD_BYTES_PER_PIXEL * sum(v.width * v.height for v in workspace.reference_views()))


def _check_space(folder: Path, needed: int, what: str, hint: str) -> None:
    free = shutil.disk_usage(folder).free
    if needed > free:
        raise DenseError(f"{folder} is on a disk with {free / 2**20:,.1f} MB free; this run writes {what}: free some "
                         f"space there, or {hint}")


def fuse_to_file(workspace: Workspace, fusion: FusionOptions, backend: str, output: str | Path,
                 progress: bool = True, stereo_dir: str | Path | None = None,
                 colmap_root: str | Path | None = None) -> int:
    """Fuse the maps in ``stereo_dir`` (default the workspace's) with ``backend`` (``dvpmvs`` or
    ``colmap``; COLMAP reads the workspace ``colmap_root``, default the workspace itself) into
    the PLY ``output``; returns the number of points."""
    from tqdm import tqdm

    if backend not in FUSION_BACKENDS:
        raise ValueError(f"unknown fusion backend {backend!r}; choose {' or '.join(FUSION_BACKENDS)}")
    if backend == "colmap":
        return fuse_with_colmap(workspace, output, fusion, root=colmap_root)
    views = workspace.reference_views()
    with tqdm(total=len(views), desc="fusion", unit="view", disable=not progress, dynamic_ncols=True) as bar:
        per_view = fuse_to_ply(workspace, output, fusion, stereo_dir=stereo_dir,
                               progress=lambda name: (bar.set_postfix_str(name), bar.update()))
    points = sum(per_view.values())
    if not points:
        log.warning(empty_cloud_message(fusion))
    return points
