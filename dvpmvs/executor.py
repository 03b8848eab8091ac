"""Where the dense stage's tasks run: in this process, one after another (``local``), or on a Dask
cluster (``dask``), one task per view and step, each started when the tasks whose outputs it reads
have finished.

A task reads the workspace and writes its outputs through the same atomic writers and
provenance records as a local run, so the only thing the workers share is the filesystem that
holds the workspace and the output folder. The driver plans every task before any runs and
checks afterwards; a task's result is small (a report), its outputs are files.

Faults: a worker that dies during a task (killed, out of memory, its machine lost) has the task
rescheduled on another worker by Dask's scheduler (up to its ``distributed.scheduler.allowed-failures``,
3 by default). The outputs a killed task had begun are temporaries or carry a pending record, so
no task reads them: a task starts only after the tasks it depends on have returned. An error in a
task (bad input) is not retried: the run stops with it and cancels the tasks not yet finished.
"""

from __future__ import annotations

import logging
import time
import uuid
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dvpmvs.errors import DvpmvsError, Interrupted
from dvpmvs.options.executor import EXECUTORS, ExecutorOptions

__all__ = ["EXECUTORS", "ExecutorError", "ExecutorOptions", "Task", "run_tasks", "dask_client"]

log = logging.getLogger(__name__)


class ExecutorError(DvpmvsError, RuntimeError):
    """The cluster stopped (or could not be reached) before the run's tasks finished."""


@dataclass(frozen=True)
class Task:
    """``function(*args)``, to run after the tasks named in ``after`` (keys of the same run;
    keys of tasks not in the run are ignored: their outputs are on disk already). ``stage``
    groups tasks for progress and timings; tasks come in an order where each follows those it
    depends on."""

    key: str
    stage: str
    function: Callable[..., Any]
    args: tuple = ()
    after: tuple[str, ...] = ()


def _timed(function: Callable[..., Any], args: tuple, *_after) -> tuple[Any, float]:
    """Run a task; its result and seconds. ``_after``: the results of the tasks it waits for
    (passed so that Dask knows the dependencies, not used)."""
    start = time.perf_counter()
    result = function(*args)
    return result, time.perf_counter() - start


def run_tasks(
    tasks: Sequence[Task], options: ExecutorOptions | None = None, progress: bool = False
) -> dict[str, tuple[Any, float]]:
    """Run ``tasks`` with the executor ``options``; key -> (result, seconds of the task)."""
    options = options or ExecutorOptions()
    keys = [task.key for task in tasks]
    if len(set(keys)) != len(keys):
        raise ValueError("task keys must be unique")
    if not tasks:
        return {}
    if options.name == "dask":
        return _run_dask(tasks, options, progress)
    return _run_local(tasks, progress)


def _run_local(tasks: Sequence[Task], progress: bool) -> dict[str, tuple[Any, float]]:
    from tqdm import tqdm

    from dvpmvs.stage_progress import StepProgress

    results: dict[str, tuple[Any, float]] = {}
    bar, stage, watch = None, None, None
    done = {"views": 0}  # of the stage (a disabled bar does not count)
    try:
        for task in tasks:
            if task.stage != stage:
                if bar is not None:
                    bar.close()
                if watch is not None:
                    watch.__exit__(None, None, None)
                stage = task.stage
                done["views"] = 0
                total = sum(t.stage == stage for t in tasks)
                bar = tqdm(
                    total=total, desc=stage, unit="view", disable=not progress, dynamic_ncols=True
                )
                # Without bars (a CI or SLURM log), a line at least every few seconds instead:
                # a view's maps take minutes on large photos.
                if not progress:
                    watch = StepProgress(stage, "views", total, lambda: done["views"]).__enter__()
            bar.set_postfix_str(task.key.rpartition(":")[2])
            results[task.key] = _timed(task.function, task.args)
            done["views"] += 1
            bar.update()
    except Interrupted as stop:
        stop.progress = _progress_of(tasks, results, stage)
        raise
    finally:
        if bar is not None:
            bar.close()
        if watch is not None:
            watch.__exit__(None, None, None)
    return results


def _progress_of(tasks: Sequence[Task], results: Mapping[str, Any], stage: str | None) -> str:
    """How far a stopped run got: ``3 of 8 views done in the photometric pass`` (of ``stage``,
    where it is known), and the tasks of every stage."""
    if stage is None:
        return f"{len(results)} of {len(tasks)} tasks done"
    of_stage = [t.key for t in tasks if t.stage == stage]
    done = sum(key in results for key in of_stage)
    return f"{done} of {len(of_stage)} views done in the {stage} ({len(results)} of {len(tasks)} tasks of the run)"


