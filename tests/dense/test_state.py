"""What a dense run's tasks share in a process (``dvpmvs.dense.state``): the run's state is built
once per process and run, from the spec alone where the driver's is not served."""

import uuid
from dataclasses import replace

from dvpmvs.dense import DenseOptions
from dvpmvs.dense.state import RunSpec, new_state, run_state, serving
from dvpmvs.workspace import Workspace


def _spec(workspace, options=None):
    options = options or DenseOptions()
    return RunSpec(
        uuid.uuid4().hex, workspace.root, workspace.options, workspace.stereo_dir, options, None
    )


def test_the_state_is_built_once_per_run_and_the_drivers_is_served(workspace_dir):
    workspace = Workspace.open(workspace_dir[0])
    spec = _spec(workspace)
    built = run_state(spec)
    assert run_state(spec) is built  # not rebuilt per task
    assert built.workspace is not workspace and built.workspace.root == workspace.root
    assert [v.name for v in built.workspace.reference_views()] == [
        v.name for v in workspace.reference_views()
    ]
    other = _spec(workspace)
    driver = new_state(other, workspace)
    with serving(other, driver):
        assert run_state(other) is driver and run_state(other).workspace is workspace
    assert run_state(other) is not driver  # after the run, a worker builds its own


def test_a_state_holds_the_providers_its_options_name(workspace_dir):
    workspace = Workspace.open(workspace_dir[0])
    plain = new_state(_spec(workspace), workspace)
    assert plain.highlights is None and not plain.masks.active and plain.cache is None
    assert plain.providers is not None  # the aligned prior's (the default deforms with regions)
    without_regions = replace(DenseOptions(), segmentation=None)
    assert new_state(_spec(workspace, without_regions), workspace).providers is None
    highlights = replace(
        DenseOptions(), priors={**DenseOptions().priors, "highlight": {"name": "dichromatic"}}
    )
    stage = new_state(_spec(workspace, highlights), workspace).highlights
    assert stage is not None and stage.name == "dichromatic"
