"""The dense stage's plan (``dvpmvs.dense.plan``): one graph of stored products per run, each with
its record's status and the products whose files it reads; its tasks in an order that runs."""

import uuid
from dataclasses import replace

import pytest

from dvpmvs.dense import DenseError, DenseOptions, run_dense
from dvpmvs.dense.plan import plan_dense
from dvpmvs.dense.products import HIGHLIGHTS, REFINED_HIGHLIGHTS, product_key
from dvpmvs.dense.state import RunSpec, new_state
from dvpmvs.options import PatchMatchOptions
from dvpmvs.passes import Pass
from dvpmvs.provenance import Status
from dvpmvs.workspace import Workspace


def _plan(workspace, options, output=None):
    stereo = workspace.stereo_dir
    spec = RunSpec(uuid.uuid4().hex, workspace.root, workspace.options, stereo, options, None)
    return plan_dense(workspace, stereo, options, new_state(spec, workspace), output), spec


def _in_order(tasks) -> bool:
    """Every task comes after the tasks of the run it reads from."""
    seen, keys = set(), {t.key for t in tasks}
    for task in tasks:
        if any(key in keys and key not in seen for key in task.after):
            return False
        seen.add(task.key)
    return True


# A plain estimate (no prior, no deformation) of the 64x48 views: the records are the point here.
FAST = DenseOptions(
    patch_match=PatchMatchOptions(num_scales=1, planar_prior=False, deformable=False),
    fuse=False,
)


def test_the_plan_is_every_view_pass_with_what_it_reads(workspace_dir):
    workspace = Workspace.open(workspace_dir[0])
    plan, spec = _plan(workspace, FAST)
    views = [v for v in workspace.reference_views() if v.sources]
    assert [p.view.name for p in plan.passes[Pass.GEOMETRIC]] == [v.name for v in views]
    for product in plan.passes[Pass.GEOMETRIC]:
        assert product.status is Status.MISSING and product.record is None
        reads = (product.view.name, *product.view.sources[: FAST.patch_match.max_sources])
        assert product.after == tuple(product_key("photometric", n) for n in reads)
        assert product.inputs["photometric"] == {
            n: next(p.fingerprint for p in plan.passes[Pass.PHOTOMETRIC] if p.view.name == n)
            for n in reads
        }
    tasks = plan.tasks(spec, progress=False)
    assert [t.stage for t in tasks] == ["photometric pass"] * len(views) + ["geometric pass"] * len(
        views
    )
    assert _in_order(tasks)


def test_what_a_run_made_is_current_and_leaves_the_graph(workspace_dir):
    workspace = Workspace.open(workspace_dir[0])
    options = FAST
    run_dense(workspace, options, progress=False)
    plan, spec = _plan(workspace, options)
    assert {p.status for products in plan.passes.values() for p in products} == {Status.CURRENT}
    assert plan.tasks(spec, progress=False) == []
    # One option of the geometric pass: its products are stale, the photometric ones current.
    changed = replace(options, patch_match=replace(options.patch_match, geom_weight=0.3))
    plan, spec = _plan(workspace, changed)
    assert {p.status for p in plan.passes[Pass.GEOMETRIC]} == {Status.STALE}
    assert [t.stage for t in plan.tasks(spec, progress=False)] == ["geometric pass"] * len(
        plan.passes[Pass.GEOMETRIC]
    )
    assert "geom_weight: 0.2 -> 0.3" in plan.explain()[-1]


