"""What a dense run reports: per view and pass, whether its maps were computed, reused or
linked from the map cache and what they cost (:class:`ViewReport`); the run's reports, timings
and cloud (:class:`DenseSummary`); and the error of a run that cannot go as asked."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dvpmvs.errors import DvpmvsError
from dvpmvs.maps import path_for_manifest
from dvpmvs.passes import Pass
from dvpmvs.patchmatch.problem import pooled_work
from dvpmvs.provenance import Record, Status

__all__ = ["DenseError", "ViewReport", "DenseSummary", "view_report"]


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

    def as_dict(self, folder: Path | None = None) -> dict:
        """The summary as a manifest holds it; paths inside the run's ``folder`` relative to it
        (:func:`~dvpmvs.maps.path_for_manifest`)."""
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
                "output": None if self.output is None else path_for_manifest(self.output, folder),
                "fingerprint": self.fusion_fingerprint,
            },
            "stereo_dir": None
            if self.stereo_dir is None
            else path_for_manifest(self.stereo_dir, folder),
        }


def view_report(product, record: Record, action: str) -> ViewReport:
    """The report of a view pass's maps (``product``, a :class:`~dvpmvs.dense.products.Product`)
    as ``record`` describes them; ``action``: what this run did."""
    stats = record.stats
    return ViewReport(
        product.view.name,
        Pass(product.kind),
        product.status,
        action,
        seconds=float(stats.get("seconds", 0.0)),
        evaluations=int(stats.get("evaluations", 0)),
        prior_seconds=float(stats.get("prior_seconds", 0.0)),
        valid_fraction=float(stats.get("valid_fraction", 0.0)),
        width=product.view.width,
        height=product.view.height,
        fingerprint=product.fingerprint,
        work=list(stats.get("work", [])),
    )
