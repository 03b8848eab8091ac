"""The dense stage's plan: its options, what shapes a view's maps of a pass (the inputs whose
fingerprint its record carries), the files it writes, and per view and pass what a run finds on
disk (:class:`~dvpmvs.provenance.Status`) and so whether it computes, reuses or refuses; the
reports of a run."""

from __future__ import annotations

import hashlib
import logging
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from dvpmvs.digests import differences, file_digest, fingerprint
from dvpmvs.errors import DvpmvsError
from dvpmvs.highlight import HighlightStage
from dvpmvs.maps import map_path
from dvpmvs.masks import ViewMasks
from dvpmvs.options.dense import DenseOptions
from dvpmvs.passes import Pass
from dvpmvs.patchmatch.problem import pooled_work
from dvpmvs.priors import PriorProviders
from dvpmvs.provenance import Record, Status, code_identity, read_record, record_path, status
from dvpmvs.view import View
from dvpmvs.workspace import Workspace

log = logging.getLogger(__name__)

_MAP_KINDS = ("visibility", "cost", "normal", "depth")  # write order: depth last

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
_SPEED_ONLY_OPTIONS = frozenset({"num_threads"})
# Fusion options that never change a cloud's points: the cloud's record lists the views fused
# without maps, and a missing view stops the run unless allowed, whatever the record says.
_SPEED_ONLY_FUSION_OPTIONS = frozenset({"num_threads", "cache_views", "allow_missing"})


class DenseError(DvpmvsError, RuntimeError):
    """The dense stage cannot run as asked (for example, the output folder holds maps that dvpmvs
    did not write); the message says what to do."""


@dataclass
class ViewReport:
    """One view's maps of one pass. ``status``: what the run found (:class:`Status`);
    ``action``: ``computed``, ``reused`` (current maps in place) or ``cached`` (linked from the
    map cache). The figures are those of the computation that made the maps, in this run or an
    earlier one (from their record)."""

    name: str
    pass_: Pass
    status: Status = Status.MISSING
    action: str = "computed"
    seconds: float = 0.0
    evaluations: int = 0
    prior_seconds: float = 0.0  # priors + segmentation (part of ``seconds``)
    valid_fraction: float = 0.0
    width: int = 0
    height: int = 0
    fingerprint: str = ""
    work: list[dict] = field(default_factory=list)  # per pyramid level: what the estimator matched

    @property
    def skipped(self) -> bool:
        """Not computed by this run."""
        return self.action != "computed"

    def as_dict(self) -> dict:
        return {
            "name": self.name,
            "pass": self.pass_.value,
            "status": self.status.value,
            "action": self.action,
            "seconds": self.seconds,
            "evaluations": self.evaluations,
            "prior_seconds": self.prior_seconds,
            "valid_fraction": self.valid_fraction,
            "size": [self.width, self.height],
            "fingerprint": self.fingerprint,
            "work": self.work,
        }


