"""Checks that run before any compute: option types and the writability of output folders.

Options objects check their ranges themselves; :func:`check_field_types` checks the types their
annotations declare, so that ``planar_prior=maybe`` or ``num_iterations=2.5`` stops the run at
its start with the option named, instead of counting as true or failing halfway through.
"""

from __future__ import annotations

import dataclasses
import math
import os
import tempfile
import types
import typing
from pathlib import Path

from dvpmvs.errors import DvpmvsError

__all__ = [
    "OutputNotWritableError",
    "check_value",
    "check_field_types",
    "simple_types",
    "check_ply_output",
    "check_threads",
    "check_writable",
    "max_threads",
]

# Threads per core a run may ask for: a little oversubscription can pay (hyper-threads the OS
# does not report); thousands make OpenMP fail to start them, or crash.
_THREADS_PER_CORE = 4


class OutputNotWritableError(DvpmvsError, PermissionError):
    """An output folder cannot be written."""


def simple_types(annotation) -> tuple[type, ...] | None:
    """The plain types an annotation allows (``bool``, ``int``, ``float``, ``str``, and those
    with ``None``), or None for annotations this check leaves to the options themselves."""
    allowed = []
    args = (
        typing.get_args(annotation)
        if typing.get_origin(annotation) in (typing.Union, types.UnionType)
        else (annotation,)
    )
    for arg in args:
        if arg in (bool, int, float, str, type(None)):
            allowed.append(arg)
        else:
            return None
    return tuple(allowed)


def _describe(allowed: tuple[type, ...]) -> str:
    words = {
        bool: "true or false",
        int: "an integer",
        float: "a number",
        str: "a string",
        type(None): "null",
    }
    return " or ".join(words[t] for t in allowed)


def check_value(name: str, value, allowed: tuple[type, ...]):
    """``value`` if it is one of the ``allowed`` plain types, else ``ValueError`` naming ``name``.

    ``bool`` takes only true/false (not 0/1, not strings); ``int`` only integers (not 2.5, not
    true); ``float`` integers or numbers (not NaN), returned as float so that ``perturbation=1``
    and ``perturbation=1.0`` are one configuration.
    """
    if value is None:
        ok = type(None) in allowed
    elif isinstance(value, bool):
        ok = bool in allowed
    elif isinstance(value, int):
        ok = int in allowed or float in allowed
        if ok and int not in allowed:
            value = float(value)
    elif isinstance(value, float):
        ok = float in allowed and not math.isnan(value)
    else:
        ok = isinstance(value, str) and str in allowed
    if not ok:
        raise ValueError(f"{name} must be {_describe(allowed)}, got {value!r}")
    return value


def check_field_types(options, prefix: str = "") -> None:
    """Check (and normalise) the fields of a frozen options dataclass against their annotations
    (:func:`check_value`); raises ``ValueError`` naming ``prefix + field``, the value given and
    what the field takes. Call it first in ``__post_init__``.
    """
    hints = typing.get_type_hints(type(options))
    for field in dataclasses.fields(options):
        allowed = simple_types(hints.get(field.name))
        if allowed is not None:
            value = getattr(options, field.name)
            checked = check_value(prefix + field.name, value, allowed)
            if checked is not value:
                object.__setattr__(options, field.name, checked)


def resolve_threads(num_threads: int, shared_by: int = 1) -> int:
    """The threads to start for a ``num_threads`` option: the value itself, or for 0 (every core)
    this machine's cores, divided between ``shared_by`` jobs or workers running side by side."""
    if num_threads > 0:
        return num_threads
    return max(1, (os.cpu_count() or 1) // max(1, shared_by))


def max_threads() -> int:
    """The most threads a kernel may be asked to start: a few per core of this machine."""
    return _THREADS_PER_CORE * max(os.cpu_count() or 1, 1)


def check_threads(key: str, value: int) -> None:
    """``value`` as a thread count: 0 (every core) or 1 to :func:`max_threads`; ``ValueError``
    naming ``key`` otherwise."""
    if value < 0:
        raise ValueError(f"{key} must be >= 0 (0: every core), got {value}")
    if value > max_threads():
        raise ValueError(
            f"{key}={value} is more threads than this machine can run: it has {os.cpu_count()} cores; "
            f"give 0 (every core) or at most {max_threads()}"
        )


def check_writable(folder: str | Path, what: str, hint: str = "") -> None:
    """Make sure files can be created in ``folder`` (created if missing) before any compute, so
    that a read-only location stops the run at its start, naming the folder."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise OutputNotWritableError(
            f"{what} {folder} is a file, not a folder" + (f"; {hint}" if hint else "")
        )
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".dvpmvs-write-check.", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise OutputNotWritableError(
            f"cannot write to {what} {folder} ({reason})" + (f"; {hint}" if hint else "")
        ) from None


def check_ply_output(path: Path, kind: str, example: str) -> None:
    """``output=PATH`` for a file written as binary PLY (``kind``: what is written, plural, e.g.
    ``fused clouds``): not a folder, a name ending in ``.ply`` (another suffix would promise
    another format), in a folder this process can write. ``example``: a file name for the message."""
    path = Path(path)
    if path.is_dir():
        raise OutputNotWritableError(
            f"output={path} is a folder; output= names the file to write, e.g. "
            f"output={path / example}"
        )
    if path.suffix.lower() != ".ply":
        raise OutputNotWritableError(
            f"output={path}: {kind} are written as binary PLY; give a file name ending in .ply"
        )
    check_writable(
        path.parent, "the folder of output=", "give output=PATH in a folder you can write"
    )
