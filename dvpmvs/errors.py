"""The base of every error dvpmvs reports to a user (bad input, not a bug).

The command line prints these without a traceback; each message names the file or option at
fault and what to do about it.
"""


class DvpmvsError(Exception):
    """An input problem the user can fix; the message says how."""


class Interrupted(BaseException):
    """The run was stopped by a signal (Ctrl-C: SIGINT, or SIGTERM from a scheduler or ``kill``).

    A ``BaseException``, as ``KeyboardInterrupt`` is, so that no ``except Exception`` swallows it
    on its way out: the atomic writers remove their temporaries, pending records stay pending,
    the writer lock is released. ``progress`` says how far the run got, where a stage knows.
    """

    def __init__(self, signal_number: int, progress: str | None = None):
        super().__init__(signal_number)
        self.signal_number = signal_number
        self.progress = progress

    @property
    def exit_status(self) -> int:
        """The shell's status for a process ended by this signal: 128 + its number (130, 143)."""
        return 128 + self.signal_number
