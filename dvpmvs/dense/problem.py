"""What a view's estimate reads, from the products the plan makes before it: the estimator's
problem of a view in a pass (its images with their highlight outputs, in the geometric pass the
neighbours' photometric maps) and its stored region labels."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from dvpmvs.highlight import HighlightStage
from dvpmvs.maps import MapFormatError, map_path, read_depth_map, read_extra_map, read_normal_map
from dvpmvs.passes import Pass
from dvpmvs.patchmatch import PatchMatchOptions, Problem, ViewData
from dvpmvs.view import View
from dvpmvs.workspace import Workspace

__all__ = ["view_problem", "read_depth_or_empty", "read_labels"]

log = logging.getLogger(__name__)


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


def view_problem(
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


def read_labels(path: Path, view: View) -> np.ndarray:
    """The region labels stored at ``path`` for ``view`` (H, W) int32; a map of another size
    is named (:class:`~dvpmvs.maps.MapFormatError`)."""
    labels = read_extra_map(path)
    if labels.shape != (view.height, view.width):
        raise MapFormatError(
            f"{path} holds {labels.shape} region labels; the view needs ({view.height}, "
            f"{view.width}): remove it and rerun to make them again"
        )
    return labels.astype(np.int32)
