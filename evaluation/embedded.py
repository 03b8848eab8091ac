"""The embedded default scene: a small synthetic room shipped with the package.

``scenes/room/`` holds the COLMAP workspace (``images/``, ``sparse/``, ``stereo/``) of
``dvpmvs synth scene=room views=5 width=320 seed=0``; its ground truth and simulated priors
(about 18 MB) are not shipped but regenerated from the same parameters, which the generator
reproduces byte for byte. ``materialise`` writes the whole scene to a folder.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from dvpmvs.evaluation.synthetic import SynthOptions, generate

__all__ = ["EMBEDDED_SCENE", "EMBEDDED_OPTIONS", "materialise"]

EMBEDDED_SCENE = Path(__file__).parent / "scenes" / "room"
EMBEDDED_OPTIONS = SynthOptions(scene="room", views=5, width=320, seed=0)


def materialise(out: str | Path, progress=None) -> Path:
    """Write the embedded scene (shipped workspace + regenerated ground truth) to ``out``."""
    out = Path(out)
    complete = out / ".embedded-scene-complete"
    if complete.is_file():
        return out  # a rerun: the scene was written in full before
    generate(out, EMBEDDED_OPTIONS, progress=progress)
    # The shipped workspace is the reference input: put its exact bytes in place.
    for part in ("images", "sparse", "stereo"):
        shutil.copytree(EMBEDDED_SCENE / part, out / part, dirs_exist_ok=True)
    # Written last, so that an interrupted run is redone rather than taken as finished.
    complete.write_text("dvpmvs embedded scene\n")
    return out
