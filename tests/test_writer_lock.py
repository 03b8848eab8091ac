"""One writer per output folder: the lock names its holder, is re-entrant in its thread, excludes
other threads and processes, and is free once its holder has died."""

import os
import signal
import subprocess
import sys
import threading

import pytest

from dvpmvs.writer_lock import LOCK_NAME, FolderLockedError, lock_holder, writer_lock


def test_the_lock_is_reentrant_in_its_thread_and_leaves_a_record_of_its_last_holder(tmp_path):
    assert lock_holder(tmp_path) is None
    with writer_lock(tmp_path / "out") as folder:
        assert (folder / LOCK_NAME).is_file()
        with writer_lock(tmp_path / "out"):  # a dense run fusing at its end takes it again
            assert lock_holder(folder)["active"] is True
        assert lock_holder(folder)["active"] is True
    holder = lock_holder(tmp_path / "out")
    assert (
        holder["active"] is False
        and holder["pid"] == os.getpid()
        and holder["command"][0] == "dvpmvs"
    )


def test_another_thread_waits_for_the_lock_or_is_told_who_holds_it(tmp_path):
    outcome = []

    def second_writer(wait):
        try:
            with writer_lock(tmp_path, wait=wait):
                outcome.append("took it")
        except FolderLockedError as error:
            outcome.append(str(error))

    with writer_lock(tmp_path):
        thread = threading.Thread(target=second_writer, args=(0.0,))
        thread.start()
        thread.join()
        waiting = threading.Thread(target=second_writer, args=(30.0,))
        waiting.start()
    waiting.join()
    assert f"PID {os.getpid()} on" in outcome[0] and "out=DIR" in outcome[0]
    assert outcome[1] == "took it"


def test_the_lock_of_a_killed_writer_is_taken_over(tmp_path):
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            (
                "import sys, time; from dvpmvs.writer_lock import writer_lock\n"
                f"with writer_lock({str(tmp_path)!r}):\n    print('held', flush=True); time.sleep(600)"
            ),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(FolderLockedError, match=f"PID {holder.pid} on"):
            with writer_lock(tmp_path):
                pass
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    assert lock_holder(tmp_path)["active"] is True  # what the killed holder left
    with writer_lock(tmp_path):
        assert lock_holder(tmp_path)["pid"] == os.getpid()
