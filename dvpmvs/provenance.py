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
import json
import logging
import os
import platform
import shutil
import tempfile
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import lru_cache
from importlib import metadata
from pathlib import Path
from typing import Any

from dvpmvs._kernel_sources import kernel_digests
from dvpmvs.digests import canonical, file_stamp, fingerprint, matches_stamp, sources_digest
from dvpmvs.errors import DvpmvsError
from dvpmvs.maps import atomic_path

__all__ = [
    "Status",
    "Record",
    "CachedOutput",
    "ForeignOutputError",
    "code_identity",
    "environment",
    "record_path",
    "read_record",
    "write_record",
    "status",
    "MapCache",
    "LIBRARIES",
    "PROVENANCE_DIR",
]

log = logging.getLogger(__name__)

PROVENANCE_DIR = "provenance"  # under stereo/, beside COLMAP's own folders (COLMAP ignores it)

# The numerical libraries the maps, clouds and scores depend on besides our code and the seed
# (another OpenCV renders other synthetic scenes and gives other maps; see constraints.txt).
LIBRARIES = ("numpy", "scipy", "opencv-python-headless", "pycolmap", "open3d", "onnxruntime")

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


# -- code and environment ----------------------------------------------------------------------


@lru_cache(maxsize=1)
def code_identity() -> dict:
    """What code made an output: the dvpmvs version, a digest of the package's sources (Python
    and Cython, as installed: an edited checkout is another code), the digests the compiled
    kernels were built from, and the numerical libraries' versions."""
    from dvpmvs._version import __version__

    package = Path(__file__).resolve().parent
    return {
        "dvpmvs": __version__,
        "sources": sources_digest(package, exclude=_NOT_MAP_CODE),
        "kernels": kernel_digests(),
        "libraries": library_versions(),
    }


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
    return {
        "python": platform.python_version(),
        "cpu": cpu,
        "cores": os.cpu_count(),
        "libraries": library_versions(),
    }


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
        return {
            "fingerprint": self.fingerprint,
            "state": "complete" if self.complete else "pending",
            "files": self.files,
            "extras": self.extras,
            "stats": canonical(self.stats),
            "inputs": canonical(self.inputs),
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Record:
        return cls(
            fingerprint=str(data["fingerprint"]),
            inputs=dict(data.get("inputs", {})),
            complete=data.get("state") == "complete",
            files=dict(data.get("files", {})),
            extras=list(data.get("extras", [])),
            stats=dict(data.get("stats", {})),
        )


def record_path(stereo_dir: str | Path, image_name: str, pass_value: str) -> Path:
    """``stereo/provenance/<image>.<pass>.json``."""
    return Path(stereo_dir) / PROVENANCE_DIR / f"{image_name}.{pass_value}.json"


def write_record(path: str | Path, record: Record) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(record.to_json(), indent=1, sort_keys=True))


def _file_states(paths: Iterable[Path]) -> dict[Path, tuple[int, int] | None]:
    states = {}
    for path in paths:
        try:
            info = Path(path).stat()
            states[Path(path)] = (info.st_size, info.st_mtime_ns)
        except FileNotFoundError:
            states[Path(path)] = None
    return states


@contextmanager
def pending_record(
    path: str | Path,
    fingerprint: str,
    inputs: dict,
    previous: Record | None,
    outputs: Iterable[Path] = (),
) -> Iterator[None]:
    """Mark the output that ``path`` describes as being made (a pending record) while the block
    runs. If the block fails before any of ``outputs`` changed, the previous record comes back
    (or none, where there was none); once one has changed, the pending record stays, so the
    output reads as interrupted and is made again. The caller writes the complete record after
    the block."""
    path = Path(path)
    before = _file_states(outputs)
    write_record(path, Record(fingerprint, inputs))
    try:
        yield
    except BaseException:
        if _file_states(before) == before:
            if previous is not None:
                write_record(path, previous)
            else:
                path.unlink(missing_ok=True)
        raise


class ForeignOutputError(DvpmvsError, FileExistsError):
    """An output path holds a file dvpmvs did not write (no provenance record)."""


