"""The dense stage: views -> estimator passes -> maps on disk -> fusion.

A photometric pass over every reference view, then (optionally) a geometric-consistency pass
that reads the neighbours' photometric maps, then fusion. Each view's maps are written
atomically, depth last, so a view counts as finished only when all its maps are valid; a rerun
skips finished views (``overwrite`` recomputes them). Images are loaded per view and released.

Per view and pass the estimator writes, in COLMAP's format and naming:
``stereo/depth_maps/<image>.<pass>.bin``, ``stereo/normal_maps/...`` (camera-frame normals),
``stereo/cost_maps/...`` (final matching cost), ``stereo/visibility_maps/...`` (one channel per
source view, in the order of ``patch-match.cfg``: the view-selection weights), and PNG previews
under ``stereo/previews/``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from dvpmvs.fusion import FusionOptions, fuse, fuse_with_colmap, write_fused_cloud
from dvpmvs.maps import MapFormatError, Pass, map_path, read_depth_map, read_extra_map, read_map_header, \
    read_normal_map, write_depth_map, write_extra_map, write_normal_map
from dvpmvs.patchmatch import PatchMatchOptions, Problem, ViewData, estimate
from dvpmvs.preview import colorize_cost, colorize_depth, colorize_normals, write_png
from dvpmvs.priors import PriorContext, PriorProviders, compute_priors
from dvpmvs.segmentation import SegmentationOptions, colorize_labels, segment
from dvpmvs.workspace import View, Workspace

__all__ = ["DenseOptions", "ViewReport", "DenseSummary", "maps_complete", "compute_pass", "run_dense", "fuse_to_file", "print_summary",
           "FUSION_BACKENDS"]

log = logging.getLogger(__name__)

FUSION_BACKENDS = ("dvpmvs", "colmap")
_MAP_KINDS = ("visibility", "cost", "normal", "depth")  # write order: depth last marks completion


@dataclass(frozen=True)
class DenseOptions:
    """patch_match: estimator options. geometric: run the geometric-consistency pass.
    overwrite: recompute views whose maps exist. fusion / fusion_backend: how the maps are fused
    (``dvpmvs`` or ``colmap``); fuse=False stops after the maps. previews: write PNG previews.
    priors: the provider configs ``{"depth_prior": ..., "normal_prior": ..., "edge": ...}``;
    segmentation: the depth-normal-edge aligned prior's options, None to let deformable
    PatchMatch's anchors go anywhere (the paper's ``w/o Agn``)."""

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
        if self.fusion_backend not in FUSION_BACKENDS:
            raise ValueError(f"unknown fusion backend {self.fusion_backend!r}; choose {' or '.join(FUSION_BACKENDS)}")

    @property
    def final_pass(self) -> Pass:
        return Pass.GEOMETRIC if self.geometric else Pass.PHOTOMETRIC


@dataclass
class ViewReport:
    name: str
    pass_: Pass
    skipped: bool  # finished by an earlier run
    seconds: float = 0.0
    evaluations: int = 0
    prior_seconds: float = 0.0  # priors + segmentation (part of ``seconds``)
    valid_fraction: float = 0.0
    width: int = 0
    height: int = 0


@dataclass
class DenseSummary:
    reports: list[ViewReport]
    pass_seconds: dict[str, float]
    fusion_seconds: float = 0.0
    num_points: int = 0
    output: Path | None = None
    stereo_dir: Path | None = None

    def computed(self, pass_: Pass) -> list[ViewReport]:
        return [r for r in self.reports if r.pass_ is pass_ and not r.skipped]


def maps_complete(workspace: Workspace, view: View, pass_: Pass) -> bool:
    """True when every map of ``view`` for ``pass_`` exists, is a valid file and has the view's size."""
    for kind in _MAP_KINDS:
        try:
            width, height, _, _ = read_map_header(map_path(workspace.stereo_dir, view.name, kind, pass_))
        except MapFormatError:
            return False
        if (width, height) != (view.width, view.height):
            log.warning("the %s maps of %s are %dx%d, the view is %dx%d: recomputing", pass_.value, view.name,
                        width, height, view.width, view.height)
            return False
    return True


