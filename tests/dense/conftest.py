"""The dense stage's scenes: the tabletop with the whole stage run once, at the size the records
and formats are checked on and at the size its stated accuracy is for."""

import pytest

from tests.dense.tabletop import SMALL, tabletop_run


@pytest.fixture(scope="module")
def dense_scene(tmp_path_factory):
    """The tabletop scene, 4 views of 96x72, with the whole dense stage run once."""
    return tabletop_run(tmp_path_factory, SMALL[0])


@pytest.fixture(scope="module")
def accuracy_scene(tmp_path_factory):
    """The tabletop scene, 4 views of 200x150 (the size its stated accuracy is for), run once."""
    return tabletop_run(tmp_path_factory, 200)
