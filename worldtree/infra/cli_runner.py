"""Running a command-line app: a :class:`~worldtree.infra.errors.UserError` becomes one ``error:`` line (exit 2),
Ctrl-C the documented interrupted line (exit 130), SIGTERM (``kill``, a batch system's stop) the same line as
"terminated" (exit 143) after the ``finally`` blocks ran, so a stop saves what an interrupt saves (the run's
timing ledger, temporary folders removed, locks released). Shared by the ``wtbench`` and ``nvls`` entry points;
the library itself never runs an app."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator, Mapping

from worldtree.infra import stop_request
from worldtree.infra.errors import SettingError, UserError

INTERRUPTED = "interrupted: re-run the same command to resume from the last checkpoint"
#: Ctrl-C of a command that keeps no checkpoint (nvls): its output appears whole or not at all.
INTERRUPTED_NO_CHECKPOINT = "interrupted: nothing was written (the unfinished output is removed); run the same command again"
NOT_A_FOLDER = "a part of this path is a file, not a folder; choose another path"


class Terminated(BaseException):
    """SIGTERM, raised in the main thread (:func:`signals_raise`) so that ``finally`` blocks run."""


def terminated_line(interrupted: str) -> str:
    """The ``interrupted`` line said of a SIGTERM."""
    return interrupted.replace("interrupted", "terminated", 1)


def stop_report(stop: BaseException, interrupted: str = INTERRUPTED) -> tuple[str, int]:
    """``(line, exit status)`` of a command stopped by ``stop``: KeyboardInterrupt -> ``interrupted``, 130;
    :class:`Terminated` -> the same line saying "terminated", 143."""
    if isinstance(stop, Terminated):
        return terminated_line(interrupted), 143
    return interrupted, 130


@contextlib.contextmanager
def signals_raise() -> Iterator[None]:
    """Inside: SIGINT raises KeyboardInterrupt and SIGTERM :class:`Terminated`, even when the process was
    started with SIGINT ignored (a shell's background job) or SIGTERM at its default (which would end the
    process without running ``finally`` blocks); the stop is also recorded for the training loops
    (:mod:`worldtree.infra.stop_request`), which raise it again where the first one was lost. Handlers are put back on exit; outside the main thread it
    does nothing (Python delivers signals there only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def on_int(signum, frame):
        stop_request.request(KeyboardInterrupt)  # raised again by the next training step if this one is lost
        raise KeyboardInterrupt

    def on_term(signum, frame):
        stop_request.request(Terminated)
        raise Terminated

    old = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    signal.signal(signal.SIGINT, on_int)
    signal.signal(signal.SIGTERM, on_term)
    try:
        yield
    finally:
        stop_request.clear()
        for sig, handler in old.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)


@contextlib.contextmanager
def options_named(options: Mapping[str, str]) -> Iterator[None]:
    """Inside: a :class:`SettingError` whose setting has an option in ``options`` (setting -> option, e.g.
    ``{"WorldTreeConfig.depth": "--depth"}``) comes out naming that option, as the user gave it. The one place
    where a command line's options replace the library's names of its settings."""
    try:
        yield
    except SettingError as e:
        if e.setting not in options:
            raise
        raise e.as_option(options[e.setting]) from e


def run_cli(app, interrupted: str = INTERRUPTED, options: Mapping[str, str] | None = None) -> None:
    """Run a typer/click ``app``; print a :class:`UserError` as one line (exit 2), Ctrl-C as exit 130 with
    the line ``interrupted`` (what a re-run does: resume from a checkpoint, or start again) and SIGTERM as exit
    143 with the same line saying "terminated". ``options``: the app's options of library settings that every
    command names alike (:func:`options_named`)."""
    import sys

    try:
        # With standalone_mode=False click returns a typer.Exit's code instead of exiting with it.
        with signals_raise(), options_named(options or {}):
            code = app(standalone_mode=False)
    except (KeyboardInterrupt, Terminated) as e:
        line, code = stop_report(e, interrupted)
        print(line, file=sys.stderr)
        raise SystemExit(code) from None
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    except NotADirectoryError as e:
        # An output path running through a file (-o FILE/sub) that a command's own check did not catch.
        print(f"error: {e.filename}: {NOT_A_FOLDER}", file=sys.stderr)
        raise SystemExit(2) from None
    except Exception as e:
        # Usage errors arrive here with standalone_mode=False. Recent typer releases vendor their own copy of
        # click, so the exception classes are matched by behaviour, not by click's class objects.
        exit_code = getattr(e, "exit_code", None)
        # Ctrl-C: typer turns it into Exit(130), click into Abort; both keep the KeyboardInterrupt as cause.
        if isinstance(e.__cause__ or e.__context__, KeyboardInterrupt):
            print(interrupted, file=sys.stderr)
            raise SystemExit(130) from None
        if callable(getattr(e, "show", None)) and isinstance(exit_code, int):
            e.show()
            raise SystemExit(exit_code) from None
        if type(e).__name__ == "Exit" and isinstance(exit_code, int):
            raise SystemExit(exit_code) from None
        if type(e).__name__ == "Abort":
            print("aborted", file=sys.stderr)
            raise SystemExit(1) from None
        raise
    if code == 130:
        # typer turns Ctrl-C into Exit(130), which click (standalone_mode=False) returns as this code.
        print(interrupted, file=sys.stderr)
    if isinstance(code, int) and code != 0:
        raise SystemExit(code)


def one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Show warnings (e.g. missing LPIPS weights) as one ``warning:`` line, without source code
    (``warnings.showwarning = one_line_warning``)."""
    import sys

    print(f"warning: {message}", file=sys.stderr)