@dataclass
class DenseSummary:
    """A run's reports. ``pass_seconds``: per pass, the seconds its tasks took (one after another
    with the local executor: the pass's wall time; on a cluster the sum over the workers);
    ``wall_seconds``: the tasks' wall time, all passes."""

    reports: list[ViewReport]
    pass_seconds: dict[str, float]
    fusion_seconds: float = 0.0
    num_points: int = 0
    output: Path | None = None
    stereo_dir: Path | None = None
    fusion_reused: bool = False
    fusion_fingerprint: str = ""
    highlight_seconds: dict[str, float] = field(
        default_factory=dict
    )  # per view the highlight stage computed
    wall_seconds: float = 0.0
    fusion_views_without_maps: list[str] = field(
        default_factory=list
    )  # a partial cloud (allow_missing)

    def computed(self, pass_: Pass) -> list[ViewReport]:
        return [r for r in self.reports if r.pass_ is pass_ and not r.skipped]

    def of_pass(self, pass_: Pass) -> list[ViewReport]:
        return [r for r in self.reports if r.pass_ is pass_]

    def seconds_per_view(self) -> float:
        """The cost of the maps and the cloud per reference view: every pass's per-view seconds
        (priors included, from the records of reused maps) and fusion, over the views."""
        views = {r.name for r in self.reports}
        return (sum(r.seconds for r in self.reports) + self.fusion_seconds) / max(len(views), 1)

    def work_per_pixel(self, pass_: Pass) -> list[dict]:
        """Per pyramid level of ``pass_``, the hypotheses, windows and samples the estimator
        matched per pixel of that level, over the views whose maps this run has (computed here or,
        from their records, earlier); the level's size is the first view's."""
        return pooled_work(level for report in self.of_pass(pass_) for level in report.work)

    def as_dict(self) -> dict:
        passes = {}
        for pass_value, seconds in self.pass_seconds.items():
            reports = self.of_pass(Pass(pass_value))
            passes[pass_value] = {
                "task_seconds": seconds,
                "views": len(reports),
                "computed": sum(r.action == "computed" for r in reports),
                "reused": sum(r.action == "reused" for r in reports),
                "cached": sum(r.action == "cached" for r in reports),
                "seconds": sum(r.seconds for r in reports),
                "prior_seconds": sum(r.prior_seconds for r in reports),
                "hypothesis_evaluations": sum(r.evaluations for r in reports),
                "work_per_pixel": self.work_per_pixel(Pass(pass_value)),
                "valid_fraction": float(np.mean([r.valid_fraction for r in reports]))
                if reports
                else 0.0,
                "view_reports": [r.as_dict() for r in reports],
            }
        return {
            "passes": passes,
            "seconds_per_view": self.seconds_per_view(),
            "wall_seconds": self.wall_seconds,
            "highlights": {
                "computed": len(self.highlight_seconds),
                "seconds": sum(self.highlight_seconds.values()),
            },
            "fusion": {
                "seconds": self.fusion_seconds,
                "points": self.num_points,
                "reused": self.fusion_reused,
                "views_without_maps": self.fusion_views_without_maps,
                "output": None if self.output is None else str(self.output),
                "fingerprint": self.fusion_fingerprint,
            },
            "stereo_dir": None if self.stereo_dir is None else str(self.stereo_dir),
        }


# -- what shapes a view's maps ---------------------------------------------------------------------


def _uses_labels(options: DenseOptions) -> bool:
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


def _sources(view: View, options: DenseOptions) -> tuple[str, ...]:
    return view.sources[: options.patch_match.max_sources]


def pass_inputs(
    workspace: Workspace,
    view: View,
    pass_: Pass,
    options: DenseOptions,
    providers: PriorProviders | None,
    photometric: dict[str, str | None],
    highlights: HighlightStage | None = None,
    masks: ViewMasks | None = None,
) -> dict:
    """Everything that shapes ``view``'s maps of ``pass_``, as a tree for :func:`fingerprint`:
    the code, the pass's estimator options, the reference's and the sources' images (digests),
    calibration and the reference's depth range; for the photometric pass with the sparse seeding
    the sparse points that seed it, and with the aligned prior its providers (configs, plugins, the
    files they read) and segmentation options and the sparse points they align to; for the
    geometric pass the fingerprints of the photometric maps it reads (``photometric``: view name
    -> fingerprint, None for none); with highlight perception (``highlights``) the fingerprints
    of the reference's and the sources' highlight outputs; with ``options.mask``, what the mask
    of ``masks`` (the run's provider) depends on."""
    pm = {
        key: value
        for key, value in options.patch_match.as_dict().items()
        if key not in _SPEED_ONLY_OPTIONS
        and not (pass_ is Pass.PHOTOMETRIC and key in GEOMETRIC_ONLY_OPTIONS)
    }
    sources = _sources(view, options)
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
    if _uses_labels(options) and pass_ is Pass.PHOTOMETRIC:
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
            raise ValueError("pass_inputs needs the run's masks (masks=) with options.mask")
        inputs["mask"] = masks.provenance(view.name, workspace.root)
    if pass_ is Pass.GEOMETRIC:
        inputs["photometric"] = {name: photometric.get(name) for name in (view.name, *sources)}
    if highlights is not None:
        if pass_ is Pass.GEOMETRIC and options.patch_match.highlight_multiview:
            inputs["highlights"] = {
                name: highlights.refined_fingerprint(
                    name,
                    _sources(workspace[name], options),
                    photometric,
                )
                for name in (view.name, *sources)
            }
        else:
            inputs["highlights"] = {
                name: highlights.fingerprint(name) for name in (view.name, *sources)
            }
    return inputs


