"""The dense stage's tasks: each makes one product of the plan in whatever process runs it
(:mod:`dvpmvs.executor`: this one, or a Dask worker), from the run's state in that process."""

from __future__ import annotations

import time
from collections.abc import Callable

from dvpmvs.dense.inputs import preview_files, regions_previews
from dvpmvs.dense.problem import read_depth_or_empty
from dvpmvs.dense.products import Product
from dvpmvs.dense.regions import compute_regions
from dvpmvs.dense.report import ViewReport, view_report
from dvpmvs.dense.state import RunSpec, run_state
from dvpmvs.dense.view_maps import compute_view_maps
from dvpmvs.passes import Pass
from dvpmvs.provenance import Record, record_path, write_record

__all__ = ["make_mask", "make_regions", "make_view_maps", "make_highlights", "refine_highlights"]


def _linked_or_made(
    spec: RunSpec, product: Product, previews: dict, make: Callable[[], Record]
) -> tuple[Record, str]:
    """``product`` linked from the map cache where it holds it (its record written), else made
    (``make()``: its complete record) and added to the cache; its record and what was done
    (``cached``, ``computed``)."""
    cache, stereo = run_state(spec).cache, spec.stereo
    previews = previews if spec.options.previews else {}
    if cache is not None and not spec.options.overwrite:
        record = cache.fetch(product.kind, product.fingerprint, stereo, product.files, previews)
        if record is not None:
            write_record(record_path(stereo, product.view.name, product.kind), record)
            return record, "cached"
    record = make()
    if cache is not None:
        cache.store(product.kind, record, stereo, previews)
    return record, "computed"


def make_view_maps(spec: RunSpec, product: Product, progress: bool) -> ViewReport:
    """A view's maps of a pass: linked from the map cache where it holds them, else computed."""
    state = run_state(spec)
    record, action = _linked_or_made(
        spec,
        product,
        preview_files(spec.stereo, product.view.name, product.pass_),
        lambda: compute_view_maps(
            state.workspace,
            spec.stereo,
            product,
            spec.options,
            progress,
            state.highlights,
            state.masks,
        ),
    )
    return view_report(product, record, action)


def make_regions(spec: RunSpec, product: Product) -> Record:
    """A view's region labels: linked from the map cache where they are, else computed; their
    record."""
    state = run_state(spec)
    return _linked_or_made(
        spec,
        product,
        regions_previews(spec.stereo, product.view.name),
        lambda: compute_regions(
            state.workspace, spec.stereo, product, spec.options, state.providers
        ),
    )[0]


def make_mask(spec: RunSpec, product: Product) -> float | None:
    """A view's mask, unless current; the seconds taken, None when reused. Its record is read
    again here: the run's check before compute (MaskStore.prepare) may have made it since."""
    store = run_state(spec).masks
    stored = store.check(product.view)
    if stored.current is not None:
        return None
    start = time.perf_counter()
    store.load(product.view, stored)
    return time.perf_counter() - start


def make_highlights(spec: RunSpec, product: Product) -> float | None:
    """A view's highlight outputs, unless current; the seconds taken, None when reused."""
    return run_state(spec).highlights.prepare_view(
        product.view.name, spec.options.overwrite, spec.options.previews, product.stored
    )


def refine_highlights(spec: RunSpec, product: Product, sources: tuple[str, ...]) -> float | None:
    """The multi-view refinement of a view's highlight outputs from the photometric maps of the
    view and its ``sources``, unless current."""
    state = run_state(spec)
    return state.highlights.refine_view(
        product.view.name,
        sources,
        product.inputs["photometric"],
        lambda n: read_depth_or_empty(spec.stereo, state.workspace[n], Pass.PHOTOMETRIC),
        spec.options.overwrite,
        spec.options.previews,
        product.stored,
    )
