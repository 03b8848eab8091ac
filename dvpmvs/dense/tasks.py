"""The dense stage's tasks: each makes one product of the plan in whatever process runs it
(:mod:`dvpmvs.executor`: this one, or a Dask worker), from the run's state in that process."""

from __future__ import annotations

import time

from dvpmvs.dense.inputs import preview_files, uses_labels
from dvpmvs.dense.products import Product
from dvpmvs.dense.report import ViewReport, view_report
from dvpmvs.dense.state import RunSpec, run_state
from dvpmvs.dense.view_maps import compute_view_maps, read_depth_or_empty
from dvpmvs.passes import Pass
from dvpmvs.provenance import record_path, write_record

__all__ = ["make_mask", "make_view_maps", "make_highlights", "refine_highlights"]


def make_view_maps(spec: RunSpec, product: Product, progress: bool) -> ViewReport:
    """A view's maps of a pass: linked from the map cache where it holds them, else computed."""
    state = run_state(spec)
    options, stereo, cache = spec.options, spec.stereo, state.cache
    pass_ = product.pass_
    previews = (
        preview_files(stereo, product.view.name, pass_, uses_labels(options))
        if options.previews
        else {}
    )
    if cache is not None and not options.overwrite:
        record = cache.fetch(pass_.value, product.fingerprint, stereo, product.files, previews)
        if record is not None:
            write_record(record_path(stereo, product.view.name, pass_.value), record)
            return view_report(product, record, "cached")
    record = compute_view_maps(
        state.workspace,
        stereo,
        product,
        options,
        state.providers,
        progress,
        state.highlights,
        state.masks,
    )
    if cache is not None:
        cache.store(pass_.value, record, stereo, previews)
    return view_report(product, record, "computed")


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
