"""Progress of a step that runs inside one library call: COLMAP's feature extraction, matching
and mapping (through pycolmap), Poisson meshing (Open3D).

Those calls say nothing until they return, minutes later on large photos. :class:`StepProgress`
watches a count from a thread while the call runs (rows in COLMAP's database, images the mapper
registered): a bar with its estimate of the time left where bars are on (``progress``), else a
log line at least every HEARTBEAT_SECONDS (a CI or SLURM log); a step without a count says how
long it has been running. A call that holds the GIL throughout (Open3D's) runs in a child
process (:func:`in_child_process`), else the watching thread could say nothing until it returns.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import pickle
import signal
import sqlite3
import sys
import threading
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

__all__ = ["HEARTBEAT_SECONDS", "StepProgress", "database_rows", "in_child_process"]

log = logging.getLogger(__name__)
T = TypeVar("T")

# Without bars, a line at least this often: a log that stays silent longer reads as a hang.
HEARTBEAT_SECONDS = 10.0
# How often the count is read.
POLL_SECONDS = 0.5
# When the last heartbeat was said, whichever step said it: a step that starts right after
# another says its first line HEARTBEAT_SECONDS after the other's last, not after its own start.
_LAST_SAID = [time.perf_counter()]


def in_child_process(function: Callable[..., T], *args: object) -> T:
    """``function(*args)`` run in a child process: its result returned, its exception raised.

    Open3D's bindings hold the GIL for the whole of a call (Poisson reconstruction, quadric
    decimation: half a minute on a photo set's cloud), so no thread of this process, a
    :class:`StepProgress` heartbeat among them, runs until it returns. The child is spawned (a
    forked child of a process that ran OpenMP can hang in its first parallel region) and ignores
    Ctrl-C: an interrupt reaches this process, which kills the child on its way out (SIGKILL: a
    library's crash handler would print a stack trace on SIGTERM), so the caller's atomic
    writers remove what the child left half-written. Inside a daemonic process (a worker of a
    multiprocessing pool or of Dask), which may not have children, or in a script read from
    standard input, which a child cannot re-run, the call runs in place."""
    main_file = getattr(sys.modules.get("__main__"), "__file__", None)
    if multiprocessing.current_process().daemon or (main_file and not os.path.isfile(main_file)):
        # A spawned child re-runs the parent's main script, which a script read from standard
        # input (``python - < job.py``, "<stdin>") does not have: it would die on start.
        return function(*args)
    context = multiprocessing.get_context("spawn")
    receiver, sender = context.Pipe(duplex=False)
    child = context.Process(target=_call_and_send, args=(sender, function, args), daemon=True)
    child.start()
    sender.close()
    try:
        outcome, value = receiver.recv()
    except EOFError:
        child.join()
        raise RuntimeError(
            f"the child process running {function.__qualname__} ended without an answer "
            f"(exit code {child.exitcode}; a negative code is the signal that stopped it; its "
            "error, if any, is printed above). The child re-runs the main script first: a script "
            'that calls dvpmvs at its top level must do so under `if __name__ == "__main__":`'
        ) from None
    except BaseException:
        child.kill()
        child.join()
        raise
    finally:
        receiver.close()
    child.join()
    if outcome == "error":
        raise value
    return value


def _call_and_send(sender, function: Callable, args: tuple) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        answer = ("result", function(*args))
    except Exception as exc:  # noqa: BLE001 - raised again in the parent
        where = f"in a child process:\n{traceback.format_exc()}"
        if hasattr(exc, "add_note"):  # Python 3.11+
            exc.add_note(where)
        answer = ("error", exc)
        try:
            pickle.loads(pickle.dumps(exc))
        except Exception:  # noqa: BLE001 - an error the parent could not rebuild: named instead
            answer = ("error", RuntimeError(f"{type(exc).__name__}: {exc}\n{where}"))
    try:
        sender.send(answer)
    except Exception:  # noqa: BLE001 - a result that does not pickle
        sender.send(
            ("error", RuntimeError(f"the result does not pickle: {traceback.format_exc()}"))
        )
    sender.close()


def database_rows(database: Path, table: str) -> Callable[[], int | None]:
    """A count of the rows of ``table`` in COLMAP's database, read while COLMAP writes it (None
    while the file or the table does not exist yet, or a page is read mid-write).

    Read as ``immutable``: SQLite then takes no lock. A reader's shared lock makes COLMAP's next
    write fail ("database is locked"), and COLMAP aborts the process on it."""

    def count() -> int | None:
        if not database.is_file():
            return None
        try:
            with sqlite3.connect(f"file:{database}?immutable=1", uri=True) as db:
                return int(db.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0])  # noqa: S608
        except sqlite3.Error:  # the table not created yet, or a page caught mid-write
            return None

    return count


class StepProgress:
    """A context manager around one long call: ``count()`` (done so far, or None when unknown)
    out of ``total`` (None: no estimate) ``unit``, shown as a bar or as heartbeat log lines.
    ``advance()`` counts one more where the call reports its own steps (a callback)."""

    def __init__(
        self,
        step: str,
        unit: str,
        total: int | None = None,
        count: Callable[[], int | None] | None = None,
        progress: bool = False,
    ):
        self.step, self.unit, self.total, self._count = step, unit, total, count
        self.progress = progress
        self._advanced = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._bar = None

    def advance(self) -> None:
        self._advanced += 1

    def done(self) -> int | None:
        if self._count is None:
            return self._advanced if self._advanced else None
        return self._count()

    def __enter__(self) -> StepProgress:
        self._start = time.perf_counter()
        if self.progress:
            from tqdm import tqdm

            self._bar = tqdm(total=self.total, desc=self.step, unit=f" {self.unit}", leave=False)
        self._thread = threading.Thread(
            target=self._watch, name=f"progress-{self.step}", daemon=True
        )
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if self._bar is not None:
            self._bar.close()

    def _watch(self) -> None:
        while not self._stop.wait(POLL_SECONDS):
            done = self.done()
            if self._bar is not None:
                if done is not None and done != self._bar.n:
                    self._bar.update(done - self._bar.n)
                else:
                    self._bar.refresh()
                continue
            now = time.perf_counter()
            if now - max(_LAST_SAID[0], self._start - HEARTBEAT_SECONDS / 2) >= HEARTBEAT_SECONDS:
                log.info("%s", self.line(done, now - self._start))
                _LAST_SAID[0] = now

    def line(self, done: int | None, elapsed: float) -> str:
        """The heartbeat: what is done of the total, the time so far and the estimate left."""
        said = f"{self.step}: "
        if done is None:
            return said + f"running for {_duration(elapsed)}"
        if not self.total:
            return said + f"{done} {self.unit} in {_duration(elapsed)}"
        said += f"{done} of {self.total} {self.unit} ({100 * done / self.total:.0f} %) in {_duration(elapsed)}"
        if 0 < done < self.total:
            said += f", about {_duration(elapsed * (self.total - done) / done)} left"
        return said


def _duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    return f"{seconds / 60:.0f} min" if seconds < 5400 else f"{seconds / 3600:.1f} h"
