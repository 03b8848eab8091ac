"""Digests: the fingerprint of a tree of inputs, and of files and source folders (a leaf).

A fingerprint is the SHA-256 of the inputs in canonical JSON, so that the same inputs give the
same fingerprint whatever their Python types (tuples, arrays, numpy scalars, enums, paths); a
file's digest is remembered for the process while its size, time and inode stay the same.
"""

from __future__ import annotations

import enum
import hashlib
import json
import math
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "canonical",
    "differences",
    "file_digest",
    "file_stamp",
    "fingerprint",
    "matches_stamp",
    "sources_digest",
]

_SOURCE_SUFFIXES = (".py", ".pyx", ".pxd")


def canonical(value: Any) -> Any:
    """``value`` as plain JSON data with one spelling per value: mappings with string keys,
    lists for tuples and arrays, Python scalars, and the strings ``inf``, ``-inf``, ``nan`` for
    the floats JSON has no literal for (so that the records are standard JSON)."""
    if isinstance(value, Mapping):
        return {str(k): canonical(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [canonical(v) for v in value]
    if isinstance(value, np.ndarray):
        return canonical(value.tolist())
    if isinstance(value, np.generic):
        return canonical(value.item())
    if isinstance(value, enum.Enum):
        return canonical(value.value)
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return value
    if value is None or isinstance(value, (bool, int, str)):
        return value
    raise TypeError(f"cannot fingerprint a {type(value).__name__}: {value!r}")


def fingerprint(inputs: Mapping[str, Any]) -> str:
    """SHA-256 (hex) of ``inputs`` in canonical JSON (sorted keys, no spaces)."""
    text = json.dumps(canonical(inputs), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def differences(
    old: Mapping[str, Any], new: Mapping[str, Any], prefix: str = ""
) -> list[tuple[str, Any, Any]]:
    """The leaves that differ between two input trees: ``(dotted key, old, new)``, a missing
    side as None, sorted by key."""
    old, new = canonical(old), canonical(new)
    found = []
    for key in sorted(set(old) | set(new)):
        a, b = old.get(key), new.get(key)
        name = f"{prefix}{key}"
        if isinstance(a, dict) and isinstance(b, dict):
            found += differences(a, b, name + ".")
        elif a != b:
            found.append((name, a, b))
    return found


# -- files -------------------------------------------------------------------------------------

_digests: dict[tuple, str] = {}


def file_digest(path: str | Path) -> str:
    """SHA-256 (hex) of a file's bytes; remembered for the process while the file's size,
    modification time and inode stay the same (images are read by many views' fingerprints)."""
    path = Path(path)
    st = path.stat()
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns, st.st_ino)
    digest = _digests.get(key)
    if digest is None:
        sha = hashlib.sha256()  # hashlib.file_digest is Python 3.11+; the same digest in chunks
        with open(path, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                sha.update(chunk)
        digest = sha.hexdigest()
        _digests[key] = digest
    return digest


def file_stamp(path: str | Path) -> dict:
    """``{"size", "mtime_ns", "sha256"}`` of a file."""
    st = Path(path).stat()
    return {"size": st.st_size, "mtime_ns": st.st_mtime_ns, "sha256": file_digest(path)}


def matches_stamp(path: Path, stamp: Mapping[str, Any]) -> bool:
    """True when ``path`` holds the bytes ``stamp`` describes. Size and modification time
    decide when both agree (as git's index does); otherwise the content's digest does (a copy
    with a new time is still the same map)."""
    try:
        st = path.stat()
    except OSError:
        return False
    if st.st_size != stamp.get("size"):
        return False
    if st.st_mtime_ns == stamp.get("mtime_ns"):
        return True
    return file_digest(path) == stamp.get("sha256")


def sources_digest(folder: str | Path, exclude: Iterable[str] = ()) -> str:
    """SHA-256 of the Python and Cython sources under ``folder`` (names and bytes), leaving out
    the top-level entries named in ``exclude``."""
    folder = Path(folder)
    digest = hashlib.sha256()
    for path in sorted(p for p in folder.rglob("*") if p.suffix in _SOURCE_SUFFIXES):
        rel = path.relative_to(folder)
        if rel.parts[0] in exclude or "__pycache__" in rel.parts:
            continue
        digest.update(rel.as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()