@contextmanager
def dask_client(options: ExecutorOptions) -> Iterator[Any]:
    """A client of the existing scheduler ``options`` names, or of a ``LocalCluster`` of
    ``options.workers`` single-task worker processes (closed on exit)."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise ImportError(
            "executor=dask needs Dask distributed: pip install 'dvpmvs[dask]'"
        ) from None
    if options.existing_cluster:
        where = (
            f"executor.address={options.address}"
            if options.address is not None
            else f"executor.scheduler_file={options.scheduler_file}"
        )
        try:
            if options.address is not None:
                _check_scheduler(options.address)
                client = Client(options.address, timeout="30s")
            else:
                if not Path(options.scheduler_file).expanduser().is_file():
                    raise FileNotFoundError(f"{options.scheduler_file} does not exist")
                client = Client(
                    scheduler_file=str(Path(options.scheduler_file).expanduser()), timeout="30s"
                )
        except OSError as exc:
            raise ExecutorError(
                f"no Dask scheduler answers at {where} ({exc}); start one (dask scheduler) or "
                f"leave executor.address and executor.scheduler_file unset for a "
                f"LocalCluster"
            ) from None
        with _dask_logs_quiet() as closing, client:
            try:
                yield client
            finally:
                closing()
        return
    with (
        _dask_logs_quiet() as closing,
        LocalCluster(
            n_workers=options.workers, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster,
        Client(cluster) as client,
    ):
        try:
            yield client
        finally:
            closing()


# Dask's own loggers: its scheduler, nannies and workers say each step of their life at INFO
# (some 40 lines a run) and, as a cluster closes, report the connections it closes as errors.
_DASK_LOGGERS = ("distributed", "dask", "tornado", "bokeh")


@contextmanager
def _dask_logs_quiet() -> Iterator[Callable[[], None]]:
    """Dask's log lines at warnings and above while the run's tasks run, none once they are
    done (the cluster's shutdown), unless verbose=true (the dvpmvs logger at DEBUG) lets them
    all through. Yields the function that silences the shutdown."""
    if logging.getLogger("dvpmvs").isEnabledFor(logging.DEBUG):
        yield lambda: None
        return
    loggers = [logging.getLogger(name) for name in _DASK_LOGGERS]
    saved = [logger.level for logger in loggers]
    for logger in loggers:
        logger.setLevel(logging.WARNING)

    def closing() -> None:
        for logger in loggers:
            logger.setLevel(logging.CRITICAL + 1)

    try:
        yield closing
    finally:
        for logger, level in zip(loggers, saved):
            logger.setLevel(level)


# A Dask scheduler sends its handshake as soon as it accepts a connection: a length (8 bytes,
# Dask's "Q") then a small message. What sends nothing in this time, or a length no handshake
# has, is not one (Dask's own client would wait past its timeout, or try to allocate exabytes).
_HANDSHAKE_SECONDS = 10
_MAX_HANDSHAKE_BYTES = 1 << 20


def _check_scheduler(address: str) -> None:
    """For a ``tcp://`` address, fail at once where nothing listens (Dask's client would retry
    until its timeout), and where what listens is not a Dask scheduler (``OSError`` saying
    which); other protocols are left to Dask."""
    import socket
    import struct
    from urllib.parse import urlsplit

    parts = urlsplit(address)
    if not (parts.scheme == "tcp" and parts.hostname and parts.port):
        return
    with socket.create_connection((parts.hostname, parts.port), timeout=_HANDSHAKE_SECONDS) as sock:
        sock.settimeout(_HANDSHAKE_SECONDS)
        header = b""
        try:
            while len(header) < 8:
                chunk = sock.recv(8 - len(header))
                if not chunk:
                    break
                header += chunk
        except TimeoutError:
            raise OSError(
                f"something listens there but sent no Dask handshake within {_HANDSHAKE_SECONDS} s: not a "
                f"Dask scheduler (a web server?)"
            ) from None
        if len(header) < 8:
            raise OSError(
                "something listens there but closed the connection without a Dask handshake"
            ) from None
        (length,) = struct.unpack("Q", header)
        if not 0 < length <= _MAX_HANDSHAKE_BYTES:
            raise OSError(
                f"something listens there but its first bytes ({header!r}) are no Dask handshake: not a "
                f"Dask scheduler"
            )


def _run_dask(
    tasks: Sequence[Task], options: ExecutorOptions, progress: bool
) -> dict[str, tuple[Any, float]]:
    import contextlib
    from concurrent.futures import CancelledError

    from distributed import as_completed
    from tqdm import tqdm

    from dvpmvs.stage_progress import StepProgress

    run = uuid.uuid4().hex[:8]  # keys unique on a scheduler shared by several runs
    with dask_client(options) as client:
        futures, key_of = {}, {}
        for task in tasks:
            after = [futures[key] for key in task.after if key in futures]
            future = client.submit(
                _timed,
                task.function,
                task.args,
                *after,
                pure=False,
                key=f"dvpmvs-{task.key.replace(':', '-')}-{run}",
            )
            futures[task.key] = future
            key_of[future.key] = task.key
        log.info(
            "executor=dask: %d tasks on %d worker(s) at %s",
            len(futures),
            len(client.scheduler_info().get("workers", {})),
            client.scheduler.address,
        )
        results: dict[str, tuple[Any, float]] = {}
        # Without bars, a line at least every few seconds (dvpmvs.stage_progress).
        watch = StepProgress("tasks", "tasks", len(futures), lambda: len(results), progress=False)
        try:
            with (
                tqdm(
                    total=len(futures),
                    desc="tasks",
                    unit="task",
                    disable=not progress,
                    dynamic_ncols=True,
                ) as bar,
                watch if not progress else contextlib.nullcontext(),
            ):
                for future in as_completed(list(futures.values())):
                    try:
                        results[key_of[future.key]] = future.result()
                    except CancelledError as exc:
                        raise ExecutorError(
                            f"the Dask cluster stopped before the run's tasks finished ({len(results)} of "
                            f"{len(futures)} done; {' '.join(str(exc).split())}); the finished views' "
                            f"outputs are kept: rerun to compute the rest"
                        ) from None
                    bar.set_postfix_str(key_of[future.key])
                    bar.update()
        except Interrupted as stop:
            stop.progress = _progress_of(tasks, results, None)
            raise
        finally:
            if len(results) < len(futures):
                client.cancel(list(futures.values()))
    return {task.key: results[task.key] for task in tasks}
