"""MeshingOptions (dvpmvs/options/meshing.py): the mesher and its parameters, checked on construction."""

import pytest

from dvpmvs.options import MeshingOptions

pytestmark = pytest.mark.smoke


@pytest.mark.parametrize(
    "bad,message",
    [
        (
            {"method": "ball_pivoting"},
            "meshing.method must be one of poisson, colmap_poisson, delaunay",
        ),
        ({"depth": 4}, r"meshing.depth must be in \[5, 16\]"),
        ({"depth": 17}, r"meshing.depth must be in \[5, 16\]"),
        ({"trim_quantile": 1.0}, r"meshing.trim_quantile must be in \[0, 1\)"),
        ({"colmap_trim": -1}, "meshing.colmap_trim must be >= 0"),
        ({"num_threads": -1}, "meshing.num_threads"),
        ({"depth": 8.5}, "meshing.depth"),
    ],
)
def test_a_bad_option_is_named_with_its_key(bad, message):
    with pytest.raises(ValueError, match=message):
        MeshingOptions(**bad)


def test_the_default_meshes_on_one_thread_for_reproducible_bytes():
    assert MeshingOptions().num_threads == 1 and MeshingOptions().method == "poisson"
    assert MeshingOptions(method="delaunay", depth=5, trim_quantile=0).depth == 5
