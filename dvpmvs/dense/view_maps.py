"""One view's maps of one pass, the dense stage's main product: its problem (images, the
neighbours' maps in the geometric pass, priors and segmentation labels), the estimator, the maps
and their previews written with their record."""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, replace
from functools import partial
from pathlib import Path

import numpy as np

from dvpmvs.dense.inputs import preview_files, uses_labels
from dvpmvs.dense.masks import MaskStore
from dvpmvs.dense.products import Product
from dvpmvs.highlight import HighlightStage
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
from dvpmvs.options.dense import DenseOptions
from dvpmvs.passes import Pass
from dvpmvs.patchmatch import PatchMatchOptions, Problem, ViewData, estimate
from dvpmvs.patchmatch.low_resolution import low_resolution_depth
from dvpmvs.preview import (
    colorize_cost,
    colorize_depth,
    colorize_labels,
    colorize_normals,
    write_png,
)
from dvpmvs.priors import PriorContext, PriorProviders, compute_priors
from dvpmvs.provenance import Record
from dvpmvs.segmentation import segment
from dvpmvs.view import View
from dvpmvs.workspace import Workspace

__all__ = ["compute_view_maps", "read_depth_or_empty", "write_missing_previews"]

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


def read_depth_or_empty(stereo: Path, view: View, pass_: Pass) -> np.ndarray:
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
        read_depth_or_empty(stereo, view, previous),
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
            read_depth_or_empty(stereo, workspace[n], previous),
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
            previews = preview_files(stereo, view.name, pass_, True)
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
        files = preview_files(stereo, view.name, pass_, False)
        lo, hi = view.depth_range
        prefix = f"{view.name}.{pass_.value}"
        write_png(files[f"{prefix}.depth.png"], colorize_depth(result.depth, lo, hi))
        write_png(files[f"{prefix}.normal.png"], colorize_normals(result.normal))
        write_png(files[f"{prefix}.cost.png"], colorize_cost(result.cost))


def write_missing_previews(stereo: Path, products: list[Product], pass_: Pass) -> int:
    """The depth, normal and cost previews (and the labels' where their map is kept) of views
    whose maps were reused, where a file is missing (the maps came from a run with
    ``previews=false``), drawn from the maps on disk. Returns how many were written."""
    written = 0
    for product in products:
        view = product.view
        prefix = f"{view.name}.{pass_.value}"
        files = preview_files(stereo, view.name, pass_, True)
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
        if "labels" in product.files:
            makers[f"{view.name}.labels.png"] = lambda: colorize_labels(
                read_extra_map(product.files["labels"]).astype(np.int32)
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


def compute_view_maps(
    workspace: Workspace,
    stereo: Path,
    product: Product,
    options: DenseOptions,
    providers: PriorProviders | None,
    progress: bool,
    highlights: HighlightStage | None,
    masks: MaskStore,
) -> Record:
    """Make ``product``, a view's maps of a pass (priors and segmentation included), and write
    them with their record; a pending record covers the work, so an interrupted view is made
    again. Returns the complete record."""
    from tqdm import tqdm

    view, pass_ = product.view, product.pass_
    with product.stored.making(options.overwrite):
        # A per-view seed keeps views independent of the order they are computed in.
        pm = replace(options.patch_match, seed=options.patch_match.seed * 1_000_003 + view.image_id)
        problem = _problem(workspace, view, pass_, pm, stereo, highlights)
        problem.mask = masks.load(view)
        prior_seconds = 0.0
        if uses_labels(options):
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
    previews = preview_files(stereo, view.name, pass_, uses_labels(options))
    return product.stored.complete(
        product.files,
        {
            "seconds": result.seconds + prior_seconds,
            "prior_seconds": prior_seconds,
            "evaluations": result.hypothesis_evaluations,
            "work": [asdict(level) for level in result.work],
            "valid_fraction": float((result.depth > 0).mean()),
        },
        [p.relative_to(stereo).as_posix() for p in previews.values() if p.is_file()],
    )