def _view_data(view: View, depth: np.ndarray | None = None, cost: np.ndarray | None = None) -> ViewData:
    return ViewData(view.name, view.load_grey(), view.K, view.R, view.t, depth, cost)


def _read_map_or(workspace: Workspace, view: View, kind: str, pass_: Pass, missing: float,
                 consequence: str) -> np.ndarray:
    """The view's one-channel ``kind`` map of ``pass_`` (H, W); where the view has none, ``missing``
    everywhere, with a warning that says the ``consequence``."""
    path = map_path(workspace.stereo_dir, view.name, kind, pass_)
    if not path.is_file():
        log.warning("source %s has no %s %s map; %s", view.name, pass_.value, kind, consequence)
        return np.full((view.height, view.width), missing, np.float32)
    data = read_depth_map(path) if kind == "depth" else read_extra_map(path)
    if data.shape[:2] != (view.height, view.width) or data.size != view.height * view.width:
        raise MapFormatError(f"{path} holds a {data.shape} map; the view needs ({view.height}, {view.width})")
    return data.reshape(view.height, view.width)


def _read_depth_or_empty(workspace: Workspace, view: View, pass_: Pass) -> np.ndarray:
    return _read_map_or(workspace, view, "depth", pass_, 0.0, "it gives no geometric constraint")


def _read_cost_or_unknown(workspace: Workspace, view: View, pass_: Pass) -> np.ndarray:
    """Infinite (unknown: never the lowest) where the view has no cost map."""
    return _read_map_or(workspace, view, "cost", pass_, np.inf, "its visibility is restored through its own depths")


def _problem(workspace: Workspace, view: View, pass_: Pass, options: PatchMatchOptions) -> Problem:
    names = view.sources[: options.max_sources]
    if pass_ is Pass.PHOTOMETRIC:
        return Problem(_view_data(view), [_view_data(workspace[n]) for n in names], view.depth_range)
    previous = Pass.PHOTOMETRIC
    initial = (_read_depth_or_empty(workspace, view, previous),
               read_normal_map(map_path(workspace.stereo_dir, view.name, "normal", previous)))
    restore = options.deformable and options.anchor_visibility and options.visibility_restore_radius > 0
    sources = [_view_data(workspace[n], _read_depth_or_empty(workspace, workspace[n], previous),
                          _read_cost_or_unknown(workspace, workspace[n], previous) if restore else None)
               for n in names]
    return Problem(_view_data(view), sources, view.depth_range, initial=initial)


def _uses_labels(options: DenseOptions) -> bool:
    return options.patch_match.deformable and options.segmentation is not None


