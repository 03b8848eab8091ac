"""The embedded default scene: a small synthetic room shipped with the package.

``scenes/room/`` holds the COLMAP workspace (``images/``, ``sparse/``, ``stereo/``) of
``dvpmvs synth scene=room views=5 width=320 seed=0``; its ground truth and simulated priors
(about 18 MB) are not shipped but regenerated from the same parameters, which the generator
reproduces byte for byte. ``materialise`` writes the whole scene to a folder.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from dvpmvs.digests import file_digest, fingerprint
from dvpmvs.evaluation.synthetic import SynthOptions, generate

__all__ = ["EMBEDDED_SCENE", "EMBEDDED_OPTIONS", "materialise"]

EMBEDDED_SCENE = Path(__file__).parent / "scenes" / "room"
EMBEDDED_OPTIONS = SynthOptions(scene="room", views=5, width=320, seed=0)


def _shipped_fingerprint() -> str:
    """The identity of the shipped workspace: its files' names and bytes."""
    return fingerprint(
        {
            path.relative_to(EMBEDDED_SCENE).as_posix(): file_digest(path)
            for path in sorted(EMBEDDED_SCENE.rglob("*"))
            if path.is_file()
        }
    )


def materialise(out: str | Path, progress=None) -> Path:
    """Write the embedded scene (shipped workspace + regenerated ground truth) to ``out``; a
    folder written from another version of the shipped scene is written anew."""
    out = Path(out)
    complete = out / ".embedded-scene-complete"
    shipped = _shipped_fingerprint()
    if complete.is_file():
        if complete.read_text().split()[-1:] == [shipped]:
            return out  # a rerun: this scene was written in full before
        if progress:
            progress("the shipped scene changed since this folder was written: writing it anew")
    generate(out, EMBEDDED_OPTIONS, progress=progress)
    # The shipped workspace is the reference input: put its exact bytes in place.
    for part in ("images", "sparse", "stereo"):
        shutil.copytree(EMBEDDED_SCENE / part, out / part, dirs_exist_ok=True)
    # Written last, so that an interrupted run is redone rather than taken as finished.
    complete.write_text(f"dvpmvs embedded scene {shipped}\n")
    return out