def test_highlight_outputs_are_products_the_maps_wait_for(workspace_dir):
    workspace = Workspace.open(workspace_dir[0])
    options = replace(FAST, priors={**FAST.priors, "highlight": {"name": "dichromatic"}})
    plan, spec = _plan(workspace, options)
    named = {p.view.name for p in plan.passes[Pass.PHOTOMETRIC]}
    assert set(plan.highlights) >= named
    assert all(
        p.kind == HIGHLIGHTS and p.status is Status.MISSING for p in plan.highlights.values()
    )
    multiview = options.patch_match.highlight_multiview
    assert bool(plan.refined) == multiview
    for product in plan.passes[Pass.PHOTOMETRIC]:
        assert product.after and all(key.startswith(f"{HIGHLIGHTS}:") for key in product.after)
        # The maps' inputs name the fingerprints of the highlight products they read.
        assert product.inputs["highlights"] == {
            n: plan.highlights[n].fingerprint for n in product.inputs["highlights"]
        }
    kind = REFINED_HIGHLIGHTS if multiview else HIGHLIGHTS
    for product in plan.passes[Pass.GEOMETRIC]:
        assert product_key(kind, product.view.name) in product.after
    tasks = plan.tasks(spec, progress=False)
    assert _in_order(tasks)
    assert sum(t.stage == "highlights" for t in tasks) == len(plan.highlights)


def test_a_views_mask_is_a_product_its_maps_wait_for(workspace_dir):
    import cv2
    import numpy as np

    from dvpmvs.dense.products import MASK

    workspace = Workspace.open(workspace_dir[0])
    folder = workspace_dir[0] / "masks"
    for view in workspace.reference_views():
        keep = np.full((view.height, view.width), 255, np.uint8)
        keep[:, : view.width // 4] = 0
        (folder / view.name).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(folder / f"{view.name}.png"), keep)
    options = replace(FAST, mask={"name": "files", "path": str(folder)})
    plan, spec = _plan(workspace, options)
    made = [p.view.name for p in plan.passes[Pass.PHOTOMETRIC]]
    assert list(plan.masks) == made
    assert all(p.kind == MASK and p.status is Status.MISSING for p in plan.masks.values())
    for products in plan.passes.values():
        for p in products:
            assert p.after[0] == product_key(MASK, p.view.name)
    tasks = plan.tasks(spec, progress=False)
    assert [t.stage for t in tasks[: len(made)]] == ["masks"] * len(made) and _in_order(tasks)
    run_dense(workspace, options, progress=False)
    plan, spec = _plan(workspace, replace(options, overwrite=True))
    assert {p.status for p in plan.masks.values()} == {Status.CURRENT}
    assert not [t for t in plan.tasks(spec, progress=False) if t.stage == "masks"]


def test_the_cloud_is_a_product_of_the_maps_the_plan_makes(workspace_dir):
    workspace = Workspace.open(workspace_dir[0])
    options = replace(FAST, fuse=True)
    output = workspace.root / "fused.ply"
    plan, _ = _plan(workspace, options, output)
    # Planned before its maps exist: it names the fingerprints they will carry.
    assert plan.cloud.stored.state is Status.MISSING and plan.cloud.wanted(overwrite=False)
    assert plan.cloud.stored.inputs["maps"] == {
        p.view.name: p.fingerprint for p in plan.passes[Pass.GEOMETRIC]
    }
    assert plan.explain()[-1].startswith("fusion: fusing 5 views")
    summary = run_dense(workspace, options, output=output, progress=False)
    assert summary.fusion_fingerprint == plan.cloud.fingerprint
    again, spec = _plan(workspace, options, output)
    assert not again.cloud.wanted(overwrite=False) and again.tasks(spec, progress=False) == []
    # A fusion option: the cloud only.
    stricter = replace(options, fusion=replace(options.fusion, min_consistent_views=3))
    changed, spec = _plan(workspace, stricter, output)
    assert changed.cloud.stored.state is Status.STALE and changed.tasks(spec, progress=False) == []
    # A cloud dvpmvs did not write stops the run before anything is computed.
    output.with_name(output.name + ".provenance.json").unlink()
    foreign, _ = _plan(workspace, options, output)
    with pytest.raises(DenseError, match="carries no dvpmvs provenance record"):
        foreign.refuse_foreign(workspace.stereo_dir)
