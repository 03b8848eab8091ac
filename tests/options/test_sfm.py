"""SfmOptions (dvpmvs/options/sfm.py): structure from motion's options, checked against COLMAP's models."""

import pytest

from dvpmvs.options import SfmOptions

pytestmark = pytest.mark.smoke


@pytest.mark.parametrize(
    "bad,message",
    [
        (
            {"camera_model": "FISHEYE_9"},
            "sfm.camera_model 'FISHEYE_9' is not a COLMAP camera model; one of",
        ),
        ({"camera_params": "500,a"}, "sfm.camera_params must be comma-separated numbers"),
        (
            {"camera_model": "PINHOLE", "camera_params": "500,320,240"},
            "sfm.camera_params has 3 values; PINHOLE takes 4",
        ),
        (
            {"matching": "vocab_tree"},
            "sfm.matching must be one of auto, exhaustive, sequential, spatial",
        ),
        ({"sequential_overlap": 0}, "sfm.sequential_overlap must be >= 1"),
        ({"num_threads": -3}, "sfm.num_threads"),
    ],
)
def test_a_bad_option_is_named_with_its_key(bad, message):
    with pytest.raises(ValueError, match=message):
        SfmOptions(**bad)


def test_known_intrinsics_and_the_matcher_auto_chooses():
    assert SfmOptions(camera_model="PINHOLE", camera_params="500,500,320,240").camera_params
    options = SfmOptions(exhaustive_max_images=10)
    assert options.matcher(10) == "exhaustive" and options.matcher(11) == "sequential"
    assert SfmOptions(matching="spatial").matcher(3) == "spatial"
