"""The dense stage's plan: the graph of a run's stored products, built once before anything is
computed. Per reference view with sources: its mask (with a mask provider), the highlight
outputs its maps read (with a highlight provider: single-view, and refined from the photometric
maps), its region labels (with the aligned prior: :func:`~dvpmvs.dense.inputs.regions_inputs`),
and its maps of each pass (:func:`~dvpmvs.dense.inputs.pass_inputs`, which names the
fingerprints of the products they read); per product what the run finds on disk
(:class:`~dvpmvs.provenance.Status`), so whether it computes, reuses or refuses; and the task
graph that makes the rest (:meth:`DensePlan.tasks`, which :mod:`dvpmvs.executor` runs)."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, replace
from pathlib import Path

from dvpmvs.dense.cloud import PlannedCloud, plan_cloud
from dvpmvs.dense.inputs import (
    map_files,
    pass_inputs,
    regions_files,
    regions_inputs,
    uses_labels,
    view_sources,
)
from dvpmvs.dense.masks import mask_path
from dvpmvs.dense.products import (
    HIGHLIGHTS,
    MASK,
    REFINED_HIGHLIGHTS,
    REGIONS,
    Product,
    product_key,
)
from dvpmvs.dense.report import DenseError
from dvpmvs.dense.state import RunSpec, RunState
from dvpmvs.dense.tasks import (
    make_highlights,
    make_mask,
    make_regions,
    make_view_maps,
    refine_highlights,
)
from dvpmvs.digests import differences
from dvpmvs.executor import Task
from dvpmvs.options.dense import DenseOptions
from dvpmvs.passes import Pass
from dvpmvs.provenance import CachedOutput, Status
from dvpmvs.workspace import Workspace

__all__ = ["DensePlan", "plan_dense"]


@dataclass
class DensePlan:
    """A run's products: per pass the views' maps (in the workspace's order), the single-view
    highlight outputs some wanted maps read (by view), the refined ones with the sources they
    are refined from (by view), the masks of the views whose maps are made (by view), and the
    region labels of every view with maps (by view; none without the aligned prior), which the
    run makes where they are not current and the view's maps are made; and the fused cloud of the
    last pass's maps, which the run makes after them."""

    passes: dict[Pass, list[Product]]
    highlights: dict[str, Product]
    refined: dict[str, tuple[Product, tuple[str, ...]]]
    overwrite: bool
    masks: dict[str, Product]
    regions: dict[str, Product]
    cloud: PlannedCloud | None = None  # with fusion

    def wanted(self, pass_: Pass) -> list[Product]:
        """The view maps of ``pass_`` this run makes."""
        return [p for p in self.passes.get(pass_, []) if p.wanted(self.overwrite)]

    def read_regions(self) -> list[Product]:
        """The region labels the maps this run makes read."""
        views = {p.view.name for pass_ in self.passes for p in self.wanted(pass_)}
        return [p for name, p in self.regions.items() if name in views]

    def wanted_regions(self) -> list[Product]:
        """The region labels this run makes: those its maps read that are not current."""
        return [p for p in self.read_regions() if p.wanted(self.overwrite)]

    def explain(self) -> list[str]:
        """A line per pass (and for the region labels, before them): how many views it computes
        and why."""
        read = self.read_regions()
        lines = [_explain(read, "region labels", "labels", self.overwrite)] if read else []
        lines += [
            _explain(products, f"{pass_.value} pass", "maps", self.overwrite)
            for pass_, products in self.passes.items()
        ]
        return lines + ([self.cloud.explain(self.overwrite)] if self.cloud is not None else [])

    def refuse_foreign(self, stereo: Path) -> None:
        """Stop, before anything is written, where maps or a cloud without a record (COLMAP's, an
        older dvpmvs's) would be overwritten."""
        products = [p for products in self.passes.values() for p in products]
        _refuse_foreign(products + self.wanted_regions(), stereo)
        if self.cloud is not None and self.cloud.stored.state is Status.FOREIGN:
            raise DenseError(
                f"{self.cloud.output} exists and carries no dvpmvs provenance record (written by "
                f"COLMAP or an older dvpmvs); dvpmvs does not overwrite it unasked: rerun with "
                f"overwrite=true, or give another output=PATH or out=DIR"
            )

    def tasks(self, spec: RunSpec, progress: bool) -> list[Task]:
        """The tasks that make the products a run makes (the others' files are read as they
        are), each after the tasks whose products it reads: the masks, the highlight outputs, the
        region labels, the photometric maps, the multi-view refinement of the highlights, the
        geometric maps. A current mask is kept even with ``overwrite`` (it is the provider's, not
        the method's)."""
        overwrite = self.overwrite
        tasks = [
            Task(p.key, "masks", make_mask, (spec, p))
            for p in self.masks.values()
            if not p.status.reusable
        ]
        tasks += [
            Task(p.key, "highlights", make_highlights, (spec, p))
            for p in self.highlights.values()
            if p.wanted(overwrite)
        ]
        tasks += [
            Task(p.key, "region labels", make_regions, (spec, p)) for p in self.wanted_regions()
        ]
        tasks += [
            Task(p.key, "photometric pass", make_view_maps, (spec, p, progress), p.after)
            for p in self.wanted(Pass.PHOTOMETRIC)
        ]
        tasks += [
            Task(p.key, "highlights (multi-view)", refine_highlights, (spec, p, sources), p.after)
            for p, sources in self.refined.values()
            if p.wanted(overwrite)
        ]
        tasks += [
            Task(p.key, "geometric pass", make_view_maps, (spec, p, progress), p.after)
            for p in self.wanted(Pass.GEOMETRIC)
        ]
        return tasks


def plan_dense(
    workspace: Workspace,
    stereo: Path,
    options: DenseOptions,
    state: RunState,
    output: Path | None = None,
) -> DensePlan:
    """Every product of a run over ``workspace`` writing to ``stereo`` (and with
    ``options.fuse`` its cloud to ``output``), checked against the records on disk; ``state``:
    the run's providers (priors, highlights, masks). Each product's fingerprint is taken once:
    the maps' inputs name those of the products they read, the cloud's those of the maps."""
    highlights = state.highlights
    multiview = (
        highlights is not None and options.geometric and options.patch_match.highlight_multiview
    )
    computed = [view for view in workspace.reference_views() if view.sources]
    reads = {view.name: (view.name, *view_sources(view, options)) for view in computed}
    read = list(dict.fromkeys(n for names in reads.values() for n in names))
    masks = {
        view.name: Product(
            MASK, view, state.masks.check(view), {"mask": mask_path(stereo, view.name)}
        )
        for view in (computed if state.masks.active else ())
    }
    regions = {
        view.name: Product(
            REGIONS,
            view,
            CachedOutput.of_view(
                stereo,
                view.name,
                REGIONS,
                regions_inputs(workspace, view, options, state.providers),
                regions_files(stereo, view.name),
            ),
            regions_files(stereo, view.name),
        )
        for view in (computed if uses_labels(options) else ())
    }
    single: dict[str, Product] = {}
    if highlights is not None:
        for name in read:
            single[name] = Product(
                HIGHLIGHTS, workspace[name], highlights.check(name), highlights.files(name)
            )
    passes: dict[Pass, list[Product]] = {}
    refined: dict[str, tuple[Product, tuple[str, ...]]] = {}
    upstream: dict[str, str | None] = {}  # the fingerprints of the pass before
    for pass_ in options.passes:
        if pass_ is Pass.GEOMETRIC and multiview:
            for name in read:
                sources = view_sources(workspace[name], options)
                product = Product(
                    REFINED_HIGHLIGHTS,
                    workspace[name],
                    highlights.check_refined(name, sources, upstream),
                    highlights.refined_files(name),
                    tuple(
                        product_key(kind, n)
                        for n in (name, *sources)
                        for kind in (HIGHLIGHTS, Pass.PHOTOMETRIC.value)
                    ),
                )
                refined[name] = (product, sources)
        # What each view's maps read: its mask, its region labels, the highlight outputs of the
        # view and its sources (refined in the geometric pass with the multi-view refinement),
        # and in the geometric pass their photometric maps.
        read_highlights = {n: p for n, (p, _) in refined.items()} if refined else single
        kinds = (Pass.PHOTOMETRIC.value,) if pass_ is Pass.GEOMETRIC else ()
        kinds += (REFINED_HIGHLIGHTS if refined else HIGHLIGHTS,) if highlights else ()
        passes[pass_] = []
        for view in computed:
            inputs = pass_inputs(
                workspace,
                view,
                pass_,
                options,
                upstream,
                {n: p.fingerprint for n, p in read_highlights.items()} if highlights else None,
                {n: p.fingerprint for n, p in masks.items()} if masks else None,
                {n: p.fingerprint for n, p in regions.items()} if regions else None,
            )
            files = map_files(stereo, view.name, pass_)
            stored = CachedOutput.of_view(stereo, view.name, pass_.value, inputs, files)
            after = (product_key(MASK, view.name),) if masks else ()
            after += (product_key(REGIONS, view.name),) if regions else ()
            after += tuple(product_key(kind, n) for n in reads[view.name] for kind in kinds)
            passes[pass_].append(Product(pass_.value, view, stored, files, after))
        upstream = {p.view.name: p.fingerprint for p in passes[pass_]}
    # What the run makes: the maps that are not current, the masks, region labels and highlight
    # outputs they read, and what the refinement of those reads.
    wanted = [p for pass_ in options.passes for p in passes[pass_] if p.wanted(options.overwrite)]
    refine = [n for p in wanted if p.kind == Pass.GEOMETRIC.value for n in reads[p.view.name]]
    refine = list(dict.fromkeys(refine)) if multiview else []
    needed = [n for p in wanted for n in reads[p.view.name]]
    needed += [n for name in refine for n in (name, *refined[name][1])]
    cloud = None
    if options.fuse and output is not None and passes[options.final_pass]:
        # The run's masks are fusion's: never estimated, never fused.
        fusion = replace(options.fusion, input_type=options.final_pass.value, mask=options.mask)
        maps = {p.view.name: p.fingerprint for p in passes[options.final_pass]}
        views = workspace.fusion_views(stereo)
        cloud = plan_cloud(
            workspace, stereo, fusion, options.fusion_backend, output, state.masks, views, maps
        )
    return DensePlan(
        passes,
        {n: single[n] for n in dict.fromkeys(needed)} if highlights else {},
        {n: refined[n] for n in refine},
        options.overwrite,
        {n: masks[n] for n in dict.fromkeys(p.view.name for p in wanted) if n in masks},
        regions,
        cloud,
    )


def _short(value) -> str:
    text = str(value)
    return text if len(text) <= 24 else text[:21] + "..."


def _explain(products: list[Product], what: str, outputs: str, overwrite: bool) -> str:
    """One line: how many views ``what`` (a pass, the region labels) computes and why;
    ``outputs``: what it makes per view."""
    total = len(products)
    if overwrite:
        return f"{what}: computing all {total} views (overwrite=true)"
    todo = [p for p in products if not p.status.reusable]
    if not todo:
        return f"{what}: the {outputs} of all {total} views are current (same inputs): reused"
    counts: dict[Status, int] = {}
    for product in todo:
        counts[product.status] = counts.get(product.status, 0) + 1
    parts = []
    if Status.STALE in counts:
        changed: dict[str, str] = {}
        for product in todo:
            if product.status is Status.STALE:
                for key, old, new in differences(product.record.inputs, product.inputs):
                    if key.startswith("photometric."):  # one entry, not a digest per source
                        changed.setdefault("photometric", "the photometric maps they read")
                    else:
                        changed.setdefault(key, f"{key}: {_short(old)} -> {_short(new)}")
        shown = list(changed.values())[:3]
        more = f", +{len(changed) - 3} more" if len(changed) > 3 else ""
        parts.append(f"{counts[Status.STALE]} made from other inputs ({'; '.join(shown)}{more})")
    wording = {
        Status.MISSING: "not computed yet",
        Status.INTERRUPTED: "interrupted",
        Status.MODIFIED: "changed on disk since they were written",
        Status.FOREIGN: "without a record",
    }
    parts += [f"{counts[s]} {text}" for s, text in wording.items() if s in counts]
    reused = total - len(todo)
    return (
        f"{what}: computing {len(todo)} of {total} views"
        + (f" ({reused} current, reused)" if reused else "")
        + ": "
        + ", ".join(parts)
    )


def _refuse_foreign(products: Iterable[Product], stereo: Path) -> None:
    foreign = [p for p in products if p.status is Status.FOREIGN]
    if not foreign:
        return
    first = foreign[0]
    example = next(
        p
        for kind, p in sorted(first.files.items(), key=lambda item: item[0] != "depth")
        if p.exists()
    )
    raise DenseError(
        f"{stereo} holds maps that carry no dvpmvs provenance record ({len(foreign)} view pass(es), e.g. "
        f"{example}): written by COLMAP or by an older dvpmvs, so dvpmvs can neither reuse them nor tell "
        f"what made them. It does not overwrite them unasked: rerun with overwrite=true to replace them, or "
        f"with out=DIR to write this run's maps and cloud elsewhere"
    )
