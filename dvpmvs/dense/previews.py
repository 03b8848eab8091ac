"""The previews of reused products whose previews are missing (they came from a run with
``previews=false``), drawn from their files: a view's maps of a pass (depth, normal, cost) and its
region labels (the priors they were made from are not stored, so theirs are not drawn)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from dvpmvs.dense.inputs import preview_files, regions_previews
from dvpmvs.dense.products import REGIONS, Product
from dvpmvs.maps import MapFormatError, read_depth_map, read_extra_map, read_normal_map
from dvpmvs.preview import (
    colorize_cost,
    colorize_depth,
    colorize_labels,
    colorize_normals,
    write_png,
)

__all__ = ["write_missing_previews"]

log = logging.getLogger(__name__)


def _drawings(stereo: Path, product: Product) -> dict[Path, Callable[[], np.ndarray]]:
    """Preview path -> how to draw it from ``product``'s files."""
    view, files = product.view, product.files
    if product.kind == REGIONS:
        path = regions_previews(stereo, view.name)[f"{view.name}.labels.png"]
        return {path: lambda: colorize_labels(read_extra_map(files["labels"]).astype(np.int32))}
    previews = preview_files(stereo, view.name, product.pass_)
    prefix = f"{view.name}.{product.kind}"
    return {
        previews[f"{prefix}.depth.png"]: lambda: colorize_depth(
            read_depth_map(files["depth"]), *view.depth_range
        ),
        previews[f"{prefix}.normal.png"]: lambda: colorize_normals(
            read_normal_map(files["normal"])
        ),
        previews[f"{prefix}.cost.png"]: lambda: colorize_cost(read_extra_map(files["cost"])),
    }


def write_missing_previews(stereo: Path, products: Iterable[Product]) -> int:
    """Draw the missing previews of ``products`` (reused view maps and region labels) from their
    files. Returns how many were written."""
    written = 0
    for product in products:
        for path, draw in _drawings(stereo, product).items():
            if path.is_file():
                continue
            try:
                image = draw()
            except (OSError, MapFormatError) as exc:
                log.warning("no preview %s: %s", path, exc)
                continue
            write_png(path, image)
            written += 1
    return written
