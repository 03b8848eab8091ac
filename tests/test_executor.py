"""The dense stage on a Dask cluster: the same maps and cloud as the local loop, a killed worker's
task done again elsewhere, a stopped cluster's run resumed from its finished views."""

import hashlib
import os
import shutil
import signal
import threading
import time
from pathlib import Path

import pytest

from dvpmvs.dense import DenseOptions, run_dense
from dvpmvs.evaluation.synthetic import SynthOptions, generate
from dvpmvs.executor import ExecutorError, ExecutorOptions, Task, run_tasks
from dvpmvs.maps import Pass
from dvpmvs.provenance import read_record
from dvpmvs.workspace import Workspace, WorkspaceOptions

distributed = pytest.importorskip("distributed", reason="the [dask] extra is not installed")


def _digests(folder: Path) -> dict[str, str]:
    """Every map file (and the cloud) under ``folder``, by relative path."""
    files = [*folder.glob("stereo/**/*.bin"), *folder.glob("*.ply")]
    return {
        p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(files)
    }


def _complete(out: Path, pass_: Pass) -> list[str]:
    """The views whose maps of ``pass_`` carry a complete record in ``out``."""
    folder = out / "stereo" / "provenance"
    records = (
        [(p, read_record(p)) for p in folder.glob(f"*.{pass_.value}.json")]
        if folder.is_dir()
        else []
    )
    return sorted(
        p.name[: -len(f".{pass_.value}.json")] for p, r in records if r is not None and r.complete
    )


def _wait_for(condition, timeout=120.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return True
        time.sleep(0.02)
    return False


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """The tabletop, 4 views of 128x96, and its maps and cloud made by the local loop."""
    root = tmp_path_factory.mktemp("executor") / "tabletop"
    generate(root, SynthOptions(scene="tabletop", views=4, width=128, priors=False))
    local = root.parent / "local"
    run_dense(Workspace.open(root), DenseOptions(), out=local, progress=False)
    return root, _digests(local)


@pytest.fixture
def cluster():
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        yield cluster


def test_executor_options_validate_themselves():
    with pytest.raises(ValueError, match="unknown executor 'ray'"):
        ExecutorOptions("ray")
    with pytest.raises(ValueError, match="workers must be at least 1"):
        ExecutorOptions("dask", workers=0)
    with pytest.raises(ValueError, match="address.*is for executor=dask"):
        ExecutorOptions("local", address="tcp://localhost:8786")
    with pytest.raises(ValueError, match="not both"):
        ExecutorOptions("dask", address="tcp://localhost:8786", scheduler_file="s.json")
    assert (
        ExecutorOptions("dask", address="tcp://x:1").kernel_threads() == 0
    )  # every core of the worker's machine
    assert ExecutorOptions("dask", workers=2, threads_per_worker=3).kernel_threads() == 3


def test_tasks_run_after_the_tasks_they_read(tmp_path):
    # Each task appends its key to a file once the keys it waits for are there: any order that
    # breaks a dependency fails the task.
    log = tmp_path / "order"

    tasks = [
        Task("a", "s", _append, (log, "a", ())),
        Task("b", "s", _append, (log, "b", ("a",)), ("a",)),
        Task("c", "s", _append, (log, "c", ("a", "b")), ("a", "b", "not-in-the-run")),
    ]
    results = run_tasks(tasks, ExecutorOptions("dask", workers=2, threads_per_worker=1))
    assert [results[k][0] for k in "abc"] == ["a", "b", "c"] and all(
        results[k][1] >= 0 for k in "abc"
    )
    assert log.read_text().split() == ["a", "b", "c"]
    with pytest.raises(ValueError, match="unique"):
        run_tasks([tasks[0], tasks[0]])


def _append(path: Path, key: str, needs: tuple[str, ...]) -> str:
    done = path.read_text().split() if path.exists() else []
    missing = [k for k in needs if k not in done]
    if missing:
        raise AssertionError(f"{key} ran before {missing}")
    path.write_text(" ".join([*done, key]))
    return key


@pytest.mark.slow
def test_a_local_cluster_gives_the_local_maps_and_cloud(tmp_path):
    # The embedded scene (the demo's, at 120 px), with highlight perception so that every kind
    # of task (highlights, photometric, multi-view highlights, geometric) runs on the workers.
    from dvpmvs.evaluation.embedded import materialise

    workspace = Workspace.open(
        materialise(tmp_path / "scene"), WorkspaceOptions(max_image_size=120)
    )
    options = DenseOptions(priors={**DenseOptions().priors, "highlight": {"name": "multiview"}})
    local = run_dense(workspace, options, out=tmp_path / "local", progress=False)
    dask = run_dense(
        workspace,
        options,
        out=tmp_path / "dask",
        progress=False,
        executor=ExecutorOptions("dask", workers=2),
    )
    expected = _digests(tmp_path / "local")
    assert (
        len(expected) > 40 and "fused.ply" in expected and any("highlights/" in k for k in expected)
    )
    assert _digests(tmp_path / "dask") == expected
    assert [(r.name, r.pass_, r.action) for r in dask.reports] == [
        (r.name, r.pass_, r.action) for r in local.reports
    ]
    assert dask.num_points == local.num_points > 9_000 and len(dask.highlight_seconds) == len(
        workspace.references
    )


@pytest.mark.slow
def test_a_worker_killed_during_a_task_leaves_complete_maps(small, cluster, tmp_path):
    root, expected = small
    out = tmp_path / "out"
    client = distributed.Client(cluster)
    killed = []

    def kill_a_worker_once_a_view_is_begun():
        # A pending record is written before a view's computation starts: a task is running.
        def begun():
            folder = out / "stereo" / "provenance"
            return folder.is_dir() and any(
                not r.complete
                for p in folder.glob("*.photometric.json")
                if (r := read_record(p)) is not None
            )

        if _wait_for(begun):
            pid = next(iter(client.run(os.getpid).values()))
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)

    killer = threading.Thread(target=kill_a_worker_once_a_view_is_begun)
    killer.start()
    summary = run_dense(
        Workspace.open(root),
        DenseOptions(),
        out=out,
        progress=False,
        executor=ExecutorOptions("dask", address=cluster.scheduler_address, threads_per_worker=1),
    )
    killer.join()
    client.close()
    assert killed, "no worker was killed: the test did not test anything"
    assert {r.action for r in summary.reports} == {"computed"} and len(summary.reports) == 8
    assert (
        _complete(out, Pass.PHOTOMETRIC)
        == _complete(out, Pass.GEOMETRIC)
        == ["0000.png", "0001.png", "0002.png", "0003.png"]
    )
    assert _digests(out) == expected
    assert not [p for p in out.rglob("*") if ".tmp" in p.name]


