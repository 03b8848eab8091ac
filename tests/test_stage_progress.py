"""Progress of one long library call, from a count read while it runs."""

import logging
import multiprocessing
import sqlite3
import subprocess
import sys
import threading
import time

import pytest

import dvpmvs.stage_progress as module
from dvpmvs.stage_progress import StepProgress, database_rows, in_child_process


def test_without_bars_a_line_says_what_is_done_and_the_time_left(monkeypatch, caplog):
    monkeypatch.setattr(module, "HEARTBEAT_SECONDS", 0.2)
    monkeypatch.setattr(module, "POLL_SECONDS", 0.05)
    done = {"n": 0}
    with caplog.at_level(logging.INFO, logger="dvpmvs.stage_progress"):
        with StepProgress("features", "photos", 10, lambda: done["n"]):
            for _ in range(4):
                time.sleep(0.15)
                done["n"] += 1
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) >= 2, lines
    assert any("features: " in line and " of 10 photos (" in line for line in lines)
    assert any("left" in line for line in lines if " 0 of " not in line)


def test_a_step_without_a_count_says_how_long_it_has_run(monkeypatch, caplog):
    monkeypatch.setattr(module, "HEARTBEAT_SECONDS", 0.1)
    monkeypatch.setattr(module, "POLL_SECONDS", 0.02)
    with caplog.at_level(logging.INFO, logger="dvpmvs.stage_progress"):
        with StepProgress("meshing", ""):
            time.sleep(0.35)
    assert any(r.getMessage().startswith("meshing: running for") for r in caplog.records)
    # A callback's steps are the count where there is no other.
    watch = StepProgress("mapping", "photos registered", 5)
    watch.advance()
    watch.advance()
    assert watch.line(watch.done(), 30) == (
        "mapping: 2 of 5 photos registered (40 %) in 30 s, about 45 s left"
    )


def test_rows_are_counted_while_another_connection_writes(tmp_path):
    database = tmp_path / "database.db"
    count = database_rows(database, "keypoints")
    assert count() is None  # not created yet
    writer = sqlite3.connect(database, check_same_thread=False)
    writer.execute("CREATE TABLE keypoints (image_id INTEGER, data BLOB)")
    writer.commit()
    seen = []
    stop = threading.Event()

    def read():
        while not stop.is_set():
            seen.append(count())

    reader = threading.Thread(target=read)
    reader.start()
    for image in range(50):
        writer.execute("INSERT INTO keypoints VALUES (?, ?)", (image, b"x" * 1000))
        writer.commit()
    stop.set()
    reader.join()
    assert count() == 50
    counts = [c for c in seen if c is not None]
    assert counts and max(counts) <= 50


class _Unpicklable(Exception):
    def __init__(self, code, reason):  # pickling calls it with one argument
        super().__init__(f"{code}: {reason}")


def _raise_unpicklable():
    raise _Unpicklable(3, "no")


def test_a_call_in_a_child_process_returns_its_result_and_raises_its_error():
    assert in_child_process(int, "12") == 12
    with pytest.raises(ValueError, match="invalid literal"):
        in_child_process(int, "twelve")
    # An error the parent cannot unpickle still comes back, named.
    with pytest.raises(RuntimeError, match="_Unpicklable: 3: no"):
        in_child_process(_raise_unpicklable)


def _in_a_daemon(queue):
    queue.put(in_child_process(int, "7"))


def test_a_daemonic_process_runs_the_call_in_place():
    # A pool's or Dask's worker is daemonic and may not start a child of its own.
    context = multiprocessing.get_context("spawn")
    queue = context.Queue()
    worker = context.Process(target=_in_a_daemon, args=(queue,), daemon=True)
    worker.start()
    assert queue.get(timeout=60) == 7
    worker.join()


def test_a_script_read_from_standard_input_runs_the_call_in_place():
    # A spawned child re-runs the parent's main script; "<stdin>" is no file it can run.
    script = (
        "from dvpmvs.stage_progress import in_child_process\nprint(in_child_process(int, '9'))\n"
    )
    done = subprocess.run(
        [sys.executable, "-"], input=script, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0 and done.stdout.strip() == "9", done.stderr[-500:]


def test_a_script_without_a_main_guard_is_told_to_add_one(tmp_path):
    # The spawned child re-runs the main script, whose top-level call then starts a child of
    # its own before the first has started: it dies, and the parent names the cause.
    script = tmp_path / "job.py"
    script.write_text(
        "from dvpmvs.stage_progress import in_child_process\nprint(in_child_process(int, '9'))\n"
    )
    done = subprocess.run(
        [sys.executable, str(script)], capture_output=True, text=True, timeout=120, cwd=tmp_path
    )
    assert done.returncode != 0
    assert "ended without an answer" in done.stderr
    assert 'if __name__ == "__main__":' in done.stderr
