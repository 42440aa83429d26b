"""`wtbench run` as a real process under faults: Ctrl-C (SIGINT) prints the documented line and exits 130, SIGTERM
the same line as "terminated" and 143, both keeping the interrupted session's time;
``kill -9`` at random points followed by the same command finishes with results identical to an uninterrupted
run and leaves nothing stale; two real processes on one run folder: the second is refused at once."""

from __future__ import annotations

import json
import os
import random
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from worldtree.infra.cli_runner import INTERRUPTED, terminated_line
from worldtree.infra.folder_lock import lock_paths

# Tiny static run: 12 steps, a checkpoint every 4 (so kills land before, between and after checkpoints).
SETS = ["--set", "init_num_points=200", "--set", "checkpoint_every=4"]


def _env() -> dict[str, str]:
    # One thread: the reference and the resumed runs must sum floats in the same order.
    return dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path), OMP_NUM_THREADS="1")


def _cmd(scene: Path, runs: Path, steps: int = 12) -> list[str]:
    return [
        sys.executable, "-m", "benchmarks.cli", "run", "--method", "static", "--scene", str(scene),
        "-o", str(runs), "--preset", "quick", "--steps", str(steps), "--device", "cpu", "--tag", "t", *SETS,
    ]  # fmt: skip


def _start(cmd: list[str]) -> subprocess.Popen:
    return subprocess.Popen(cmd, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for(path: Path, proc: subprocess.Popen, timeout: float = 120.0) -> bool:
    """Wait until ``path`` exists (True) or ``proc`` ended first (False)."""
    deadline = time.monotonic() + timeout
    while not path.exists():
        if proc.poll() is not None:
            return False
        assert time.monotonic() < deadline, f"{path} did not appear"
        time.sleep(0.02)
    return True


def _stale(runs: Path) -> list[str]:
    """Leftovers of interrupted writes under ``runs`` (temporary files/folders, a live lock's owner record)."""
    return sorted(
        str(p.relative_to(runs))
        for p in runs.rglob("*")
        if p.name.endswith((".tmp", ".partial", ".old", ".lock.owner"))
    )


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl_c", "sigterm"])
def test_a_stop_prints_the_interrupted_line_and_keeps_the_session_time(scene, tmp_path, sig):
    """Ctrl-C exits 130, SIGTERM (kill, a batch system) 143 with the same line saying "terminated"; both
    leave through the stage's ``finally``, so the run's ledger holds the interrupted training's time."""
    proc = _start(_cmd(scene, tmp_path / "runs", steps=100_000))
    # Interrupt the training loop (the documented case), not the first-use kernel build before it: wait for
    # the first checkpoint.
    checkpoints = tmp_path / "runs" / "tiny" / "static" / "t" / "checkpoints"
    deadline = time.monotonic() + 300
    while not any(checkpoints.glob("ckpt_*.pt")):
        assert proc.poll() is None and time.monotonic() < deadline, "the run made no checkpoint"
        time.sleep(0.02)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    # The progress line is redrawn with carriage returns; the message follows on a line of its own.
    lines = [ln.strip() for ln in re.split(r"[\r\n]", err) if ln.strip()]
    term = sig == signal.SIGTERM
    assert proc.returncode == (143 if term else 130), err
    assert lines[-1] == (terminated_line(INTERRUPTED) if term else INTERRUPTED) and "Traceback" not in err, err
    ledger = json.loads((checkpoints / "timing_sessions.json").read_text())
    assert ledger["stages_s"].get("train", 0.0) > 0.0, ledger  # written on the way out, not lost


def test_a_second_process_on_the_same_run_folder_is_refused_at_once(scene, tmp_path):
    runs = tmp_path / "runs"
    folder = runs / "tiny" / "static" / "t"
    first = _start(_cmd(scene, runs, steps=100_000))
    try:
        assert _wait_for(folder / "config.json", first)
        for extra in ([], ["--force"]):
            second = subprocess.run(
                _cmd(scene, runs, steps=100_000) + extra, env=_env(), capture_output=True, text=True
            )
            lines = second.stderr.strip().splitlines()
            assert second.returncode == 2 and len(lines) == 1, second.stderr
            assert f"in use by PID {first.pid} on " in lines[0]
        assert first.poll() is None and (folder / "config.json").is_file()  # --force deleted nothing
    finally:
        first.send_signal(signal.SIGKILL)
        first.wait()


def _model(folder: Path) -> dict[str, torch.Tensor]:
    obj = torch.load(folder / "model" / "gaussians.pt", map_location="cpu", weights_only=False)
    return {k: v for k, v in _flatten(obj).items()}


def _flatten(obj, prefix: str = "") -> dict:
    if isinstance(obj, dict):
        out = {}
        for k, v in obj.items():
            out.update(_flatten(v, f"{prefix}{k}."))
        return out
    return {prefix: obj}


def test_kill_9_at_random_points_then_the_same_command_finishes_identically(scene, tmp_path):
    ref_runs, runs = tmp_path / "ref", tmp_path / "runs"
    ref = subprocess.run(_cmd(scene, ref_runs), env=_env(), capture_output=True, text=True)
    assert ref.returncode == 0, ref.stderr
    folder = runs / "tiny" / "static" / "t"
    rng = random.Random(13)
    for _ in range(2):  # two kills at random moments after the run folder exists, then a run to the end
        proc = _start(_cmd(scene, runs))
        if _wait_for(folder / "config.json", proc):
            time.sleep(rng.uniform(0.0, 4.0))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    done = subprocess.run(_cmd(scene, runs), env=_env(), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    ref_folder = ref_runs / "tiny" / "static" / "t"
    assert (ref_folder / "metrics.csv").read_bytes() == (folder / "metrics.csv").read_bytes()
    ref_renders = sorted((ref_folder / "renders").iterdir())
    assert [p.name for p in ref_renders] == sorted(p.name for p in (folder / "renders").iterdir())
    for p in ref_renders:
        assert p.read_bytes() == (folder / "renders" / p.name).read_bytes(), p.name
    a, b = _model(ref_folder), _model(folder)
    assert a.keys() == b.keys()
    for k in a:
        if isinstance(a[k], torch.Tensor):
            assert torch.equal(a[k], b[k]), k
    assert _stale(runs) == [] and not lock_paths(folder)[1].exists()


def test_a_resumed_run_removes_what_a_killed_write_left(scene, tmp_path):
    """The kill above lands mid-write only by chance; here the leftovers are placed: an unfinished run folder
    holding a killed atomic write's temporary file and folder. The same command removes them and finishes."""
    import tempfile

    runs = tmp_path / "runs"
    folder = runs / "tiny" / "static" / "t"
    first = subprocess.run(_cmd(scene, runs), env=_env(), capture_output=True, text=True)
    assert first.returncode == 0, first.stderr
    (folder / "DONE").unlink()  # unfinished again: the next run resumes it
    fd, _ = tempfile.mkstemp(prefix=".timing.json.", suffix=".tmp", dir=folder)
    os.close(fd)
    tempfile.mkdtemp(prefix=".renders.", suffix=".partial", dir=folder)
    assert len(_stale(runs)) == 2
    done = subprocess.run(_cmd(scene, runs), env=_env(), capture_output=True, text=True)
    assert done.returncode == 0 and "resuming" in done.stderr, done.stderr
    assert _stale(runs) == [] and (folder / "DONE").is_file()
