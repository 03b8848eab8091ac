"""One view's region labels, the aligned prior's product (paper Sec. 3.2): the view's priors
(edges, depth, normals; :mod:`dvpmvs.priors`) segmented into regions (:mod:`dvpmvs.segmentation`),
stored as an extra map beside the photometric maps with its record, and read back by both passes
of the view's maps (the deformable matching keeps its anchors inside the reference's region)."""

from __future__ import annotations

import logging
import time
from functools import partial
from pathlib import Path

import numpy as np

from dvpmvs.dense.inputs import regions_previews
from dvpmvs.dense.problem import view_problem
from dvpmvs.dense.products import Product
from dvpmvs.maps import write_extra_map
from dvpmvs.options.dense import DenseOptions
from dvpmvs.passes import Pass
from dvpmvs.patchmatch.low_resolution import low_resolution_depth
from dvpmvs.preview import colorize_depth, colorize_labels, colorize_normals, write_png
from dvpmvs.priors import PriorContext, PriorProviders, compute_priors
from dvpmvs.provenance import Record
from dvpmvs.segmentation import segment
from dvpmvs.workspace import Workspace

__all__ = ["compute_regions"]

log = logging.getLogger(__name__)


def compute_regions(
    workspace: Workspace,
    stereo: Path,
    product: Product,
    options: DenseOptions,
    providers: PriorProviders | None,
) -> Record:
    """Make ``product``, a view's region labels, and write them (and with ``options.previews``
    the previews of the labels and of the priors) with their record. Returns the complete
    record; its stats hold the seconds and the segmentation's counts."""
    view = product.view
    start = time.perf_counter()
    with product.stored.making(options.overwrite):
        problem = view_problem(workspace, view, Pass.PHOTOMETRIC, options.patch_match, stereo)
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
                "the aligned prior needs an edge detector and a depth prior; set edge= and "
                "depth_prior=, or segmentation=null (method=w_o_agn) to deform without regions"
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
        del problem  # release the images before writing
        write_extra_map(product.files["labels"], result.labels)
        previews = regions_previews(stereo, view.name)
        if options.previews:
            write_png(previews[f"{view.name}.labels.png"], colorize_labels(result.labels))
            write_png(previews[f"{view.name}.edges.png"], (priors.edges * 255).astype(np.uint8))
            write_png(
                previews[f"{view.name}.depth_prior.png"],
                colorize_depth(priors.depth, *view.depth_range),
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
    return product.stored.complete(
        product.files,
        {
            "seconds": time.perf_counter() - start,
            "regions": int(result.labels.max()),
            "splits": result.splits,
            "merges": result.merges,
            "filtered": result.filtered,
        },
        [p.relative_to(stereo).as_posix() for p in previews.values() if p.is_file()],
    )
