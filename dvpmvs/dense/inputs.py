"""What shapes a view's products, as the trees their fingerprints are taken of: the inputs of
a view's maps of a pass (:func:`pass_inputs`), and the files a pass writes for it (maps,
previews)."""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path

import numpy as np

from dvpmvs.digests import file_digest
from dvpmvs.maps import map_path
from dvpmvs.options.dense import DenseOptions
from dvpmvs.passes import Pass
from dvpmvs.priors import PriorProviders
from dvpmvs.provenance import code_identity
from dvpmvs.view import View
from dvpmvs.workspace import Workspace

__all__ = [
    "PASS_MAPS",
    "GEOMETRIC_ONLY_OPTIONS",
    "uses_labels",
    "view_sources",
    "pass_inputs",
    "map_files",
    "preview_files",
]

# The maps a pass writes per view, in their write order (depth last: a view with a depth map has
# the others).
PASS_MAPS = ("visibility", "cost", "normal", "depth")

# Estimator options the photometric pass never reads (tests check its maps do not move with
# them), so that runs differing only in these share their photometric maps.
GEOMETRIC_ONLY_OPTIONS = frozenset(
    {
        "geom_iterations",
        "geom_weight",
        "geom_max_error",
        "geom_deformable",
        "visibility_restoration",
        "highlight_multiview",
    }
)
# Options that change how fast outputs are made, never what they hold.
SPEED_ONLY_OPTIONS = frozenset({"num_threads"})


def uses_labels(options: DenseOptions) -> bool:
    return options.patch_match.deformable and options.segmentation is not None


def _camera(view: View) -> dict:
    return {
        "name": view.name,
        "image": file_digest(view.path),
        "size": [view.width, view.height],
        "K": view.K,
        "R": view.R,
        "t": view.t,
    }


def view_sources(view: View, options: DenseOptions) -> tuple[str, ...]:
    return view.sources[: options.patch_match.max_sources]


def pass_inputs(
    workspace: Workspace,
    view: View,
    pass_: Pass,
    options: DenseOptions,
    providers: PriorProviders | None,
    photometric: dict[str, str | None],
    highlights: Mapping[str, str] | None = None,
    masks: Mapping[str, str] | None = None,
) -> dict:
    """Everything that shapes ``view``'s maps of ``pass_``, as a tree for :func:`fingerprint`:
    the code, the pass's estimator options, the reference's and the sources' images (digests),
    calibration and the reference's depth range; for the photometric pass with the sparse seeding
    the sparse points that seed it, and with the aligned prior its providers (configs, plugins, the
    files they read) and segmentation options and the sparse points they align to; for the
    geometric pass the fingerprints of the photometric maps it reads (``photometric``: view name
    -> fingerprint, None for none); with highlight perception the fingerprints of the reference's
    and the sources' highlight outputs the pass reads (``highlights``: view name -> fingerprint;
    in a geometric pass with the multi-view refinement, the refined ones'); with ``options.mask``,
    the fingerprint of the reference's mask (``masks``: view name -> fingerprint)."""
    pm = {
        key: value
        for key, value in options.patch_match.as_dict().items()
        if key not in SPEED_ONLY_OPTIONS
        and not (pass_ is Pass.PHOTOMETRIC and key in GEOMETRIC_ONLY_OPTIONS)
    }
    sources = view_sources(view, options)
    inputs = {
        "pass": pass_.value,
        "code": code_identity(),
        "patch_match": pm,
        "reference": {
            **_camera(view),
            "image_id": view.image_id,
            "depth_range": list(view.depth_range),
        },
        "sources": [_camera(workspace[name]) for name in sources],
    }
    if options.patch_match.sparse_seed and pass_ is Pass.PHOTOMETRIC:
        seeds = np.ascontiguousarray(workspace.observed_points(view.name), np.float64)
        inputs["sparse_seed_points"] = hashlib.sha256(seeds.tobytes()).hexdigest()
    if uses_labels(options) and pass_ is Pass.PHOTOMETRIC:
        sparse = np.ascontiguousarray(workspace.sparse_points(view.name), np.float64)
        inputs["aligned_prior"] = {
            "segmentation": asdict(options.segmentation),
            "providers": providers.provenance(view.name, workspace.root)
            if providers is not None
            else None,
            "sparse_points": hashlib.sha256(sparse.tobytes()).hexdigest(),
        }
    if options.mask is not None:
        if masks is None:
            raise ValueError(
                "pass_inputs needs the fingerprints of the views' masks (masks=) with options.mask"
            )
        inputs["mask"] = masks[view.name]
    if pass_ is Pass.GEOMETRIC:
        inputs["photometric"] = {name: photometric.get(name) for name in (view.name, *sources)}
    if highlights is not None:
        inputs["highlights"] = {name: highlights[name] for name in (view.name, *sources)}
    return inputs


def map_files(stereo: Path, view_name: str, pass_: Pass, labels: bool) -> dict[str, Path]:
    """The map files a pass writes for a view (labels: the photometric pass's region labels)."""
    kinds = (("labels",) if labels and pass_ is Pass.PHOTOMETRIC else ()) + PASS_MAPS
    return {kind: map_path(stereo, view_name, kind, pass_) for kind in kinds}


def preview_files(stereo: Path, view_name: str, pass_: Pass, labels: bool) -> dict[str, Path]:
    folder = stereo / "previews"
    names = [f"{view_name}.{pass_.value}.{kind}.png" for kind in ("depth", "normal", "cost")]
    if labels and pass_ is Pass.PHOTOMETRIC:
        names += [
            f"{view_name}.{kind}.png" for kind in ("labels", "edges", "depth_prior", "normal_prior")
        ]
    return {name: folder / name for name in names}
