"""ExecutorOptions (dvpmvs/options/executor.py): local or Dask, and the kernels' threads per task."""

import os

import pytest

from dvpmvs.options import ExecutorOptions

pytestmark = pytest.mark.smoke


@pytest.mark.parametrize(
    "bad,message",
    [
        ({"name": "ray"}, "unknown executor 'ray'; choose local or dask"),
        ({"name": "dask", "workers": 0}, "executor.workers must be at least 1"),
        ({"name": "dask", "threads_per_worker": -1}, "executor.threads_per_worker must be >= 0"),
        (
            {"address": "tcp://127.0.0.1:8786"},
            "executor.address='tcp://127.0.0.1:8786' is for executor=dask",
        ),
        (
            {"name": "dask", "address": "tcp://127.0.0.1:8786", "scheduler_file": "s.json"},
            "not both",
        ),
    ],
)
def test_a_bad_option_is_named(bad, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        ExecutorOptions(**bad)


def test_a_local_cluster_shares_the_cores_and_an_existing_one_leaves_them_to_its_workers():
    cores = os.cpu_count() or 1
    assert ExecutorOptions("dask", workers=2).kernel_threads() == max(1, cores // 2)
    assert ExecutorOptions("dask", workers=4 * cores).kernel_threads() == 1
    assert ExecutorOptions("dask", threads_per_worker=3).kernel_threads() == 3
    existing = ExecutorOptions("dask", address="tcp://127.0.0.1:8786")
    assert (
        existing.existing_cluster and existing.kernel_threads() == 0
    )  # every core of the worker's machine
    assert not ExecutorOptions().existing_cluster