def map_files(stereo: Path, view_name: str, pass_: Pass, labels: bool) -> dict[str, Path]:
    """The map files a pass writes for a view (labels: the photometric pass's region labels)."""
    kinds = (("labels",) if labels and pass_ is Pass.PHOTOMETRIC else ()) + _MAP_KINDS
    return {kind: map_path(stereo, view_name, kind, pass_) for kind in kinds}


def _preview_files(stereo: Path, view_name: str, pass_: Pass, labels: bool) -> dict[str, Path]:
    folder = stereo / "previews"
    names = [f"{view_name}.{pass_.value}.{kind}.png" for kind in ("depth", "normal", "cost")]
    if labels and pass_ is Pass.PHOTOMETRIC:
        names += [
            f"{view_name}.{kind}.png" for kind in ("labels", "edges", "depth_prior", "normal_prior")
        ]
    return {name: folder / name for name in names}


@dataclass
class _ViewPlan:
    view: View
    inputs: dict
    fingerprint: str
    record: Record | None
    status: Status
    files: dict[str, Path]


def _plan_pass(
    workspace: Workspace,
    stereo: Path,
    pass_: Pass,
    options: DenseOptions,
    providers: PriorProviders | None,
    photometric: dict[str, str | None],
    highlights: HighlightStage | None = None,
    masks: ViewMasks | None = None,
) -> list[_ViewPlan]:
    plans = []
    labels = _uses_labels(options)
    for view in workspace.reference_views():
        if not view.sources:
            continue
        inputs = pass_inputs(
            workspace, view, pass_, options, providers, photometric, highlights, masks
        )
        fp = fingerprint(inputs)
        record = read_record(record_path(stereo, view.name, pass_.value))
        files = map_files(stereo, view.name, pass_, labels)
        plans.append(
            _ViewPlan(view, inputs, fp, record, status(record, fp, stereo, files.values()), files)
        )
    return plans


def _short(value) -> str:
    text = str(value)
    return text if len(text) <= 24 else text[:21] + "..."


def _explain(plans: list[_ViewPlan], pass_: Pass, overwrite: bool) -> str:
    """One line: how many views this pass computes and why."""
    total = len(plans)
    if overwrite:
        return f"{pass_.value} pass: computing all {total} views (overwrite=true)"
    todo = [p for p in plans if not p.status.reusable]
    if not todo:
        return (
            f"{pass_.value} pass: the maps of all {total} views are current (same inputs): reused"
        )
    counts: dict[Status, int] = {}
    for plan in todo:
        counts[plan.status] = counts.get(plan.status, 0) + 1
    parts = []
    if Status.STALE in counts:
        changed: dict[str, str] = {}
        for plan in todo:
            if plan.status is Status.STALE:
                for key, old, new in differences(plan.record.inputs, plan.inputs):
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
        f"{pass_.value} pass: computing {len(todo)} of {total} views"
        + (f" ({reused} current, reused)" if reused else "")
        + ": "
        + ", ".join(parts)
    )


def _refuse_foreign(plans: Iterable[tuple[Pass, _ViewPlan]], stereo: Path) -> None:
    foreign = [(pass_, plan) for pass_, plan in plans if plan.status is Status.FOREIGN]
    if not foreign:
        return
    pass_, first = foreign[0]
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
