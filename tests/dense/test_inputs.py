"""What shapes a view's maps (``dvpmvs.dense.inputs``): the geometric-only options leave the
photometric maps alone; the sparse points that seed a view are inputs of its photometric maps."""

from dataclasses import replace

import numpy as np
import pycolmap
import pytest

from dvpmvs.dense import (
    GEOMETRIC_ONLY_OPTIONS,
    DenseOptions,
)
from dvpmvs.maps import (
    Pass,
)
from dvpmvs.patchmatch import PatchMatchOptions
from dvpmvs.workspace import Workspace, WorkspaceOptions
from tests.dense.tabletop import copy_workspace


@pytest.mark.slow
def test_photometric_maps_do_not_depend_on_the_geometric_only_options(dense_scene):
    # Runs that differ only in these share their photometric maps: check that none of them
    # reaches the photometric pass (visibility-aware deformation on, so that its options run).
    from dvpmvs.dense.problem import view_problem
    from dvpmvs.patchmatch import estimate

    root, _ = dense_scene
    workspace = Workspace.open(root, WorkspaceOptions(max_image_size=100))
    view = workspace.reference_views()[1]
    base = PatchMatchOptions(anchor_visibility=True, num_scales=1)
    problem = view_problem(workspace, view, Pass.PHOTOMETRIC, base)
    reference = estimate(problem, base, Pass.PHOTOMETRIC)
    changes = {
        "geom_iterations": 2,
        "geom_weight": 0.5,
        "geom_max_error": 4.0,
        "geom_deformable": False,
        "visibility_restoration": False,
        "highlight_multiview": False,
    }
    assert set(changes) == GEOMETRIC_ONLY_OPTIONS
    for key, value in changes.items():
        result = estimate(problem, replace(base, **{key: value}), Pass.PHOTOMETRIC)
        assert np.array_equal(result.depth, reference.depth), key
        assert np.array_equal(result.normal, reference.normal), key


def test_the_sparse_points_that_seed_a_view_are_inputs_of_its_photometric_maps(
    dense_scene, tmp_path
):
    # Moving one sparse point changes the seeds, not the depth range: the photometric maps'
    # fingerprint must change with it even without the aligned prior (which reads the points too).
    from dvpmvs.dense import pass_inputs
    from dvpmvs.digests import fingerprint

    root, _ = dense_scene
    moved = copy_workspace(root, tmp_path)
    model = pycolmap.Reconstruction(str(moved / "sparse"))
    workspace = Workspace.open(root)
    view = workspace.reference_views()[0]
    point_id = next(
        pid
        for pid, point in model.points3D.items()
        if any(e.image_id == view.image_id for e in point.track.elements)
    )
    model.points3D[point_id].xyz = model.points3D[point_id].xyz + 1e-3
    model.write(str(moved / "sparse"))
    other = Workspace.open(moved)
    assert other[view.name].depth_range == view.depth_range

    plain = replace(DenseOptions(), segmentation=None)
    unseeded = replace(plain, patch_match=PatchMatchOptions(sparse_seed=False))

    def photometric(ws, options):
        return fingerprint(pass_inputs(ws, ws[view.name], Pass.PHOTOMETRIC, options, {}))

    assert photometric(workspace, plain) != photometric(other, plain)
    assert photometric(workspace, unseeded) == photometric(other, unseeded)
