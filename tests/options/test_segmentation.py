"""SegmentationOptions (dvpmvs/options/segmentation.py): the aligned prior's options and Table V's symbols."""

import pytest

from dvpmvs.options import PAPER_SYMBOLS, SegmentationOptions

pytestmark = pytest.mark.smoke


@pytest.mark.parametrize(
    "bad,message",
    [
        ({"min_region": 2}, "min_region must be >= 3"),
        ({"plane_similarity": 1.5}, r"plane_similarity must be in \[-1, 1\]"),
        ({"erosion_gain": 0}, "erosion_gain must be > 0"),
        ({"min_inlier_ratio": 0}, r"min_inlier_ratio must be in \(0, 1\]"),
        ({"adjacency_radius": 0}, "normal_search and adjacency_radius must be >= 1"),
        ({"seam_band": -1}, "seam_band must be >= 0"),
        ({"max_step_tilt": 0}, r"max_step_tilt must be in \(0, 180\]"),
        ({"filter_iterations": 0}, "filter_iterations must be >= 1"),
        ({"ransac_points": 2}, "ransac_points >= 3"),
        ({"erosion": "off"}, "segmentation.erosion"),
    ],
)
def test_a_bad_option_is_named(bad, message):
    with pytest.raises(ValueError, match=message):
        SegmentationOptions(**bad)


def test_the_papers_symbols_stand_for_their_options_and_unknown_keys_are_named():
    options = SegmentationOptions.from_mapping({"eta": 800, "kappa": 0.6, "phi": None, "seed": 3})
    assert (options.min_region, options.min_inlier_ratio, options.seed) == (800, 0.6, 3)
    assert (
        options.normal_similarity == SegmentationOptions().normal_similarity
    )  # None: the option holds
    assert set(PAPER_SYMBOLS) == {"eta", "varphi", "phi", "gamma", "kappa", "delta"}
    with pytest.raises(ValueError, match="unknown segmentation option.*min_regoin"):
        SegmentationOptions.from_mapping({"min_regoin": 3})
