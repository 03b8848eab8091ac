"""PatchMatchOptions (dvpmvs/options/patch_match.py) validates itself and names unknown keys."""

import pytest

from dvpmvs.options.patch_match import VISIBILITY_MAX_ERROR
from dvpmvs.patchmatch import PatchMatchOptions

# Also run on the other Pythons `make test` checks (scripts/other_pythons.py).
pytestmark = pytest.mark.smoke


@pytest.mark.parametrize(
    "bad",
    [
        {"window_step": 0},
        {"max_sources": 40},
        {"num_threads": -1},
        {"perturbation": 0.001},
        {"window_radius": 15, "deform_centre_step": 1},
        {"deform_anchor_step": 0},
        {"deform_anchor_step": 6},
        {"image_sigma": -0.5},
        {"geom_weight": -0.1},
        # The anchors' visibility threshold reads the reprojection error clipped there.
        {"geom_max_error": VISIBILITY_MAX_ERROR},
    ],
)
def test_options_validate_themselves(bad):
    with pytest.raises(ValueError):
        PatchMatchOptions(**bad)


def test_options_from_mapping_names_unknown_keys():
    with pytest.raises(ValueError, match="num_iteration"):
        PatchMatchOptions.from_mapping({"num_iteration": 3})
