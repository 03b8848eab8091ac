"""The benchmark's scenes (``dvpmvs.evaluation.bench``): rendered once, reused while their
content is what was rendered."""

import cv2
import pytest

from dvpmvs.errors import DvpmvsError
from dvpmvs.evaluation.bench import render_scene, rendered_digest


def test_a_scene_changed_since_it_was_rendered_is_not_the_render(tmp_path):
    workspace = render_scene(tmp_path / "room", "room", views=2, width=64, seed=0)
    digest = rendered_digest(workspace)
    assert rendered_digest(workspace) == digest  # read again: the same content, the same digest
    image = next((workspace / "images").iterdir())
    pixels = cv2.imread(str(image))
    pixels[:, : pixels.shape[1] // 2] = 0  # half of one image blackened
    cv2.imwrite(str(image), pixels)
    # Reused (its marker names the same inputs), but its digest is the content's.
    assert render_scene(workspace, "room", views=2, width=64, seed=0) == workspace
    with pytest.raises(DvpmvsError, match=r"changed since it was rendered \(differing: images\)"):
        rendered_digest(workspace)
