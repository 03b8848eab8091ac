"""A stored product (``dvpmvs.dense.products``): its key, its record's status, whether a run makes
it."""

import pytest

from dvpmvs.dense.products import HIGHLIGHTS, MASK, Product, product_key
from dvpmvs.passes import Pass
from dvpmvs.provenance import CachedOutput, Status
from dvpmvs.workspace import Workspace


@pytest.fixture
def view(workspace_dir):
    return Workspace.open(workspace_dir[0]).reference_views()[0]


def _product(tmp_path, kind, inputs, view):
    files = {"depth": tmp_path / "depth.bin"}
    stored = CachedOutput.check(tmp_path / "record.json", inputs, tmp_path, files.values())
    return Product(kind, view, stored, files)


def test_a_product_is_made_until_its_record_says_current(tmp_path, view):
    inputs = {"pass": "photometric", "value": 1}
    product = _product(tmp_path, Pass.PHOTOMETRIC.value, inputs, view)
    assert product.key == f"photometric:{view.name}"
    assert product.key == product_key(Pass.PHOTOMETRIC.value, view.name)
    assert product.pass_ is Pass.PHOTOMETRIC
    assert product.status is Status.MISSING and product.record is None
    assert product.wanted(overwrite=False)
    with product.stored.making():
        product.files["depth"].write_bytes(b"maps")
    product.stored.complete(product.files, {"seconds": 1.5})
    again = _product(tmp_path, Pass.PHOTOMETRIC.value, inputs, view)
    assert again.status is Status.CURRENT and again.record.stats == {"seconds": 1.5}
    assert again.fingerprint == product.fingerprint and again.inputs == inputs
    assert not again.wanted(overwrite=False) and again.wanted(overwrite=True)
    other = _product(tmp_path, Pass.PHOTOMETRIC.value, {**inputs, "value": 2}, view)
    assert other.status is Status.STALE and other.wanted(overwrite=False)


def test_files_without_a_record_are_foreign_and_a_failed_make_keeps_them_so(tmp_path, view):
    (tmp_path / "depth.bin").write_bytes(b"COLMAP's")
    product = _product(tmp_path, MASK, {"stage": "mask"}, view)
    assert product.status is Status.FOREIGN and product.wanted(overwrite=False)
    with pytest.raises(FileExistsError, match="overwrite=true"):
        product.stored.making(overwrite=False)
    # A make that fails before it changed a file leaves no record behind.
    with pytest.raises(RuntimeError), product.stored.making(overwrite=True):
        raise RuntimeError("provider failed")
    assert not (tmp_path / "record.json").exists()
    assert _product(tmp_path, HIGHLIGHTS, {"stage": "mask"}, view).status is Status.FOREIGN


def test_a_make_cut_off_after_writing_reads_as_interrupted(tmp_path, view):
    product = _product(tmp_path, Pass.GEOMETRIC.value, {"pass": "geometric"}, view)
    with pytest.raises(KeyboardInterrupt), product.stored.making():
        product.files["depth"].write_bytes(b"half")
        raise KeyboardInterrupt
    again = _product(tmp_path, Pass.GEOMETRIC.value, {"pass": "geometric"}, view)
    assert again.status is Status.INTERRUPTED
