"""Options of the task executor (:mod:`dvpmvs.executor`): local, or a Dask cluster."""

from __future__ import annotations

from dataclasses import dataclass

from dvpmvs.validation import check_field_types, resolve_threads

__all__ = ["EXECUTORS", "ExecutorOptions"]


EXECUTORS = ("local", "dask")


@dataclass(frozen=True)
class ExecutorOptions:
    """Where the dense stage's tasks run. Validates itself.

    Parameters
    ----------
    name : str
        ``local`` (this process, the tasks one after another) or ``dask``.
    address : str | None
        The scheduler of an existing Dask cluster (``tcp://host:8786``).
    scheduler_file : str | None
        Instead, the file its scheduler wrote (``dask scheduler --scheduler-file F``); with neither, a
        ``LocalCluster`` of ``workers`` processes on this machine.
    workers : int
        The local cluster's worker processes.
    threads_per_worker : int
        The kernels' threads in each task; 0: this machine's cores shared by the local workers, or every core of
        the worker's machine on an existing cluster. Each worker runs one task at a time (start the workers of
        an existing cluster with ``--nthreads 1``).
    """

    name: str = "local"
    address: str | None = None
    scheduler_file: str | None = None
    workers: int = 2
    threads_per_worker: int = 0

    def __post_init__(self):
        check_field_types(self)
        if self.name not in EXECUTORS:
            raise ValueError(f"unknown executor {self.name!r}; choose {' or '.join(EXECUTORS)}")
        if self.workers < 1:
            raise ValueError(f"executor.workers must be at least 1, got {self.workers}")
        # A worker's machine is not this one: its cores bound its threads there.
        if self.threads_per_worker < 0:
            raise ValueError(
                f"executor.threads_per_worker must be >= 0 (0: the cores a worker has), got "
                f"{self.threads_per_worker}"
            )
        for key in ("address", "scheduler_file"):
            if getattr(self, key) is not None and self.name != "dask":
                raise ValueError(f"executor.{key}={getattr(self, key)!r} is for executor=dask")
        if self.address is not None and self.scheduler_file is not None:
            raise ValueError("give executor.address or executor.scheduler_file, not both")

    @property
    def existing_cluster(self) -> bool:
        return self.address is not None or self.scheduler_file is not None

    def kernel_threads(self) -> int:
        """The kernels' threads in a task on a worker (0: every core of the worker's machine)."""
        if self.threads_per_worker > 0 or self.existing_cluster:
            return self.threads_per_worker
        return resolve_threads(0, self.workers)
