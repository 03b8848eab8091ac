"""WorkspaceOptions (dvpmvs/options/workspace.py): image size, depth ranges and sources, checked on construction."""

import pytest

from dvpmvs.options import MIN_IMAGE_SIZE, WorkspaceOptions

pytestmark = pytest.mark.smoke


@pytest.mark.parametrize(
    "bad,message",
    [
        ({"depth_quantiles": (0.9, 0.1)}, "depth_quantiles must satisfy 0 <= lo < hi <= 1"),
        ({"depth_margin": 1.0}, r"depth_margin must be in \[0, 1\)"),
        ({"min_points_for_range": 0}, "min_points_for_range must be >= 1"),
        ({"depth_range": (5.0, 3.0)}, "depth_range must be finite with 0 < min < max"),
        ({"depth_range": (0.0, float("inf"))}, "depth_range must be finite"),
        ({"default_num_sources": 0}, "default_num_sources must be >= 1"),
        ({"resolution_level": -1}, "resolution_level must be >= 0"),
        (
            {"min_resolution": MIN_IMAGE_SIZE - 1},
            f"min_resolution must be at least {MIN_IMAGE_SIZE} pixels",
        ),
        (
            {"max_image_size": MIN_IMAGE_SIZE - 1},
            f"max_image_size must be -1 .* or at least {MIN_IMAGE_SIZE} pixels",
        ),
    ],
)
def test_a_bad_option_is_named(bad, message):
    with pytest.raises(ValueError, match=message):
        WorkspaceOptions(**bad)


def test_the_size_limits_accept_their_bounds():
    assert WorkspaceOptions(max_image_size=MIN_IMAGE_SIZE).max_image_size == MIN_IMAGE_SIZE
    assert WorkspaceOptions(max_image_size=-1, min_resolution=MIN_IMAGE_SIZE).max_image_size == -1
    assert WorkspaceOptions(max_image_size=0).max_image_size == 0  # <= 0 keeps the images' own size
    assert WorkspaceOptions(depth_range=(1, 2)).depth_range == (1, 2)
