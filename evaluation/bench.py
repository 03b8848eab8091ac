"""The benchmark of the dense stage: ``dvpmvs bench``, a sweep over synthetic scenes and configurations.

``dvpmvs bench scene=room width=800`` renders the scene (once: :func:`render_scene`), runs the
dense stage on it with any ``dense`` option, scores the fused cloud and the depth maps against
the exact ground truth (``evaluate.*``; ``evaluate.colmap_fusion=true`` also COLMAP's fusion of
the same maps) and writes the run's manifest (:mod:`dvpmvs.run`). Under ``-m``
every job runs in its own folder and the sweep ends with one table
(:mod:`dvpmvs.sweep`). For example (docs/benchmarks.md has the figures)::

    dvpmvs bench -m scene=room,facade,tabletop width=800 num_threads=2 method=default,paper
"""

from __future__ import annotations

import json
import shutil
import tempfile
from dataclasses import asdict
from pathlib import Path

__all__ = ["render_scene", "rendered_digest", "SCENES"]

SCENES = ("room", "facade", "tabletop", "street", "courtyard")
_COMPLETE = ".bench-scene-complete"
# The modules that render a scene: another version of any of them may render another scene (the
# scene's identity is its content's digest; this keys the cache of rendered scenes).
_GENERATOR = (
    "synthetic.py",
    "synthetic_scenes.py",
    "render.py",
    "textures.py",
    "geometry.py",
    "depth_scans.py",
)


def _scene_fingerprint(options) -> str:
    """What a rendered scene depends on: its parameters, the generator's sources and the
    libraries (another OpenCV or Open3D renders other images)."""
    from dvpmvs.digests import file_digest, fingerprint
    from dvpmvs.provenance import library_versions

    folder = Path(__file__).resolve().parent
    return fingerprint(
        {
            "options": asdict(options),
            "generator": {n: file_digest(folder / n) for n in _GENERATOR},
            "libraries": library_versions(),
        }
    )


def _marker(workspace: Path) -> dict:
    try:
        marker = json.loads((workspace / _COMPLETE).read_text())
    except (OSError, ValueError):
        return {}
    return marker if isinstance(marker, dict) else {}


def _rendered_fingerprint(workspace: Path) -> str | None:
    return _marker(workspace).get("fingerprint")


def rendered_digest(workspace: str | Path):
    """The :class:`~dvpmvs.evaluation.scene_digest.SceneDigest` of a scene ``render_scene`` made,
    computed from its files as they are now. A scene changed since it was rendered (its digest
    is not the one its marker recorded) is an error naming the parts that differ: figures run
    on it would be quoted as the render's."""
    from dvpmvs.errors import DvpmvsError
    from dvpmvs.evaluation.scene_digest import scene_digest

    workspace = Path(workspace)
    digest = scene_digest(workspace)
    recorded = _marker(workspace).get("digest") or {}
    if recorded.get("parts") and recorded.get("rule") == _digest_rule():
        differing = digest.differing(dict(recorded["parts"]))
        if differing:
            raise DvpmvsError(
                f"the scene in {workspace} was changed since it was rendered (differing: "
                f"{', '.join(differing)}): its figures would not be the render's. Delete the "
                f"folder to render the scene again, or choose another scenes_dir="
            )
    return digest


def _digest_rule() -> str:
    """The rule a marker's digest was computed by: the digest module's own source."""
    from dvpmvs.digests import file_digest
    from dvpmvs.evaluation import scene_digest as module

    return file_digest(Path(module.__file__))


def render_scene(workspace: str | Path, scene: str, views: int, width: int, seed: int) -> Path:
    """The synthetic ``scene`` rendered into ``workspace`` unless the same inputs rendered it
    there already (its marker carries their fingerprint; other inputs are an error, not a silent
    reuse). Rendered into a temporary folder beside it and renamed into place, so that jobs of a
    sweep running side by side never read half a scene (the same parameters give the same bytes:
    whichever job renders first, the scene is the same)."""
    from dvpmvs.errors import DvpmvsError
    from dvpmvs.evaluation.scene_digest import scene_digest
    from dvpmvs.evaluation.synthetic import SynthOptions, generate

    workspace = Path(workspace)
    if scene not in SCENES:
        raise DvpmvsError(f"unknown scene {scene!r}; choose one of {', '.join(SCENES)}")
    options = SynthOptions(scene=scene, views=views, width=width, seed=seed)
    expected = _scene_fingerprint(options)
    if (workspace / _COMPLETE).is_file():
        if _rendered_fingerprint(workspace) == expected:
            return workspace
        raise DvpmvsError(
            f"{workspace} was rendered from other inputs (other parameters, another version of the "
            f"scene generator, OpenCV or Open3D); delete it to render it anew, or choose another "
            f"scenes_dir="
        )
    if workspace.exists():
        raise DvpmvsError(
            f"{workspace} exists but is not a finished bench scene (no {_COMPLETE}); delete it to "
            f"render the scene again"
        )
    workspace.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{workspace.name}.", dir=workspace.parent))
    try:
        generate(staging, options)
        digest = scene_digest(staging)
        (staging / _COMPLETE).write_text(
            json.dumps(
                {
                    "fingerprint": expected,
                    "options": asdict(options),
                    "digest": {**digest.to_json(), "rule": _digest_rule()},
                }
            )
            + "\n"
        )
        try:
            staging.rename(workspace)
        except OSError:
            if _rendered_fingerprint(workspace) != expected:  # not a job that finished first
                raise
    finally:
        if staging.exists():
            shutil.rmtree(staging, ignore_errors=True)
    return workspace
