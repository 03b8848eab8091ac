"""What shapes a view's products, as the trees their fingerprints are taken of: the inputs of
a view's region labels (:func:`regions_inputs`) and of its maps of a pass (:func:`pass_inputs`),
and the files each writes (maps, previews)."""

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
    "regions_inputs",
    "pass_inputs",
    "map_files",
    "preview_files",
    "regions_files",
    "regions_previews",
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


def _estimator_inputs(workspace: Workspace, view: View, pass_: Pass, options: DenseOptions) -> dict:
    """The code, the estimator options ``pass_`` reads, the reference's and the sources' images
    (digests) and calibration, the reference's depth range and, for the photometric pass with
    the sparse seeding, the sparse points that seed it."""
    pm = {
        key: value
        for key, value in options.patch_match.as_dict().items()
        if key not in SPEED_ONLY_OPTIONS
        and not (pass_ is Pass.PHOTOMETRIC and key in GEOMETRIC_ONLY_OPTIONS)
    }
    inputs = {
        "pass": pass_.value,
        "code": code_identity(),
        "patch_match": pm,
        "reference": {
            **_camera(view),
            "image_id": view.image_id,
            "depth_range": list(view.depth_range),
        },
        "sources": [_camera(workspace[name]) for name in view_sources(view, options)],
    }
    if options.patch_match.sparse_seed and pass_ is Pass.PHOTOMETRIC:
        seeds = np.ascontiguousarray(workspace.observed_points(view.name), np.float64)
        inputs["sparse_seed_points"] = hashlib.sha256(seeds.tobytes()).hexdigest()
    return inputs


def regions_inputs(
    workspace: Workspace, view: View, options: DenseOptions, providers: PriorProviders | None
) -> dict:
    """Everything that shapes ``view``'s region labels (the aligned prior: priors, then
    segmentation), as a tree for :func:`fingerprint`: what shapes its photometric maps but the
    masks and highlights (a depth prior may run the estimator at low resolution on the view and
    its sources, ``coarse_mvs``), the prior providers (configs, plugins, the files they read), the
    segmentation options and the sparse points the priors align to."""
    inputs = _estimator_inputs(workspace, view, Pass.PHOTOMETRIC, options)
    inputs["pass"] = "regions"
    sparse = np.ascontiguousarray(workspace.sparse_points(view.name), np.float64)
    inputs["aligned_prior"] = {
        "segmentation": asdict(options.segmentation),
        "providers": providers.provenance(view.name, workspace.root)
        if providers is not None
        else None,
        "sparse_points": hashlib.sha256(sparse.tobytes()).hexdigest(),
    }
    return inputs


def pass_inputs(
    workspace: Workspace,
    view: View,
    pass_: Pass,
    options: DenseOptions,
    photometric: dict[str, str | None],
    highlights: Mapping[str, str] | None = None,
    masks: Mapping[str, str] | None = None,
    regions: Mapping[str, str] | None = None,
) -> dict:
    """Everything that shapes ``view``'s maps of ``pass_``, as a tree for :func:`fingerprint`:
    the code, the pass's estimator options, the reference's and the sources' images (digests),
    calibration and the reference's depth range; for the photometric pass with the sparse seeding
    the sparse points that seed it; for the geometric pass the fingerprints of the photometric
    maps it reads (``photometric``: view name -> fingerprint, None for none); with highlight
    perception the fingerprints of the reference's and the sources' highlight outputs the pass
    reads (``highlights``: view name -> fingerprint; in a geometric pass with the multi-view
    refinement, the refined ones'); with ``options.mask``, the fingerprint of the reference's mask
    (``masks``: view name -> fingerprint); with the aligned prior, the fingerprint of the
    reference's region labels (``regions``: view name -> fingerprint), which both passes read."""
    inputs = _estimator_inputs(workspace, view, pass_, options)
    for key, given, used in (
        ("mask", masks, options.mask is not None),
        ("regions", regions, uses_labels(options)),
    ):
        if used:
            if given is None:
                raise ValueError(f"pass_inputs needs the fingerprints of the views' {key} ({key}=)")
            inputs[key] = given[view.name]
    if pass_ is Pass.GEOMETRIC:
        names = (view.name, *view_sources(view, options))
        inputs["photometric"] = {name: photometric.get(name) for name in names}
    if highlights is not None:
        inputs["highlights"] = {
            name: highlights[name] for name in (view.name, *view_sources(view, options))
        }
    return inputs


def map_files(stereo: Path, view_name: str, pass_: Pass) -> dict[str, Path]:
    """The map files a pass writes for a view."""
    return {kind: map_path(stereo, view_name, kind, pass_) for kind in PASS_MAPS}


def preview_files(stereo: Path, view_name: str, pass_: Pass) -> dict[str, Path]:
    """The previews of a view's maps of a pass."""
    folder = stereo / "previews"
    names = [f"{view_name}.{pass_.value}.{kind}.png" for kind in ("depth", "normal", "cost")]
    return {name: folder / name for name in names}


def regions_files(stereo: Path, view_name: str) -> dict[str, Path]:
    """The region labels' map of a view (beside the photometric maps: they are read with them)."""
    return {"labels": map_path(stereo, view_name, "labels", Pass.PHOTOMETRIC)}


def regions_previews(stereo: Path, view_name: str) -> dict[str, Path]:
    """The previews of a view's region labels and of the priors they are made from."""
    folder = stereo / "previews"
    names = [
        f"{view_name}.{kind}.png" for kind in ("labels", "edges", "depth_prior", "normal_prior")
    ]
    return {name: folder / name for name in names}
