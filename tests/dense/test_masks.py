"""Each view's mask made once and kept (``dvpmvs.dense.masks``): COLMAP's layout, its record,
reuse, a file dvpmvs did not write."""

from dataclasses import dataclass

import cv2
import numpy as np
import pytest

from dvpmvs.dense.masks import MaskStore, mask_path
from dvpmvs.provenance import ForeignOutputError
from tests.helpers import read_only


@dataclass
class _View:
    name: str
    height: int = 12
    width: int = 16

    def load_rgb(self):
        return np.zeros((self.height, self.width, 3), np.float32)


class _Counted:
    """A provider's calls, counted (the provider runs as it is)."""

    def __init__(self, provider):
        self.provider, self.calls = provider, []
        self.costly = getattr(provider, "costly", False)

    def __call__(self, view, root):
        self.calls.append(view.name)
        return self.provider(view, root)

    def __getattr__(self, name):  # input_files: the provenance of the files read
        return getattr(self.provider, name)


def _left_half_masks(folder, names, size=(12, 16)):
    """Masks in COLMAP's layout that mask the left half of each view."""
    for name in names:
        mask = np.full(size, 255, np.uint8)
        mask[:, : size[1] // 2] = 0
        path = folder / f"{name}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(path), mask)


def _store(tmp_path, **kwargs):
    store = MaskStore.from_config(
        {"name": "files", "path": str(tmp_path / "masks")}, tmp_path / "stereo", tmp_path, **kwargs
    )
    store.masks.provider = _Counted(store.masks.provider)
    return store


VIEWS = [_View("a.png"), _View("sub/b.png")]


def test_a_mask_is_made_once_kept_in_colmaps_layout_and_reused(tmp_path):
    _left_half_masks(tmp_path / "masks", ["a.png", "sub/b.png"])
    store = _store(tmp_path)
    store.prepare(VIEWS)  # every view's mask, before any compute
    for view in VIEWS * 2:
        keep = store.load(view)
        assert keep.dtype == bool and keep.shape == (12, 16)
        assert not keep[:, :8].any() and keep[:, 8:].all()
    assert store.masks.provider.calls == ["a.png", "sub/b.png"]
    stored = cv2.imread(str(mask_path(tmp_path / "stereo", "sub/b.png")), cv2.IMREAD_GRAYSCALE)
    assert set(np.unique(stored)) == {0, 255} and (stored[:, :8] == 0).all()
    assert (tmp_path / "stereo" / "provenance" / "sub" / "b.png.mask.json").is_file()
    # A later run with the same provider and files reads the stored masks ...
    again = _store(tmp_path)
    assert again.stored_folder(VIEWS) == tmp_path / "stereo" / "mask_maps"
    assert again.masks.provider.calls == []
    # ... and makes anew a mask whose file changed, or a view of another size.
    _left_half_masks(tmp_path / "masks", ["a.png"], size=(24, 32))
    again.load(_View("a.png", 24, 32))
    again.load(_View("sub/b.png", 6, 8))
    assert again.masks.provider.calls == ["a.png", "sub/b.png"]


def test_a_costly_providers_check_is_the_first_views_mask(tmp_path):
    _left_half_masks(tmp_path / "masks", ["a.png", "sub/b.png"])
    store = _store(tmp_path)
    store.masks.provider.costly = True
    store.prepare(VIEWS)
    assert store.masks.provider.calls == ["a.png"]


def test_a_file_dvpmvs_did_not_write_is_kept_unless_overwrite(tmp_path):
    _left_half_masks(tmp_path / "masks", ["a.png"])
    theirs = mask_path(tmp_path / "stereo", "a.png")
    theirs.parent.mkdir(parents=True)
    cv2.imwrite(str(theirs), np.full((12, 16), 255, np.uint8))
    with pytest.raises(ForeignOutputError, match="overwrite=true"):
        _store(tmp_path).load(_View("a.png"))
    assert (cv2.imread(str(theirs), cv2.IMREAD_GRAYSCALE) == 255).all()
    assert not _store(tmp_path, overwrite=True).load(_View("a.png"))[:, :8].any()


def test_a_read_only_folder_keeps_the_masks_in_memory(tmp_path):
    _left_half_masks(tmp_path / "masks", ["a.png"])
    (tmp_path / "stereo").mkdir()
    with read_only(tmp_path / "stereo"):
        store = _store(tmp_path)
        for _ in range(2):
            store.load(_View("a.png"))
        assert store.masks.provider.calls == ["a.png"]
        assert store.stored_folder([_View("a.png")]) is None
        assert not (tmp_path / "stereo" / "mask_maps").exists()
