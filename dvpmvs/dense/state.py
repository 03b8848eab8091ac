"""What the tasks of a dense run share in a process: the run's spec (what any process that
sees the same files needs to rebuild the run's state) and its state (the workspace, the prior,
highlight and mask providers, the map cache), built once per process and run, not per task."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from dvpmvs.dense.inputs import uses_labels
from dvpmvs.dense.masks import MaskStore
from dvpmvs.highlight import HighlightStage, highlight_config
from dvpmvs.options.dense import DenseOptions
from dvpmvs.priors import PriorProviders
from dvpmvs.provenance import MapCache
from dvpmvs.workspace import Workspace, WorkspaceOptions

__all__ = ["RunSpec", "RunState", "new_state", "run_state", "serving"]


@dataclass(frozen=True)
class RunSpec:
    """What a task needs to rebuild the run's state in any process that sees the same files:
    the workspace (folder and read options), the maps' folder, the options, the map cache."""

    token: str
    root: Path
    workspace_options: WorkspaceOptions
    stereo: Path
    options: DenseOptions
    cache: Path | None


@dataclass
class RunState:
    workspace: Workspace
    providers: PriorProviders | None
    highlights: HighlightStage | None
    cache: MapCache | None
    # One provider per process and run (a network's session is loaded once); its masks stored.
    masks: MaskStore


# The runs' states in this process, by token: built once per worker process and run, not per task.
_states: dict[str, RunState] = {}


def new_state(
    spec: RunSpec, workspace: Workspace | None = None, cache: MapCache | None = None
) -> RunState:
    workspace = (
        workspace if workspace is not None else Workspace.open(spec.root, spec.workspace_options)
    )
    options = spec.options
    highlight = highlight_config(options.priors.get("highlight"))
    return RunState(
        workspace,
        PriorProviders.from_configs(options.priors) if uses_labels(options) else None,
        HighlightStage(workspace, spec.stereo, highlight) if highlight is not None else None,
        cache if cache is not None else MapCache(spec.cache) if spec.cache is not None else None,
        MaskStore.from_config(options.mask, spec.stereo, workspace.root, options.overwrite),
    )


def run_state(spec: RunSpec) -> RunState:
    state = _states.get(spec.token)
    if state is None:
        import cv2

        if (
            spec.options.patch_match.num_threads > 0
        ):  # OpenCV reads 0 as "no threads", not "every core"
            cv2.setNumThreads(spec.options.patch_match.num_threads)
        while len(_states) >= 2:  # a worker serves one run at a time; keep the last ones only
            _states.pop(next(iter(_states)))
        state = _states[spec.token] = new_state(spec)
    return state


@contextmanager
def serving(spec: RunSpec, state: RunState) -> Iterator[None]:
    """While the block runs, tasks of ``spec`` run in this process use ``state`` (the driver's,
    already built) instead of building their own."""
    _states[spec.token] = state
    try:
        yield
    finally:
        _states.pop(spec.token, None)
