"""DenseOptions (dvpmvs/options/dense.py): the dense stage's passes and its fusion backend."""

from dataclasses import FrozenInstanceError, replace

import pytest

from dvpmvs.options import DenseOptions, FusionOptions
from dvpmvs.passes import Pass

pytestmark = pytest.mark.smoke


def test_the_passes_follow_the_geometric_switch():
    assert (
        DenseOptions().passes == [Pass.PHOTOMETRIC, Pass.GEOMETRIC]
        and DenseOptions().final_pass is Pass.GEOMETRIC
    )
    alone = DenseOptions(geometric=False)
    assert alone.passes == [Pass.PHOTOMETRIC] and alone.final_pass is Pass.PHOTOMETRIC


def test_a_bad_backend_or_type_is_named_and_the_options_are_frozen():
    with pytest.raises(
        ValueError, match="unknown fusion backend 'openmvs'; choose dvpmvs or colmap"
    ):
        DenseOptions(fusion_backend="openmvs")
    with pytest.raises(ValueError, match="geometric"):
        DenseOptions(geometric="yes")
    with pytest.raises(FrozenInstanceError):
        DenseOptions().fuse = False


def test_dense_options_validate():
    with pytest.raises(ValueError, match="fusion backend"):
        DenseOptions(fusion_backend="openmvs")
    with pytest.raises(ValueError):
        FusionOptions(max_normal_error=0)
    with pytest.raises(ValueError):
        FusionOptions(input_type="final")
    assert replace(DenseOptions(), geometric=False).final_pass is Pass.PHOTOMETRIC
