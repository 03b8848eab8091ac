"""The estimator's passes name COLMAP's map files and its fusion's input types."""

import pytest

from dvpmvs.maps import map_path
from dvpmvs.passes import Pass


def test_a_pass_is_the_word_colmap_writes_in_its_map_names():
    assert [p.value for p in Pass] == ["photometric", "geometric"]  # COLMAP's --input_type values
    assert Pass("geometric") is Pass.GEOMETRIC and Pass.GEOMETRIC == "geometric"
    assert (
        map_path("stereo", "a b.png", "depth", "photometric").as_posix()
        == "stereo/depth_maps/a b.png.photometric.bin"
    )
    with pytest.raises(ValueError):
        Pass("fused")
