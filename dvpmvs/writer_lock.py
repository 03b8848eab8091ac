"""One writer per output folder: ``dense`` and ``fuse`` hold ``<folder>/.dvpmvs.lock`` while they
write maps or a cloud there, so that two runs with different options cannot interleave their
maps view by view. Readers (``eval``) take no lock.

The lock is an advisory ``flock`` on the file: the operating system releases it when its holder
exits, however it exits (``kill -9`` included), so a lock left by a killed run is taken over by
the next one without a timeout to guess. The file also holds who took it (PID, host, start time,
command line), for the message the second writer gets. Locks are per process and re-entrant: a
``dense`` run that fuses at its end takes its own folder's lock again.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import socket
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path

from dvpmvs.errors import DvpmvsError

__all__ = ["LOCK_NAME", "FolderLockedError", "writer_lock", "lock_holder"]

log = logging.getLogger(__name__)

LOCK_NAME = ".dvpmvs.lock"

# (folder, thread) -> [open lock file, depth]: the locks this process holds. Keyed by thread too:
# two threads of one process (a sweep's jobs) on one folder exclude each other like two processes.
_held: dict[tuple[Path, int], list] = {}


class FolderLockedError(DvpmvsError, RuntimeError):
    """Another process is writing to the output folder."""


def lock_holder(folder: str | Path) -> dict | None:
    """What the lock file of ``folder`` says about its last holder (None: no readable record)."""
    try:
        return json.loads((Path(folder) / LOCK_NAME).read_text())
    except (OSError, ValueError):
        return None


def _describe(holder: dict | None) -> str:
    if not holder:
        return "another process"
    command = " ".join(holder.get("command") or [])
    return f"PID {holder.get('pid')} on {holder.get('host')}, started {holder.get('started')}" + (
        f": {command}" if command else ""
    )


@contextmanager
def writer_lock(folder: str | Path, wait: float = 0.0) -> Iterator[Path]:
    """Hold the writer lock of ``folder`` (created if missing) for the ``with`` block.

    If another process holds it, wait up to ``wait`` seconds, then raise
    :class:`FolderLockedError` naming the holder. A lock whose holder died is free: it is taken
    over, with a note in the log.
    """
    folder = Path(folder).expanduser().resolve()
    key = (folder, threading.get_ident())
    if key in _held:
        _held[key][1] += 1
        try:
            yield folder
        finally:
            _held[key][1] -= 1
        return
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / LOCK_NAME
    previous = lock_holder(folder)
    handle = open(path, "a+")
    deadline = time.monotonic() + wait
    while True:
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            break
        except BlockingIOError:
            if time.monotonic() >= deadline:
                handle.close()
                raise FolderLockedError(
                    f"{folder} is being written by another dvpmvs run ({_describe(lock_holder(folder))}); "
                    f"wait for it to finish, or write this run elsewhere with out=DIR"
                ) from None
            time.sleep(min(1.0, max(0.05, deadline - time.monotonic())))
    if previous and previous.get("active") and previous.get("pid") != os.getpid():
        log.info(
            "took over the lock of %s, which ended without releasing it (%s)",
            folder,
            _describe(previous),
        )
    holder = {
        "pid": os.getpid(),
        "host": socket.gethostname(),
        "active": True,
        "started": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": ["dvpmvs", *sys.argv[1:]] if sys.argv else [],
    }
    handle.seek(0)
    handle.truncate()
    handle.write(json.dumps(holder))
    handle.flush()
    _held[key] = [handle, 1]
    try:
        yield folder
    finally:
        del _held[key]
        try:
            handle.seek(0)
            handle.truncate()
            handle.write(json.dumps({**holder, "active": False}))
            handle.flush()
        finally:
            fcntl.flock(handle.fileno(), fcntl.LOCK_UN)
            handle.close()
