"""The one exception type for errors a user can cause (bad file, bad option, bad data).

The CLI turns a :class:`CmtoolError` into a one-line message and a non-zero exit; anything else
is a bug and keeps its traceback.
"""


class CmtoolError(Exception):
    """An error caused by the user's input, reported without a traceback."""


class Terminated(BaseException):
    """SIGTERM, raised in the main thread so that a command unwinds (temporary files removed, worker processes
    stopped) as it does on Ctrl-C; not an ``Exception``, so no ``except Exception`` swallows it."""
