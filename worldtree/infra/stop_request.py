"""A stop asked for by a signal, seen by the long loops even when the exception its handler raised was lost.

A signal handler raises its exception wherever the main thread is; if that is inside a callback whose errors
Python only prints (a weakref callback run by an import, a ``__del__``), the exception is dropped and the
command trains on (seen as a leave-one-out run still training two minutes after Ctrl-C). The handler
therefore also records the stop here, and every training step checks it (:func:`check`): at most one step
later the stop is raised again. Whoever installed the handler clears it on the way out (:func:`clear`).
"""

from __future__ import annotations

__all__ = ["check", "clear", "request"]

_pending: list[type[BaseException]] = []


def request(exc_type: type[BaseException]) -> None:
    """Record a stop that raises ``exc_type`` (KeyboardInterrupt, or a SIGTERM exception)."""
    _pending.append(exc_type)


def clear() -> None:
    """Forget every recorded stop (the command that asked for it has left)."""
    _pending.clear()


def check() -> None:
    """Raise the last recorded stop, if any (called once per training step)."""
    if _pending:
        raise _pending[-1]()
