"""The dense stage's tasks (``dvpmvs.dense.tasks``): each makes one product of the plan and stores
it with its record; a current product is not made again, a cached one is linked."""

import uuid
from dataclasses import replace

from dvpmvs.dense import DenseOptions
from dvpmvs.dense.plan import plan_dense
from dvpmvs.dense.state import RunSpec, new_state, serving
from dvpmvs.dense.tasks import make_highlights, make_view_maps
from dvpmvs.maps import read_depth_map
from dvpmvs.options import PatchMatchOptions
from dvpmvs.passes import Pass
from dvpmvs.provenance import MapCache, Status
from dvpmvs.workspace import Workspace

# A plain estimate of the 64x48 views, without the geometric pass: the products are the point.
FAST = DenseOptions(
    patch_match=PatchMatchOptions(num_scales=1, planar_prior=False, deformable=False),
    geometric=False,
    fuse=False,
    priors={**DenseOptions().priors, "highlight": {"name": "dichromatic"}},
)


def _planned(workspace, stereo, cache=None):
    spec = RunSpec(uuid.uuid4().hex, workspace.root, workspace.options, stereo, FAST, cache)
    state = new_state(spec, workspace)
    return plan_dense(workspace, stereo, FAST, state), spec, state


def test_a_task_makes_its_product_once_and_stores_it(workspace_dir):
    workspace = Workspace.open(workspace_dir[0])
    stereo = workspace.stereo_dir
    plan, spec, state = _planned(workspace, stereo)
    highlight = next(iter(plan.highlights.values()))
    maps = plan.passes[Pass.PHOTOMETRIC][0]
    with serving(spec, state):
        assert make_highlights(spec, highlight) > 0
        for other in plan.highlights.values():  # the maps read their sources' outputs too
            make_highlights(spec, other)
        report = make_view_maps(spec, maps, progress=False)
    assert report.action == "computed" and report.seconds > 0 and report.name == maps.view.name
    depth = read_depth_map(maps.files["depth"])
    assert depth.shape == (maps.view.height, maps.view.width)
    again, spec, state = _planned(workspace, stereo)
    stored = again.passes[Pass.PHOTOMETRIC][0]
    assert stored.status is Status.CURRENT and stored.record.complete
    # The record describes the maps on disk.
    assert stored.record.stats["valid_fraction"] == report.valid_fraction == (depth > 0).mean()
    # What is left: the other views' maps; the highlight outputs they read are current.
    left = again.tasks(spec, progress=False)
    assert [t.key for t in left] == [p.key for p in again.passes[Pass.PHOTOMETRIC][1:]]
    current = replace(highlight, stored=state.highlights.check(highlight.view.name))
    assert current.status is Status.CURRENT
    with serving(spec, state):  # a current highlight output is not made again
        assert make_highlights(spec, current) is None


def test_a_cached_product_is_linked_into_another_folder(workspace_dir, tmp_path):
    workspace = Workspace.open(workspace_dir[0])
    cache = tmp_path / "cache"
    first, spec, state = _planned(workspace, workspace.stereo_dir, cache)
    product = first.passes[Pass.PHOTOMETRIC][0]
    with serving(spec, state):
        for highlight in first.highlights.values():
            make_highlights(spec, highlight)
        assert make_view_maps(spec, product, progress=False).action == "computed"
    out = tmp_path / "out"
    workspace.link_output(out)
    second, spec, state = _planned(workspace, out / "stereo", cache)
    linked = next(p for p in second.passes[Pass.PHOTOMETRIC] if p.view.name == product.view.name)
    assert linked.fingerprint == product.fingerprint and linked.status is Status.MISSING
    with serving(spec, state):
        report = make_view_maps(spec, linked, progress=False)
    assert report.action == "cached"
    assert linked.files["depth"].read_bytes() == product.files["depth"].read_bytes()
    assert MapCache(cache).root.is_dir()
