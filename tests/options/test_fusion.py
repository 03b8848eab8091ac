"""FusionOptions (dvpmvs/options/fusion.py): COLMAP's StereoFusionOptions, checked on construction."""

import pytest

from dvpmvs.options import FusionOptions

pytestmark = pytest.mark.smoke


@pytest.mark.parametrize(
    "bad,message",
    [
        ({"min_consistent_views": 0}, "min_consistent_views must be >= 1"),
        ({"max_reproj_error": 0}, "must be > 0"),
        ({"max_depth_error": -0.01}, "must be > 0"),
        ({"max_normal_error": 181}, r"max_normal_error in \(0, 180\]"),
        ({"colmap_max_reproj_error": 0}, "must be > 0"),
        ({"input_type": "fused"}, "'fused' is not a valid Pass"),
        ({"max_neighbours": 65}, r"max_neighbours must be in \[1, 64\]"),
        ({"cache_views": 1}, "cache_views must be >= 2"),
        ({"num_threads": -1}, "num_threads"),
        ({"point_average": "mode"}, "point_average must be 'median' or 'mean'"),
        ({"allow_missing": "no"}, "fusion_options.allow_missing"),
    ],
)
def test_a_bad_option_is_named(bad, message):
    with pytest.raises(ValueError, match=message):
        FusionOptions(**bad)


def test_the_defaults_are_colmaps_where_the_method_does_not_differ():
    options = FusionOptions()
    # COLMAP's min_num_pixels 3 and max_reproj_error 2 px; the normal threshold is the method's 30 degrees.
    assert options.min_consistent_views + 1 == 3 and options.max_reproj_error == 2.0
    assert options.input_type == "geometric" and options.point_average == "median"
    assert FusionOptions(input_type="photometric", point_average="mean").input_type == "photometric"