def _labels(workspace: Workspace, view: View, problem: Problem, pass_: Pass, options: DenseOptions,
            providers: PriorProviders | None) -> tuple[np.ndarray, float]:
    """The view's region labels and the seconds spent: read back in the geometric pass (the
    photometric pass before it made them, also under ``overwrite``), else priors ->
    segmentation, saved as an extra map and a preview."""
    path = map_path(workspace.stereo_dir, view.name, "labels", Pass.PHOTOMETRIC)
    if pass_ is Pass.GEOMETRIC:
        try:
            labels = read_extra_map(path)
            if labels.shape == (view.height, view.width):
                return labels.astype(np.int32), 0.0
        except MapFormatError:
            pass
    start = time.perf_counter()
    ctx = PriorContext(view.name, problem.reference.image, view.K, view.depth_range,
                       workspace.sparse_points(view.name), rgb_loader=view.load_rgb, problem=problem,
                       options=options.patch_match, root=workspace.root)
    priors = compute_priors(ctx, providers)
    if priors.edges is None or priors.depth is None:
        raise ValueError("the aligned prior needs an edge detector and a depth prior; set edge= and depth_prior=, "
                         "or segmentation=null (ablation=w_o_agn) to deform without regions")
    result = segment(priors.edges, priors.depth, priors.normal, view.K, view.depth_range, options.segmentation,
                     priors.depth_valid, priors.normal_from_depth)
    write_extra_map(path, result.labels)
    if options.previews:
        folder = workspace.stereo_dir / "previews"
        write_png(folder / f"{view.name}.labels.png", colorize_labels(result.labels))
        write_png(folder / f"{view.name}.edges.png", (priors.edges * 255).astype(np.uint8))
        lo, hi = view.depth_range
        write_png(folder / f"{view.name}.depth_prior.png", colorize_depth(priors.depth, lo, hi))
        if priors.normal is not None:
            write_png(folder / f"{view.name}.normal_prior.png", colorize_normals(priors.normal))
    log.debug("view %s: %d regions, %d splits, %d merges, %d pixels filtered", view.name,
              int(result.labels.max()), result.splits, result.merges, result.filtered)
    return result.labels, time.perf_counter() - start


def _write_maps(workspace: Workspace, view: View, pass_: Pass, result, previews: bool) -> None:
    stereo = workspace.stereo_dir
    write_extra_map(map_path(stereo, view.name, "visibility", pass_), result.visibility)
    write_extra_map(map_path(stereo, view.name, "cost", pass_), result.cost)
    write_normal_map(map_path(stereo, view.name, "normal", pass_), result.normal)
    valid = result.depth[result.depth > 0]
    depth_range = (float(valid.min()), float(valid.max())) if valid.size else None
    write_depth_map(map_path(stereo, view.name, "depth", pass_), result.depth, depth_range)
    if previews:
        folder = stereo / "previews"
        lo, hi = view.depth_range
        write_png(folder / f"{view.name}.{pass_.value}.depth.png", colorize_depth(result.depth, lo, hi))
        write_png(folder / f"{view.name}.{pass_.value}.normal.png", colorize_normals(result.normal))
        write_png(folder / f"{view.name}.{pass_.value}.cost.png", colorize_cost(result.cost))


def compute_pass(workspace: Workspace, pass_: Pass, options: DenseOptions, progress: bool = True) -> list[ViewReport]:
    """Run one estimator pass over every reference view that has sources; returns one report per view."""
    from tqdm import tqdm

    pass_ = Pass(pass_)
    views = [v for v in workspace.reference_views() if v.sources]
    reports = []
    providers = PriorProviders.from_configs(options.priors) if _uses_labels(options) else None
    bar = tqdm(views, desc=f"{pass_.value} pass", unit="view", disable=not progress, dynamic_ncols=True)
    for view in bar:
        bar.set_postfix_str(view.name)
        if not options.overwrite and maps_complete(workspace, view, pass_):
            reports.append(ViewReport(view.name, pass_, skipped=True, width=view.width, height=view.height))
            continue
        # A per-view seed keeps views independent of the order they are computed in.
        pm = replace(options.patch_match, seed=options.patch_match.seed * 1_000_003 + view.image_id)
        problem = _problem(workspace, view, pass_, pm)
        prior_seconds = 0.0
        if _uses_labels(options):
            problem.labels, prior_seconds = _labels(workspace, view, problem, pass_, options, providers)
        with tqdm(total=1, desc=f"  {view.name}", unit="sweep", leave=False, disable=not progress,
                  dynamic_ncols=True) as inner:
            def on_sweep(done: int, total: int) -> None:
                inner.total = total
                inner.n = done
                inner.refresh()

            result = estimate(problem, pm, pass_, on_sweep=on_sweep)
        del problem  # release the images before writing
        _write_maps(workspace, view, pass_, result, options.previews)
        reports.append(ViewReport(view.name, pass_, skipped=False, seconds=result.seconds + prior_seconds,
                                  evaluations=result.hypothesis_evaluations, prior_seconds=prior_seconds,
                                  valid_fraction=float((result.depth > 0).mean()),
                                  width=view.width, height=view.height))
    return reports


