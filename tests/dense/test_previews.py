"""Previews of reused products (``dvpmvs.dense.previews``): drawn from their files where a run
without previews left none."""

import shutil

from dvpmvs.dense import DenseOptions, run_dense
from dvpmvs.maps import Pass
from dvpmvs.workspace import Workspace
from tests.dense.tabletop import copy_workspace


def test_missing_previews_of_reused_maps_and_labels_are_drawn(dense_scene, tmp_path):
    root, _ = dense_scene
    workspace = Workspace.open(copy_workspace(root, tmp_path))
    previews = workspace.stereo_dir / "previews"
    shutil.rmtree(previews)
    summary = run_dense(workspace, DenseOptions(fuse=False), progress=False)
    assert {r.action for r in summary.reports} == {"reused"}
    names = {p.name for p in previews.iterdir()}
    for view in workspace.reference_views():
        for pass_ in Pass:
            for kind in ("depth", "normal", "cost"):
                assert f"{view.name}.{pass_.value}.{kind}.png" in names
        assert f"{view.name}.labels.png" in names
        # The priors the labels were made from are not stored: theirs are not drawn.
        assert f"{view.name}.edges.png" not in names
