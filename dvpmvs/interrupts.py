"""Runs stopped by Ctrl-C or SIGTERM: the signal becomes :class:`~dvpmvs.errors.Interrupted` in
the main thread, so that a run leaves through its ``finally`` blocks (temporaries removed, locks
released) and the command ends with one line saying how far it got and how to resume."""

from __future__ import annotations

import sys

from dvpmvs.errors import Interrupted

__all__ = ["report_interruption", "stop_on_signals"]


def report_interruption(name: str, stop: Interrupted) -> None:
    import signal

    where = f": {stop.progress}" if stop.progress else ""
    print(
        f"dvpmvs {name}: interrupted ({signal.Signals(stop.signal_number).name}){where}; rerun the same command "
        f"to resume (what was finished is kept)",
        file=sys.stderr,
    )


def stop_on_signals() -> dict:
    """Ctrl-C (SIGINT) and SIGTERM raise :class:`Interrupted` in the main thread, so that a run
    stops through its ``finally`` blocks (temporaries removed, lock released) and says how far it
    got. pycolmap's import installs glog's failure handler, which answers SIGTERM with a native
    stack trace: it is imported first, so that ours replaces it. Returns the previous handlers."""
    import signal
    import threading

    import pycolmap  # noqa: F401 - see above

    if threading.current_thread() is not threading.main_thread():
        return {}

    def stop(signal_number, frame):
        raise Interrupted(signal_number)

    # A signal the caller ignores (SIGINT in a background job of a script) stays ignored.
    return {
        sig: signal.signal(sig, stop)
        for sig in (signal.SIGINT, signal.SIGTERM)
        if signal.getsignal(sig) is not signal.SIG_IGN
    }
