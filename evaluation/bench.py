"""The benchmark of the dense stage: ``dvpmvs bench``, a sweep over synthetic scenes and configurations.

``dvpmvs bench scene=room width=800`` renders the scene (once: :func:`render_scene`), runs the
dense stage on it with any ``dense`` option, scores the fused cloud and the depth maps against
the exact ground truth (``evaluate.*``; ``evaluate.colmap_fusion=true`` also COLMAP's fusion of
the same maps) and writes the run's manifest (:mod:`dvpmvs.evaluation.runs`). Under ``-m``
every job runs in its own folder and the sweep ends with one table
(:mod:`dvpmvs.evaluation.sweep`). The figures in docs/benchmarks.md::

    dvpmvs bench -m scene=room,facade,tabletop views=8 width=800 num_threads=2 evaluate.colmap_fusion=true
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

__all__ = ["render_scene", "SCENES"]

SCENES = ("room", "facade", "tabletop")
_COMPLETE = ".bench-scene-complete"


def render_scene(workspace: str | Path, scene: str, views: int, width: int, seed: int) -> Path:
    """The synthetic ``scene`` rendered into ``workspace`` unless it is there already. Rendered
    into a temporary folder beside it and renamed into place, so that jobs of a sweep running
    side by side never read half a scene (the same parameters give the same bytes: whichever
    job renders first, the scene is the same)."""
    from dvpmvs.errors import DvpmvsError
    from dvpmvs.evaluation.synthetic import SynthOptions, generate

    workspace = Path(workspace)
    if (workspace / _COMPLETE).is_file():
        return workspace
    if scene not in SCENES:
        raise DvpmvsError(f"unknown scene {scene!r}; choose one of {', '.join(SCENES)}")
    if workspace.exists():
        raise DvpmvsError(f"{workspace} exists but is not a finished bench scene (no {_COMPLETE}); delete it to "
                          f"render the scene again")
    workspace.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{workspace.name}.", dir=workspace.parent))
    try:
        generate(staging, SynthOptions(scene=scene, views=views, width=width, seed=seed))
        (staging / _COMPLETE).write_text(f"{scene} {views} views {width} px seed {seed}\n")
        try:
            staging.rename(workspace)
        except OSError:
            if not (workspace / _COMPLETE).is_file():  # not a job that finished first
                raise
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
    return workspace
