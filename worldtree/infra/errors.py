"""The one exception type that command-line tools turn into a one-line message."""

from __future__ import annotations


class UserError(Exception):
    """Bad input or configuration the user can fix.

    The message must name the file or option at fault and the fix, on one line. The CLIs print it as
    ``error: <message>`` and exit with status 2, without a traceback.
    """
