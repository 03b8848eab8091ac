"""What a view's estimate reads (``dvpmvs.dense.problem``): the estimator's problem in the
geometric pass."""

from dataclasses import replace

import numpy as np
import pytest

from dvpmvs.maps import (
    Pass,
    map_path,
    read_extra_map,
)
from dvpmvs.patchmatch import PatchMatchOptions
from dvpmvs.workspace import Workspace
from tests.dense.tabletop import copy_workspace


def test_without_restoration_the_geometric_pass_sees_only_the_selected_sources(dense_scene):
    # The paper's w/o Res: visibility from view selection alone. With no source selected
    # anywhere, restoration makes visible the sources the photometric depths reproject into.
    from dvpmvs.dense.problem import view_problem
    from dvpmvs.patchmatch._patchmatch import PlaneState
    from dvpmvs.patchmatch.estimator import (
        _kernel_params,
        _Level,
        _matching_images,
        _visible_sources,
    )

    root, _ = dense_scene
    workspace = Workspace.open(root)
    view = workspace.reference_views()[1]
    restoring = PatchMatchOptions(anchor_visibility=True)
    problem = view_problem(workspace, view, Pass.GEOMETRIC, restoring)
    level = _Level.build(problem, 1.0, use_depth=True, images=_matching_images(problem, restoring))
    h, w = level.ref.shape
    S = len(problem.sources)
    state = PlaneState.empty(h, w, S)  # no source selected anywhere
    state.depth[...] = problem.initial[0]
    state.normal[...] = problem.initial[1]
    params = _kernel_params(problem, restoring)
    restored = _visible_sources(level, restoring, state, params, 2)
    selected_only = _visible_sources(
        level, replace(restoring, visibility_restoration=False), state, params, 2
    )
    assert 0.33 < (restored > 0).mean() < 0.42 and not selected_only.any()  # measured 0.373


def test_geometric_problem_carries_the_sources_costs_for_the_visibility_restoration(
    dense_scene, tmp_path
):
    from dvpmvs.dense.problem import view_problem
    from dvpmvs.maps import MapFormatError
    from dvpmvs.options.patch_match import PatchMatchOptions

    root, _ = dense_scene
    workspace = Workspace.open(copy_workspace(root, tmp_path))
    view = workspace.reference_views()[0]
    restoring = PatchMatchOptions(anchor_visibility=True)
    problem = view_problem(workspace, view, Pass.GEOMETRIC, restoring)
    for src in problem.sources:
        stored = read_extra_map(map_path(workspace.stereo_dir, src.name, "cost", Pass.PHOTOMETRIC))
        assert np.array_equal(src.cost, stored.reshape(src.shape))
    # Loaded only where they are used.
    assert all(
        src.cost is None
        for src in view_problem(
            workspace, view, Pass.GEOMETRIC, replace(restoring, anchor_visibility=False)
        ).sources
    )
    assert all(
        src.cost is None
        for src in view_problem(
            workspace, view, Pass.GEOMETRIC, replace(restoring, geom_deformable=False)
        ).sources
    )
    # A missing cost map is unknown (the kernel then keeps the source's own depths); a corrupt
    # one is an error, not a silent fallback.
    path = map_path(workspace.stereo_dir, problem.sources[0].name, "cost", Pass.PHOTOMETRIC)
    data = path.read_bytes()
    path.unlink()
    assert np.isinf(view_problem(workspace, view, Pass.GEOMETRIC, restoring).sources[0].cost).all()
    path.write_bytes(data[:1000])
    with pytest.raises(MapFormatError):
        view_problem(workspace, view, Pass.GEOMETRIC, restoring)
