"""Compiled kernels carry the digest of their source; a stale build is refused on import."""

import importlib
from pathlib import Path

import pytest

from dvpmvs._kernel_sources import require_current, source_beside, source_digest

# Also run on the other Pythons `make test` checks (scripts/other_pythons.py).
pytestmark = pytest.mark.smoke

KERNELS = [
    "dvpmvs._fusion",
    "dvpmvs._image",
    "dvpmvs.patchmatch._anchors",
    "dvpmvs.patchmatch._patchmatch",
    "dvpmvs.patchmatch._upsample",
    "dvpmvs.evaluation._accuracy",
]


@pytest.mark.parametrize("name", KERNELS)
def test_each_kernel_was_built_from_the_source_beside_it(name):
    module = importlib.import_module(name)
    source = source_beside(module)
    assert source.is_file()
    assert len(module.SOURCE_DIGEST) == 64 and module.SOURCE_DIGEST == source_digest(source)
    require_current(module)


def test_a_kernel_edited_since_its_build_is_refused(tmp_path):
    module = importlib.import_module("dvpmvs._image")
    edited = tmp_path / "dvpmvs" / "_image.pyx"
    edited.parent.mkdir()
    (tmp_path / "dvpmvs" / "__init__.py").write_text("")
    original = source_beside(module).read_text()
    edited.write_text(original + "\n# one more line\n")
    with pytest.raises(ImportError, match="_image.pyx.*rebuild the kernels"):
        require_current(module, edited)


def test_the_digest_covers_the_cimported_declarations(tmp_path):
    # _image.pyx cimports dvpmvs._sampling: an edited .pxd changes what the kernel compiles to.
    package = tmp_path / "dvpmvs"
    package.mkdir()
    (package / "__init__.py").write_text("")
    root = Path(importlib.import_module("dvpmvs").__file__).parent
    for name in ("_image.pyx", "_sampling.pxd", "_digest.pxd"):
        (package / name).write_text((root / name).read_text())
    before = source_digest(package / "_image.pyx")
    assert before == source_digest(root / "_image.pyx")
    (package / "_sampling.pxd").write_text((root / "_sampling.pxd").read_text() + "\n")
    assert source_digest(package / "_image.pyx") != before
