"""The base of every error dvpmvs reports to a user (bad input, not a bug).

The command line prints these without a traceback; each message names the file or option at
fault and what to do about it.
"""


class DvpmvsError(Exception):
    """An input problem the user can fix; the message says how."""
