"""A view's region labels (``dvpmvs.dense.regions``): a product of their own, made once per view
and stored with their record, read by both passes, their cost reported with the photometric pass."""

import uuid

import pytest

from dvpmvs.dense import DenseOptions, run_dense
from dvpmvs.dense.plan import plan_dense
from dvpmvs.dense.products import REGIONS
from dvpmvs.dense.state import RunSpec, new_state
from dvpmvs.maps import Pass
from dvpmvs.provenance import Status, read_record, record_path
from dvpmvs.workspace import Workspace
from tests.dense.tabletop import copy_workspace


def _plan(workspace, options):
    spec = RunSpec(
        uuid.uuid4().hex, workspace.root, workspace.options, workspace.stereo_dir, options, None
    )
    return plan_dense(workspace, workspace.stereo_dir, options, new_state(spec, workspace))


def test_both_passes_read_the_labels_their_product_stored(dense_scene):
    root, _ = dense_scene
    workspace = Workspace.open(root)
    plan = _plan(workspace, DenseOptions())
    assert {p.status for p in plan.regions.values()} == {Status.CURRENT}
    for pass_ in Pass:
        for maps in plan.passes[pass_]:
            regions = plan.regions[maps.view.name]
            assert maps.inputs["regions"] == regions.fingerprint
            assert regions.key in maps.after
    # Without the aligned prior there are none, and the maps name none.
    plain = _plan(workspace, DenseOptions(segmentation=None))
    assert plain.regions == {} and "regions" not in plain.passes[Pass.PHOTOMETRIC][0].inputs


@pytest.mark.slow
def test_deleted_labels_are_made_again_alone_and_the_same(dense_scene, tmp_path):
    root, _ = dense_scene
    workspace = Workspace.open(copy_workspace(root, tmp_path))
    view = workspace.reference_views()[1]
    labels = _plan(workspace, DenseOptions()).regions[view.name].files["labels"]
    original = labels.read_bytes()
    labels.unlink()
    (workspace.stereo_dir / "depth_maps" / f"{view.name}.geometric.bin").unlink()
    summary = run_dense(workspace, DenseOptions(fuse=False), progress=False)
    # The geometric maps that read them are remade; the photometric ones, made from labels
    # with the same fingerprint, are current.
    assert summary.computed(Pass.PHOTOMETRIC) == []
    assert [r.name for r in summary.computed(Pass.GEOMETRIC)] == [view.name]
    assert labels.read_bytes() == original
    record = read_record(record_path(workspace.stereo_dir, view.name, REGIONS))
    assert record.complete and record.stats["regions"] >= 2 and record.stats["seconds"] > 0


def test_the_labels_cost_is_reported_with_the_photometric_pass(dense_scene):
    root, summary = dense_scene
    for report in summary.of_pass(Pass.PHOTOMETRIC):
        record = read_record(record_path(root / "stereo", report.name, REGIONS))
        assert report.prior_seconds == record.stats["seconds"] > 0
        assert report.seconds > report.prior_seconds
    assert all(r.prior_seconds == 0 for r in summary.of_pass(Pass.GEOMETRIC))
