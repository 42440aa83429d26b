"""The folder lock: one writer, named holder, stale locks of dead processes taken over."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from worldtree.infra.errors import UserError
from worldtree.infra.folder_lock import FolderLock, is_locked, lock_paths, read_holder

HOLD = """
import sys, time
from worldtree.infra.folder_lock import FolderLock
lock = FolderLock(sys.argv[1], "run folder").acquire()
print("held", flush=True)
time.sleep(60)
"""


def _holder_process(folder):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(folder)], stdout=subprocess.PIPE, env=env, text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_second_process_is_refused_with_the_holders_pid_and_then_takes_a_dead_holders_lock(tmp_path):
    folder = tmp_path / "runs" / "scene" / "base" / "quick"
    proc = _holder_process(folder)
    try:
        assert is_locked(folder)
        holder = read_holder(folder)
        assert holder is not None and holder.pid == proc.pid
        with pytest.raises(UserError, match=rf"in use by PID {proc.pid} on "):
            FolderLock(folder, "run folder").acquire()
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    # The kernel released the dead process's lock; its owner record is stale but the lock is free.
    deadline = time.time() + 10
    while is_locked(folder) and time.time() < deadline:
        time.sleep(0.05)
    assert not is_locked(folder)
    with FolderLock(folder, "run folder") as lock:
        assert lock.held
        assert read_holder(folder).pid == os.getpid()
    assert read_holder(folder) is None
    assert not is_locked(folder)


def test_lock_lives_beside_the_folder_so_deleting_the_folder_keeps_it(tmp_path):
    folder = tmp_path / "run"
    lock_file, owner = lock_paths(folder)
    assert lock_file.parent == tmp_path and owner.parent == tmp_path
    with FolderLock(folder):
        folder.mkdir()
        folder.rmdir()
        assert lock_file.exists()
