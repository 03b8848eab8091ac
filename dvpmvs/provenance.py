"""Provenance: what made an output, so that a rerun reuses only what the same inputs made.

Every view's maps of a pass carry a *record* (``stereo/provenance/<image>.<pass>.json``): the
*inputs* that shape them (the resolved options of that pass, the view's calibration, depth
range and sources, the digests of the images and prior files read, the code and the numerical
libraries, and for the geometric pass the fingerprints of the photometric maps it read), their
*fingerprint* (SHA-256 of those inputs in canonical JSON), and a stamp of every file written
(size, modification time, SHA-256). A record is written *pending* before the first map of a
view and *complete* after the last, so an interrupted view is told from a finished one.

:func:`status` compares what is on disk with the fingerprint a run would produce:

- ``CURRENT``: a complete record with that fingerprint, every file as stamped: reuse;
- ``MISSING``, ``INTERRUPTED``, ``STALE`` (another fingerprint; :func:`differences` says which
  inputs changed), ``MODIFIED`` (a file differs from its stamp): recompute;
- ``FOREIGN``: maps without a record (written by COLMAP or by a dvpmvs older than records):
  neither reused nor overwritten unless the user asks (``overwrite=true``).

:class:`MapCache` shares finished maps between runs that write to different folders (the jobs
of a sweep): an entry per pass and fingerprint, filled and read through hard links.
"""

from __future__ import annotations

import enum
import hashlib
import json
import logging
import math
import os
import platform
import shutil
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import lru_cache
from importlib import metadata
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping

import numpy as np

from dvpmvs.maps import atomic_path

__all__ = ["Status", "Record", "canonical", "fingerprint", "differences", "file_digest", "file_stamp",
           "code_identity", "sources_digest", "environment", "matches_stamp", "record_path", "read_record",
           "write_record", "status", "MapCache",
           "LIBRARIES", "PROVENANCE_DIR"]

log = logging.getLogger(__name__)

PROVENANCE_DIR = "provenance"  # under stereo/, beside COLMAP's own folders (COLMAP ignores it)

# The numerical libraries the maps, clouds and scores depend on besides our code and the seed
# (another OpenCV renders other synthetic scenes and gives other maps; see constraints.txt).
LIBRARIES = ("numpy", "scipy", "opencv-python-headless", "pycolmap", "open3d", "onnxruntime")

_SOURCE_SUFFIXES = (".py", ".pyx", ".pxd")
_NOT_MAP_CODE = ("evaluation", "conf")  # installed inside the package but shaping no map


class Status(str, enum.Enum):
    """What a run finds where it would write a view's maps of a pass."""

    CURRENT = "current"
    MISSING = "missing"
    INTERRUPTED = "interrupted"
    STALE = "stale"
    MODIFIED = "modified"
    FOREIGN = "foreign"

    @property
    def reusable(self) -> bool:
        return self is Status.CURRENT


# -- fingerprints ------------------------------------------------------------------------------


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


def differences(old: Mapping[str, Any], new: Mapping[str, Any], prefix: str = "") -> list[tuple[str, Any, Any]]:
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


# -- code and environment ----------------------------------------------------------------------


@lru_cache(maxsize=1)
def code_identity() -> dict:
    """What code made an output: the dvpmvs version, a digest of the package's sources (Python
    and Cython, as installed: an edited checkout is another code), the digests the compiled
    kernels were built from, and the numerical libraries' versions."""
    from dvpmvs._version import __version__

    package = Path(__file__).resolve().parent
    return {"dvpmvs": __version__, "sources": sources_digest(package, exclude=_NOT_MAP_CODE),
            "kernels": kernel_digests(), "libraries": library_versions()}


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


def kernel_digests() -> dict[str, str]:
    """The source digest compiled into each map-making kernel (``SOURCE_DIGEST``)."""
    import dvpmvs._fusion as _fusion
    import dvpmvs._image as _image
    import dvpmvs.patchmatch._patchmatch as _patchmatch
    import dvpmvs.patchmatch._upsample as _upsample

    return {module.__name__: getattr(module, "SOURCE_DIGEST", "") for module in
            (_image, _fusion, _patchmatch, _upsample)}


def library_versions(names: Iterable[str] = LIBRARIES) -> dict[str, str | None]:
    versions = {}
    for name in names:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def environment() -> dict:
    """The machine a figure was measured on: Python, CPU model and core count, and the libraries."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"python": platform.python_version(), "cpu": cpu, "cores": os.cpu_count(),
            "libraries": library_versions()}


# -- records -----------------------------------------------------------------------------------


@dataclass
class Record:
    """What made one view's maps of one pass (or any other output).

    files: kind -> ``{"path"`` (relative to the folder the record describes), ``"size"``,
    ``"mtime_ns"``, ``"sha256"}``; extras: relative paths of files written beside them that
    are not checked (previews); stats: figures of the computation that made them (seconds,
    hypothesis evaluations...), so that a reused view still reports its cost."""

    fingerprint: str
    inputs: dict
    complete: bool = False
    files: dict[str, dict] = field(default_factory=dict)
    extras: list[str] = field(default_factory=list)
    stats: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"fingerprint": self.fingerprint, "state": "complete" if self.complete else "pending",
                "files": self.files, "extras": self.extras, "stats": canonical(self.stats),
                "inputs": canonical(self.inputs)}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> "Record":
        return cls(fingerprint=str(data["fingerprint"]), inputs=dict(data.get("inputs", {})),
                   complete=data.get("state") == "complete", files=dict(data.get("files", {})),
                   extras=list(data.get("extras", [])), stats=dict(data.get("stats", {})))


def record_path(stereo_dir: str | Path, image_name: str, pass_value: str) -> Path:
    """``stereo/provenance/<image>.<pass>.json``."""
    return Path(stereo_dir) / PROVENANCE_DIR / f"{image_name}.{pass_value}.json"


def write_record(path: str | Path, record: Record) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(record.to_json(), indent=1, sort_keys=True))


@contextmanager
def pending_record(path: str | Path, fingerprint: str, inputs: dict, previous: Record | None) -> Iterator[None]:
    """Mark the output that ``path`` describes as being made (a pending record) while the block
    runs; if the block fails, the output (written atomically, so untouched) keeps its
    ``previous`` record, or none. The caller writes the complete record after the block."""
    path = Path(path)
    write_record(path, Record(fingerprint, inputs))
    try:
        yield
    except BaseException:
        if previous is not None:
            write_record(path, previous)
        else:
            path.unlink(missing_ok=True)
        raise


def read_record(path: str | Path) -> Record | None:
    """The record at ``path``; None if there is none. An unreadable record (only an outside
    edit makes one: records are written atomically) reads as a pending one."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        return Record.from_json(json.loads(path.read_text()))
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        log.warning("%s is not a readable provenance record; its maps count as unfinished", path)
        return Record(fingerprint="", inputs={})


