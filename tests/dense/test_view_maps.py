"""One view's maps of a pass (``dvpmvs.dense.view_maps``): made from the products stored before
them (here the region labels), with their record."""

import uuid

import numpy as np

from dvpmvs.dense import DenseOptions
from dvpmvs.dense.plan import plan_dense
from dvpmvs.dense.state import RunSpec, new_state, serving
from dvpmvs.dense.tasks import make_view_maps
from dvpmvs.maps import Pass, read_extra_map, write_extra_map
from dvpmvs.workspace import Workspace
from tests.dense.tabletop import copy_workspace


def test_the_maps_are_made_from_the_stored_labels(dense_scene, tmp_path):
    root, _ = dense_scene
    workspace = Workspace.open(copy_workspace(root, tmp_path))
    options = DenseOptions(geometric=False, fuse=False)
    spec = RunSpec(uuid.uuid4().hex, root, workspace.options, workspace.stereo_dir, options, None)
    state = new_state(spec, workspace)
    plan = plan_dense(workspace, workspace.stereo_dir, options, state)
    maps = plan.passes[Pass.PHOTOMETRIC][0]
    labels = plan.regions[maps.view.name].files["labels"]
    stored = maps.files["depth"].read_bytes()
    with serving(spec, state):
        # Made again from the same labels: the same bytes (same seed).
        assert make_view_maps(spec, maps, progress=False).action == "computed"
        assert maps.files["depth"].read_bytes() == stored
        # From other labels (one region for the whole view): other anchors, other maps.
        assert read_extra_map(labels).max() >= 2
        write_extra_map(labels, np.ones((maps.view.height, maps.view.width), np.int32))
        make_view_maps(spec, maps, progress=False)
    assert maps.files["depth"].read_bytes() != stored
