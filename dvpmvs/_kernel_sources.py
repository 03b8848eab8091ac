"""Which source a compiled kernel was built from, so that a stale build is refused.

``setup.py`` hashes each ``_name.pyx`` together with the dvpmvs ``.pxd`` files it cimports
(directly or through other ``.pxd`` files) and the C headers they include, and compiles the
digest into the extension (``SOURCE_DIGEST``, through :mod:`dvpmvs._digest`). In a
source checkout, where the ``.pyx`` lies beside its compiled module, :func:`require_current`
compares the two on import: a kernel edited (or reverted) without a rebuild would otherwise run
silently, and every figure taken with it would belong to code that no commit holds.
Where no ``.pyx`` lies beside a compiled module (an installed wheel may ship none), nothing is
compared.
This module imports nothing from dvpmvs: ``setup.py`` loads it by path before anything is built.
"""

from __future__ import annotations

import hashlib
import importlib
import re
from pathlib import Path
from types import ModuleType

# The compiled modules whose code shapes maps (a map's record names their digests).
MAP_KERNELS = (
    "dvpmvs._image",
    "dvpmvs._fusion",
    "dvpmvs.patchmatch._patchmatch",
    "dvpmvs.patchmatch._upsample",
)

_CIMPORT = re.compile(
    r"^\s*(?:from\s+dvpmvs\.([\w.]+)\s+cimport|cimport\s+dvpmvs\.([\w.]+))", re.MULTILINE
)
_HEADER = re.compile(r"^\s*cdef\s+extern\s+from\s+\"([\w./-]+\.h)\"", re.MULTILINE)


def _dependencies(source: Path, package_root: Path | None) -> list[Path]:
    """The dvpmvs ``.pxd`` files ``source`` cimports and the headers it includes (beside it)."""
    text = source.read_text(encoding="utf-8")
    found = [source.parent / name for name in _HEADER.findall(text)]
    if package_root is not None:
        for a, b in _CIMPORT.findall(text):
            found.append(package_root / "dvpmvs" / Path(*(a or b).split(".")).with_suffix(".pxd"))
    return [path for path in found if path.is_file()]


def source_digest(pyx: str | Path) -> str:
    """SHA-256 of a ``.pyx`` file and of every file it compiles with: the dvpmvs ``.pxd`` files
    it cimports, directly or through other ``.pxd`` files, and the C headers any of them
    includes (sorted by path)."""
    pyx = Path(pyx)
    package_root = next(
        (p for p in pyx.resolve().parents if (p / "dvpmvs" / "__init__.py").is_file()), None
    )
    seen: set[Path] = set()
    pending = _dependencies(pyx, package_root)
    while pending:
        path = pending.pop()
        if path not in seen:
            seen.add(path)
            if path.suffix == ".pxd":
                pending.extend(_dependencies(path, package_root))
    digest = hashlib.sha256(pyx.read_bytes())
    for path in sorted(seen, key=lambda p: p.name):
        digest.update(path.read_bytes())
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
            f"`python setup.py build_ext --inplace`"
        )


def kernel_digests() -> dict[str, str]:
    """The source digest compiled into each map-making kernel (``SOURCE_DIGEST``), by module
    name (imported here, on call: ``setup.py`` loads this module before they are built)."""
    return {
        name: getattr(importlib.import_module(name), "SOURCE_DIGEST", "") for name in MAP_KERNELS
    }