@dataclass
class CachedOutput:
    """A stage's output against its record: made from ``inputs`` (their fingerprint), described
    by the record at ``record_file``, its files relative to ``folder``. :meth:`check` reads the
    record; :attr:`current` is it when the outputs on disk are what those inputs made (reuse
    them); else the stage makes them inside :meth:`making` (a pending record, the previous one
    restored if the work fails before an output changed) and ends with :meth:`complete`."""

    record_file: Path
    inputs: dict
    folder: Path
    fingerprint: str
    previous: Record | None
    state: Status
    outputs: tuple[Path, ...] = ()

    @classmethod
    def check(
        cls, record_file: str | Path, inputs: dict, folder: str | Path, outputs: Iterable[Path] = ()
    ) -> CachedOutput:
        """``outputs``: the paths the stage writes, to tell missing ones from foreign ones
        when there is no record."""
        fp = fingerprint(inputs)
        previous = read_record(record_file)
        outputs = tuple(Path(p) for p in outputs)
        return cls(
            Path(record_file),
            inputs,
            Path(folder),
            fp,
            previous,
            status(previous, fp, Path(folder), outputs),
            outputs,
        )

    @classmethod
    def of_view(
        cls,
        stereo: str | Path,
        image_name: str,
        stage: str,
        inputs: dict,
        files: Mapping[str, Path],
    ) -> CachedOutput:
        """A view's output of ``stage`` in the maps' folder ``stereo`` (its ``files``: kind ->
        path), against its record ``stereo/provenance/<image>.<stage>.json``."""
        return cls.check(record_path(stereo, image_name, stage), inputs, stereo, files.values())

    @property
    def current(self) -> Record | None:
        return self.previous if self.state.reusable else None

    def making(self, overwrite: bool = False):
        """The block that makes the outputs. Outputs on disk without a record (another program's
        or an older dvpmvs's) are never replaced unless ``overwrite``: :class:`ForeignOutputError`
        names the first and the remedy."""
        if self.state is Status.FOREIGN and not overwrite:
            existing = next(
                (p for p in self.outputs if p.exists()),
                self.outputs[0] if self.outputs else self.folder,
            )
            raise ForeignOutputError(
                f"{existing} exists and carries no dvpmvs provenance record (written by COLMAP, another program or an "
                f"older dvpmvs); dvpmvs does not replace a file it did not write unasked: rerun with overwrite=true "
                f"to replace it, or give another output path"
            )
        return pending_record(
            self.record_file, self.fingerprint, self.inputs, self.previous, self.outputs
        )

    def complete(
        self, files: Mapping[str, Path], stats: dict, extras: Iterable[str] = ()
    ) -> Record:
        """Write the complete record: ``files`` (kind -> path under ``folder``) stamped."""
        record = Record(
            self.fingerprint,
            self.inputs,
            True,
            stamp_files(self.folder, files),
            list(extras),
            stats,
        )
        write_record(self.record_file, record)
        return record


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
    return {
        kind: {"path": Path(p).relative_to(folder).as_posix(), **file_stamp(p)}
        for kind, p in paths.items()
    }


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
            raise DvpmvsError(
                f"the map cache {self.root} is a file; cache= names a folder (or false for none)"
            )

    def _entry(self, pass_value: str, fp: str) -> Path:
        return self.root / pass_value / fp[:2] / fp

    def fetch(
        self,
        pass_value: str,
        fp: str,
        folder: Path,
        paths: Mapping[str, Path],
        extras: Mapping[str, Path],
    ) -> Record | None:
        """Link the entry's files onto ``paths`` (kind -> target under ``folder``) and
        ``extras`` (name -> target); returns the record they now carry, or None on a miss."""
        entry = self._entry(pass_value, fp)
        cached = read_record(entry / "record.json")
        if (
            cached is None
            or not cached.complete
            or cached.fingerprint != fp
            or set(cached.files) != set(paths)
        ):
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

    def store(
        self, pass_value: str, record: Record, folder: Path, extras: Mapping[str, Path]
    ) -> None:
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
            write_record(
                staging / "record.json",
                Record(record.fingerprint, record.inputs, True, files, [], record.stats),
            )
            try:
                os.rename(staging, entry)
            except OSError:  # another run stored the same entry first
                pass
        finally:
            if staging.exists():
                shutil.rmtree(staging, ignore_errors=True)
