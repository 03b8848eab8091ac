"""Signals become an interruption in the main thread, and the command says how far it got."""

import os
import signal
import threading

import pytest

from dvpmvs.errors import Interrupted
from dvpmvs.interrupts import report_interruption, stop_on_signals


@pytest.fixture
def handlers():
    """The handlers of a program started from a terminal, whatever started the tests (a shell's
    background job inherits SIGINT ignored, which stop_on_signals rightly leaves alone)."""
    saved = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    yield
    for sig, handler in saved.items():
        signal.signal(sig, handler)


def test_sigterm_raises_an_interruption_in_the_main_thread(handlers):
    previous = stop_on_signals()
    assert set(previous) == {signal.SIGINT, signal.SIGTERM}
    with pytest.raises(Interrupted) as stopped:
        os.kill(os.getpid(), signal.SIGTERM)
        signal.sigtimedwait([], 0)  # let the handler run here
    assert stopped.value.signal_number == signal.SIGTERM


def test_an_ignored_signal_stays_ignored_and_other_threads_install_nothing(handlers):
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    assert set(stop_on_signals()) == {signal.SIGTERM}
    assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    found = []
    thread = threading.Thread(target=lambda: found.append(stop_on_signals()))
    thread.start()
    thread.join()
    assert found == [{}]


def test_the_report_names_the_signal_the_progress_and_how_to_resume(capsys):
    report_interruption("dense", Interrupted(signal.SIGINT, "geometric pass: 2 of 5 views"))
    said = capsys.readouterr().err
    assert said.startswith("dvpmvs dense: interrupted (SIGINT): geometric pass: 2 of 5 views;")
    assert "rerun the same command to resume" in said