@pytest.mark.slow
def test_a_run_whose_cluster_stopped_resumes_from_its_finished_views(small, cluster, tmp_path):
    root, expected = small
    out = tmp_path / "out"

    def stop_the_cluster_after_a_first_view():
        if _wait_for(lambda: _complete(out, Pass.PHOTOMETRIC)):
            cluster.close()

    stopper = threading.Thread(target=stop_the_cluster_after_a_first_view)
    stopper.start()
    with pytest.raises(
        ExecutorError, match="cluster stopped before the run's tasks finished.*rerun"
    ):
        run_dense(
            Workspace.open(root),
            DenseOptions(),
            out=out,
            progress=False,
            executor=ExecutorOptions(
                "dask", address=cluster.scheduler_address, threads_per_worker=1
            ),
        )
    stopper.join()
    finished = {(p, name) for p in Pass for name in _complete(out, p)}
    assert 1 <= len(finished) < 8
    again = run_dense(Workspace.open(root), DenseOptions(), out=out, progress=False)
    assert {(r.pass_, r.name) for r in again.reports if r.action == "reused"} == finished
    assert {(r.pass_, r.name) for r in again.reports if r.action == "computed"} == {
        (p, f"000{i}.png") for p in Pass for i in range(4)
    } - finished
    assert _digests(out) == expected


