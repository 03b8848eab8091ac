"""The two kinds of stop a user sees: an input error, and a run interrupted by a signal."""

import signal

import pytest

from dvpmvs.errors import DvpmvsError, Interrupted


def test_an_interruption_passes_every_except_exception_and_carries_the_shells_status():
    with pytest.raises(Interrupted) as stopped:
        try:
            raise Interrupted(signal.SIGTERM, progress="photometric pass: 3 of 5 views")
        except Exception:  # noqa: BLE001 - what an interruption must get through
            pytest.fail("an interruption was caught as an error")
    assert stopped.value.exit_status == 143 and Interrupted(signal.SIGINT).exit_status == 130
    assert stopped.value.progress == "photometric pass: 3 of 5 views"
    assert issubclass(DvpmvsError, Exception) and not issubclass(Interrupted, Exception)
