"""Which source a compiled kernel was built from, so that a stale build is refused.

``setup.py`` hashes each ``_name.pyx`` together with the dvpmvs ``.pxd`` files it cimports and
compiles the digest into the extension (``SOURCE_DIGEST``, through :mod:`dvpmvs._digest`). In a
source checkout, where the ``.pyx`` lies beside its compiled module, :func:`require_current`
compares the two on import: a kernel edited (or reverted) without a rebuild would otherwise run
silently, and every figure taken with it would belong to code that no commit holds.
Where no ``.pyx`` lies beside a compiled module (an installed wheel may ship none), nothing is
compared.
This module imports nothing from dvpmvs: ``setup.py`` loads it by path before anything is built.
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path
from types import ModuleType

_CIMPORT = re.compile(r"^\s*(?:from\s+dvpmvs\.([\w.]+)\s+cimport|cimport\s+dvpmvs\.([\w.]+))", re.MULTILINE)


def source_digest(pyx: str | Path) -> str:
    """SHA-256 of a ``.pyx`` file and of the dvpmvs ``.pxd`` files it cimports (sorted by name)."""
    pyx = Path(pyx)
    text = pyx.read_bytes()
    package_root = next((p for p in pyx.resolve().parents if (p / "dvpmvs" / "__init__.py").is_file()), None)
    digest = hashlib.sha256(text)
    if package_root is not None:
        names = {a or b for a, b in _CIMPORT.findall(text.decode("utf-8"))}
        for name in sorted(names):
            pxd = package_root / "dvpmvs" / Path(*name.split(".")).with_suffix(".pxd")
            if pxd.is_file():
                digest.update(pxd.read_bytes())
    return digest.hexdigest()


def source_beside(module: ModuleType) -> Path:
    """The ``.pyx`` path beside a compiled module (``_name.cpython-*.so`` -> ``_name.pyx``)."""
    compiled = Path(module.__file__)
    return compiled.with_name(compiled.name.split(".")[0] + ".pyx")


def require_current(module: ModuleType, source: str | Path | None = None) -> None:
    """Raise ImportError when ``module`` was compiled from another version of its ``.pyx``.

    ``source``: the ``.pyx`` to compare with; by default :func:`source_beside` (if none is
    there, as in an installed package, nothing is checked)."""
    if source is None:
        source = source_beside(module)
        if not source.is_file():
            return
    built = getattr(module, "SOURCE_DIGEST", "")
    if built != source_digest(source):
        raise ImportError(
            f"{module.__file__} was compiled from another version of {source} (or of the .pxd files "
            f"it cimports); rebuild the kernels: `make setup`, `pip install -e .` or "
            f"`python setup.py build_ext --inplace`")