@pytest.mark.slow
def test_an_unreachable_scheduler_is_named(small, tmp_path):
    root, _ = small
    with pytest.raises(
        ExecutorError, match="no Dask scheduler answers at executor.address=tcp://127.0.0.1:9"
    ):
        run_dense(
            Workspace.open(root),
            DenseOptions(fuse=False),
            out=tmp_path / "o",
            progress=False,
            executor=ExecutorOptions("dask", address="tcp://127.0.0.1:9"),
        )
    with pytest.raises(
        ExecutorError, match="executor.scheduler_file=.*nowhere.json does not exist"
    ):
        run_dense(
            Workspace.open(root),
            DenseOptions(fuse=False),
            out=tmp_path / "o",
            progress=False,
            executor=ExecutorOptions("dask", scheduler_file=str(tmp_path / "nowhere.json")),
        )


@pytest.mark.slow
def test_the_cli_runs_dense_on_a_local_cluster(small, tmp_path):
    import subprocess
    import sys

    root, expected = small
    ws = tmp_path / "ws"
    shutil.copytree(root, ws)
    # As README's example: a relative out=, the default verbosity.
    done = subprocess.run(
        [
            Path(sys.executable).with_name("dvpmvs"),
            "dense",
            "workspace=ws",
            "out=run_dask",
            "executor=dask",
            "executor.workers=2",
            "progress=false",
        ],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=tmp_path,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert _digests(tmp_path / "run_dask") == expected
    assert (tmp_path / "run_dask" / "report.html").is_file()
    said = done.stdout + done.stderr
    # Dask's own lines (its scheduler, nannies and workers, their shutdown) stay out of it.
    for dask_line in ("Traceback", "Nanny", "Scheduler", "Register worker", "Lost all workers"):
        assert dask_line not in said, said[-3000:]
    assert "executor=dask: 12 tasks on 2 worker(s)" in said


@pytest.mark.parametrize("server", ["http", "banner"])
def test_an_address_where_no_dask_scheduler_listens_is_named_within_seconds(server, monkeypatch):
    """A web server (which waits for a request) and a server that greets in its own protocol:
    Dask's client hung past 150 s on the first and tried to allocate exabytes on the second."""
    import http.server
    import socketserver

    from dvpmvs import executor
    from dvpmvs.executor import dask_client

    # The wait for a handshake, shortened: the web server's case waits it out.
    monkeypatch.setattr(executor, "_HANDSHAKE_SECONDS", 2)

    class Banner(socketserver.BaseRequestHandler):
        def handle(self):
            self.request.sendall(b"SSH-2.0-OpenSSH_9.2\r\n")
            time.sleep(1)

    handler = http.server.SimpleHTTPRequestHandler if server == "http" else Banner
    with socketserver.ThreadingTCPServer(("127.0.0.1", 0), handler) as httpd:
        threading.Thread(target=httpd.serve_forever, daemon=True).start()
        address = f"tcp://127.0.0.1:{httpd.server_address[1]}"
        start = time.monotonic()
        with pytest.raises(
            ExecutorError,
            match=f"no Dask scheduler answers at executor.address={address}.*not a Dask scheduler",
        ):
            with dask_client(ExecutorOptions("dask", address=address)):
                pass
        assert time.monotonic() - start < 7
        httpd.shutdown()


def test_a_dask_scheduler_passes_the_handshake_check():
    from dvpmvs.executor import _check_scheduler

    with distributed.LocalCluster(n_workers=0, processes=False, dashboard_address=None) as cluster:
        _check_scheduler(cluster.scheduler_address)


def test_without_bars_the_local_loop_says_how_far_each_stage_is(monkeypatch, caplog):
    # A view's maps take minutes on large photos: a CI or SLURM log gets a line at least every
    # HEARTBEAT_SECONDS (here shortened), with the views done of the stage and the time left.
    import logging

    import dvpmvs.stage_progress as stage_progress
    from dvpmvs.executor import Task, run_tasks

    monkeypatch.setattr(stage_progress, "HEARTBEAT_SECONDS", 0.15)
    monkeypatch.setattr(stage_progress, "POLL_SECONDS", 0.02)
    tasks = [Task(f"photometric:{i}", "photometric pass", time.sleep, (0.1,)) for i in range(4)]
    with caplog.at_level(logging.INFO, logger="dvpmvs.stage_progress"):
        run_tasks(tasks, progress=False)
    lines = [r.getMessage() for r in caplog.records]
    assert any(line.startswith("photometric pass: ") and " of 4 views (" in line for line in lines)
    assert any("left" in line for line in lines)