def run_dense(workspace: Workspace, options: DenseOptions | None = None, output: str | Path | None = None,
              progress: bool = True) -> DenseSummary:
    """Every pass, then fusion into ``output`` (default ``WS/fused.ply``)."""
    options = options or DenseOptions()
    passes = [Pass.PHOTOMETRIC] + ([Pass.GEOMETRIC] if options.geometric else [])
    reports, pass_seconds = [], {}
    for pass_ in passes:
        start = time.perf_counter()
        reports += compute_pass(workspace, pass_, options, progress)
        pass_seconds[pass_.value] = time.perf_counter() - start
    summary = DenseSummary(reports, pass_seconds, stereo_dir=workspace.stereo_dir)
    if not options.fuse:
        return summary
    output = Path(output) if output is not None else workspace.root / "fused.ply"
    fusion = replace(options.fusion, input_type=options.final_pass.value)
    start = time.perf_counter()
    summary.num_points = fuse_to_file(workspace, fusion, options.fusion_backend, output, progress)
    summary.fusion_seconds = time.perf_counter() - start
    summary.output = output
    return summary


def fuse_to_file(workspace: Workspace, fusion: FusionOptions, backend: str, output: str | Path,
                 progress: bool = True) -> int:
    """Fuse the maps with ``backend`` (``dvpmvs`` or ``colmap``) into the PLY ``output``;
    returns the number of points."""
    from tqdm import tqdm

    if backend not in FUSION_BACKENDS:
        raise ValueError(f"unknown fusion backend {backend!r}; choose {' or '.join(FUSION_BACKENDS)}")
    if backend == "colmap":
        return fuse_with_colmap(workspace, output, fusion)
    views = workspace.reference_views()
    with tqdm(total=len(views), desc="fusion", unit="view", disable=not progress, dynamic_ncols=True) as bar:
        cloud = fuse(workspace, fusion, progress=lambda name: (bar.set_postfix_str(name), bar.update()))
    write_fused_cloud(output, cloud)
    return len(cloud)


def print_summary(summary: DenseSummary, console=None) -> None:
    """The closing table: per pass views computed/skipped, seconds per view, evaluation rate."""
    from rich.console import Console
    from rich.table import Table

    console = console or Console(stderr=True)
    table = Table(title="dvpmvs dense", title_justify="left")
    for column in ("stage", "views", "skipped", "s / view", "M hyp-evals / s", "valid px", "size"):
        table.add_column(column, justify="right")
    for pass_name, seconds in summary.pass_seconds.items():
        pass_ = Pass(pass_name)
        done = summary.computed(pass_)
        skipped = sum(1 for r in summary.reports if r.pass_ is pass_ and r.skipped)
        busy = sum(r.seconds for r in done)
        evals = sum(r.evaluations for r in done)
        sizes = sorted({f"{r.width}x{r.height}" for r in summary.reports if r.pass_ is pass_})
        table.add_row(pass_name, str(len(done)), str(skipped),
                      f"{seconds / len(done):.2f}" if done else "-",
                      f"{evals / busy / 1e6:.2f}" if busy > 0 else "-",
                      f"{np.mean([r.valid_fraction for r in done]) * 100:.1f} %" if done else "-",
                      ", ".join(sizes[:2]) + (" ..." if len(sizes) > 2 else ""))
    if summary.output is not None:
        table.add_row("fusion", "", "", "", "", f"{summary.num_points:,} pts", f"{summary.fusion_seconds:.1f} s")
    console.print(table)
    console.print(f"maps: {summary.stereo_dir}" + (f"\nfused cloud: {summary.output}" if summary.output else ""))
