"""What a dense run reports (``dvpmvs.dense.report``): a view pass's figures from its record, and
the run's totals and per-pixel work over computed and reused views."""

import json
from dataclasses import asdict

import pytest

from dvpmvs.dense.products import Product
from dvpmvs.dense.report import DenseSummary, view_report
from dvpmvs.passes import Pass
from dvpmvs.patchmatch.problem import LevelWork
from dvpmvs.provenance import CachedOutput, Record, Status
from dvpmvs.workspace import Workspace

# One pyramid level's counts (totals over its 64x48 pixels): 10 hypotheses, 900 samples a pixel.
LEVEL = asdict(LevelWork(0, 64, 48, 10 * 64 * 48, 40 * 64 * 48, 900 * 64 * 48))


@pytest.fixture
def views(workspace_dir):
    return Workspace.open(workspace_dir[0]).reference_views()[:2]


def _report(tmp_path, view, pass_, seconds, action):
    stored = CachedOutput.check(tmp_path / f"{view.name}.{pass_.value}.json", {"v": 1}, tmp_path)
    product = Product(pass_.value, view, stored, {})
    stats = {"seconds": seconds, "prior_seconds": 0.5, "evaluations": 7, "work": [LEVEL]}
    return view_report(product, Record("f", {}, True, {}, [], stats), action)


def test_a_view_report_carries_its_records_figures(tmp_path, views):
    report = _report(tmp_path, views[0], Pass.GEOMETRIC, 3.0, "reused")
    assert (report.name, report.pass_, report.status) == (
        views[0].name,
        Pass.GEOMETRIC,
        Status.MISSING,
    )
    assert (report.seconds, report.prior_seconds, report.evaluations) == (3.0, 0.5, 7)
    assert (report.width, report.height) == (views[0].width, views[0].height)
    assert report.skipped and report.as_dict()["size"] == [views[0].width, views[0].height]


def test_the_summary_adds_every_pass_and_fusion_per_view(tmp_path, views):
    reports = [
        _report(tmp_path, views[0], Pass.PHOTOMETRIC, 2.0, "computed"),
        _report(tmp_path, views[1], Pass.PHOTOMETRIC, 4.0, "reused"),
        _report(tmp_path, views[0], Pass.GEOMETRIC, 1.0, "cached"),
    ]
    summary = DenseSummary(reports, {"photometric": 2.0, "geometric": 0.0}, fusion_seconds=3.0)
    assert summary.seconds_per_view() == pytest.approx((2.0 + 4.0 + 1.0 + 3.0) / 2)
    assert [r.name for r in summary.computed(Pass.PHOTOMETRIC)] == [views[0].name]
    assert summary.computed(Pass.GEOMETRIC) == []
    passes = json.loads(json.dumps(summary.as_dict()))["passes"]
    assert (passes["photometric"]["computed"], passes["photometric"]["reused"]) == (1, 1)
    assert passes["geometric"]["cached"] == 1
    assert passes["photometric"]["hypothesis_evaluations"] == 14
    level = passes["photometric"]["work_per_pixel"][0]
    assert level["samples"] == pytest.approx(900.0) and level["hypotheses"] == pytest.approx(10.0)