def stamp_files(folder: Path, paths: Mapping[str, Path]) -> dict[str, dict]:
    """``kind -> {"path", "size", "mtime_ns", "sha256"}`` of files under ``folder``."""
    return {kind: {"path": Path(p).relative_to(folder).as_posix(), **file_stamp(p)} for kind, p in paths.items()}


def status(record: Record | None, expected: str, folder: Path, existing: Iterable[Path]) -> Status:
    """How the outputs described by ``record`` (files relative to ``folder``) stand against the
    fingerprint ``expected``; ``existing``: the output paths a run would write, to tell missing
    outputs from foreign ones when there is no record."""
    if record is None:
        return Status.FOREIGN if any(Path(p).exists() for p in existing) else Status.MISSING
    if not record.complete:
        return Status.INTERRUPTED
    if record.fingerprint != expected:
        return Status.STALE
    for stamp in record.files.values():
        if not matches_stamp(folder / stamp["path"], stamp):
            return Status.MODIFIED
    return Status.CURRENT


# -- the cache shared between output folders -----------------------------------------------------


def _link(source: Path, target: Path) -> None:
    """Make ``target`` the file ``source`` (a hard link; a copy across file systems), atomically."""
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".link", dir=target.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    tmp.unlink()
    try:
        try:
            os.link(source, tmp)
        except OSError:
            shutil.copy2(source, tmp)
        os.replace(tmp, target)
    finally:
        if tmp.exists():
            tmp.unlink()


class MapCache:
    """Finished maps keyed by pass and fingerprint, shared by the runs that name the same folder
    (the jobs of a sweep write to their own folders; a job whose photometric inputs match another's
    links that job's maps instead of computing them). Entries are only added, whole (a folder
    renamed into place), and hold hard links, so they cost no space while a job folder holds the
    same files; delete the cache folder at any time to reclaim the rest."""

    def __init__(self, root: str | Path):
        from dvpmvs.errors import DvpmvsError

        self.root = Path(root)
        if self.root.exists() and not self.root.is_dir():
            raise DvpmvsError(f"the map cache {self.root} is a file; cache= names a folder (or false for none)")

    def _entry(self, pass_value: str, fp: str) -> Path:
        return self.root / pass_value / fp[:2] / fp

    def fetch(self, pass_value: str, fp: str, folder: Path, paths: Mapping[str, Path],
              extras: Mapping[str, Path]) -> Record | None:
        """Link the entry's files onto ``paths`` (kind -> target under ``folder``) and
        ``extras`` (name -> target); returns the record they now carry, or None on a miss."""
        entry = self._entry(pass_value, fp)
        cached = read_record(entry / "record.json")
        if cached is None or not cached.complete or cached.fingerprint != fp or set(cached.files) != set(paths):
            return None
        for kind, stamp in cached.files.items():
            if not matches_stamp(entry / f"{kind}.bin", stamp):
                log.warning("cache entry %s is damaged; computing instead", entry)
                return None
        for kind, target in paths.items():
            _link(entry / f"{kind}.bin", target)
        linked = []
        for name, target in extras.items():
            if (entry / name).is_file():
                _link(entry / name, target)
                linked.append(Path(target).relative_to(folder).as_posix())
        return Record(fp, cached.inputs, True, stamp_files(folder, paths), linked, cached.stats)

    def store(self, pass_value: str, record: Record, folder: Path, extras: Mapping[str, Path]) -> None:
        """Add the complete ``record``'s files (and ``extras``: name -> path) as an entry."""
        entry = self._entry(pass_value, record.fingerprint)
        if (entry / "record.json").is_file():
            return
        entry.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{record.fingerprint[:12]}.", dir=entry.parent))
        try:
            for kind, stamp in record.files.items():
                _link(folder / stamp["path"], staging / f"{kind}.bin")
            for name, path in extras.items():
                if Path(path).is_file():
                    _link(Path(path), staging / name)
            files = {kind: {**stamp, "path": f"{kind}.bin"} for kind, stamp in record.files.items()}
            write_record(staging / "record.json",
                         Record(record.fingerprint, record.inputs, True, files, [], record.stats))
            try:
                os.rename(staging, entry)
            except OSError:  # another run stored the same entry first
                pass
        finally:
            if staging.exists():
                shutil.rmtree(staging, ignore_errors=True)
