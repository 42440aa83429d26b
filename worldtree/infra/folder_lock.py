"""One writer per output folder: an exclusive lock held for the writing process's life.

A run folder, a scene being built and a sweep's report each have exactly one writer. The lock is an OS file
lock (``filelock``, ``flock`` on Linux) on a file *beside* the folder (``PARENT/.NAME.lock``), so deleting the
folder (``--force``) never deletes the lock, and the kernel releases it when the holder dies: a lock left by a
killed process is simply taken by the next writer. Who holds it (PID, host, start time) is written to
``PARENT/.NAME.lock.owner`` so that a refused writer, ``--force`` and ``wtbench sweep --status`` can name it.
"""

from __future__ import annotations

import json
import os
import socket
import time
from dataclasses import dataclass
from pathlib import Path

import filelock

from worldtree.infra.atomic import atomic_write_json
from worldtree.infra.errors import UserError


@dataclass(frozen=True)
class LockHolder:
    """Who holds a folder's lock, as its holder recorded it."""

    pid: int
    host: str
    since: float  # seconds since the epoch

    def describe(self) -> str:
        return f"PID {self.pid} on {self.host}"


def lock_paths(folder: str | Path) -> tuple[Path, Path]:
    """The lock file and its owner record for ``folder`` (both beside it, in its parent)."""
    folder = Path(folder).absolute()
    return folder.parent / f".{folder.name}.lock", folder.parent / f".{folder.name}.lock.owner"


def read_holder(folder: str | Path) -> LockHolder | None:
    """The recorded holder of ``folder``'s lock, or None when no readable record exists.

    The record may be stale (its process gone); :func:`is_locked` tells whether the lock is held now.
    """
    _, owner = lock_paths(folder)
    try:
        data = json.loads(owner.read_text())
        return LockHolder(pid=int(data["pid"]), host=str(data["host"]), since=float(data["since"]))
    except (OSError, ValueError, KeyError, TypeError):
        return None


def is_locked(folder: str | Path) -> bool:
    """Whether some live process holds ``folder``'s lock now (tries it without waiting)."""
    lock_file, _ = lock_paths(folder)
    if not lock_file.exists():
        return False
    probe = filelock.FileLock(str(lock_file), timeout=0)
    try:
        probe.acquire()
    except filelock.Timeout:
        return True
    probe.release()
    return False


class FolderLock:
    """Exclusive lock on one output folder, held until :meth:`release` (or the process ends).

    Use as a context manager. ``what`` names the folder's role in the error message ("run folder",
    "scene", "sweep report"). Acquiring fails at once, with a one-line :class:`UserError` naming the
    holder's PID and host, when another process holds it.
    """

    def __init__(self, folder: str | Path, what: str = "folder") -> None:
        self.folder = Path(folder)
        self.what = what
        lock_file, self._owner = lock_paths(self.folder)
        self._lock = filelock.FileLock(str(lock_file), timeout=0)

    @property
    def held(self) -> bool:
        return self._lock.is_locked

    def acquire(self) -> FolderLock:
        self._owner.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._lock.acquire()
        except filelock.Timeout:
            holder = read_holder(self.folder)
            who = holder.describe() if holder else "another process"
            raise UserError(
                f"{self.folder}: this {self.what} is in use by {who}; wait for it to finish or stop it first"
            ) from None
        atomic_write_json(self._owner, {"pid": os.getpid(), "host": socket.gethostname(), "since": time.time()})
        return self

    def release(self) -> None:
        if self._lock.is_locked:
            # Remove the owner record first: a record without a held lock would name a finished process.
            try:
                self._owner.unlink()
            except FileNotFoundError:
                pass
            self._lock.release()

    def __enter__(self) -> FolderLock:
        return self.acquire()

    def __exit__(self, *exc: object) -> None:
        self.release()
