"""One view's maps of one pass, the dense stage's main product: its problem (images, the
neighbours' maps in the geometric pass, the region labels), the estimator, the maps and their
previews written with their record."""

from __future__ import annotations

from dataclasses import asdict, replace
from pathlib import Path

from dvpmvs.dense.inputs import preview_files, regions_files, uses_labels
from dvpmvs.dense.masks import MaskStore
from dvpmvs.dense.problem import read_labels, view_problem
from dvpmvs.dense.products import Product
from dvpmvs.highlight import HighlightStage
from dvpmvs.maps import map_path, write_depth_map, write_extra_map, write_normal_map
from dvpmvs.options.dense import DenseOptions
from dvpmvs.passes import Pass
from dvpmvs.patchmatch import estimate
from dvpmvs.preview import colorize_cost, colorize_depth, colorize_normals, write_png
from dvpmvs.provenance import Record
from dvpmvs.view import View
from dvpmvs.workspace import Workspace

__all__ = ["compute_view_maps"]


def _write_maps(stereo: Path, view: View, pass_: Pass, result, previews: bool) -> None:
    write_extra_map(map_path(stereo, view.name, "visibility", pass_), result.visibility)
    write_extra_map(map_path(stereo, view.name, "cost", pass_), result.cost)
    write_normal_map(map_path(stereo, view.name, "normal", pass_), result.normal)
    valid = result.depth[result.depth > 0]
    depth_range = (float(valid.min()), float(valid.max())) if valid.size else None
    write_depth_map(map_path(stereo, view.name, "depth", pass_), result.depth, depth_range)
    if previews:
        files = preview_files(stereo, view.name, pass_)
        lo, hi = view.depth_range
        prefix = f"{view.name}.{pass_.value}"
        write_png(files[f"{prefix}.depth.png"], colorize_depth(result.depth, lo, hi))
        write_png(files[f"{prefix}.normal.png"], colorize_normals(result.normal))
        write_png(files[f"{prefix}.cost.png"], colorize_cost(result.cost))


def compute_view_maps(
    workspace: Workspace,
    stereo: Path,
    product: Product,
    options: DenseOptions,
    progress: bool,
    highlights: HighlightStage | None,
    masks: MaskStore,
) -> Record:
    """Make ``product``, a view's maps of a pass, from its images, its mask, its region labels
    and the highlight outputs (as stored by the products the plan makes first), and write them
    with their record; a pending record covers the work, so an interrupted view is made again.
    Returns the complete record."""
    from tqdm import tqdm

    view, pass_ = product.view, product.pass_
    with product.stored.making(options.overwrite):
        # A per-view seed keeps views independent of the order they are computed in.
        pm = replace(options.patch_match, seed=options.patch_match.seed * 1_000_003 + view.image_id)
        problem = view_problem(workspace, view, pass_, pm, stereo, highlights)
        problem.mask = masks.load(view)
        if uses_labels(options):
            problem.labels = read_labels(regions_files(stereo, view.name)["labels"], view)
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
    previews = preview_files(stereo, view.name, pass_)
    return product.stored.complete(
        product.files,
        {
            "seconds": result.seconds,
            "evaluations": result.hypothesis_evaluations,
            "work": [asdict(level) for level in result.work],
            "valid_fraction": float((result.depth > 0).mean()),
        },
        [p.relative_to(stereo).as_posix() for p in previews.values() if p.is_file()],
    )
