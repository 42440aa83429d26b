"""`wtbench sweep --executor`: option parsing, run states read from run folders, and the local executor's
worker processes (one torch thread each) against the same runs made in-process."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.runner import sweep_executors as se
from benchmarks.runner.runs import RunFolder
from worldtree.infra.errors import UserError
from worldtree.infra.folder_lock import FolderLock


@pytest.mark.parametrize(
    ("text", "minutes"),
    [("90", 90), ("1:30", 2), ("1:00", 1), ("2:00:00", 120), ("1:30:30", 91), ("1-0", 1440),
     ("2-03", 2 * 1440 + 180), ("1-02:03", 1440 + 123), ("1-02:03:04", 1440 + 124)],
)  # fmt: skip
def test_slurm_time_in_minutes(text, minutes):
    # Slurm's own forms: MM, MM:SS, HH:MM:SS, D-HH, D-HH:MM, D-HH:MM:SS; seconds round up to a minute.
    assert se.parse_slurm_time(text) == minutes


@pytest.mark.parametrize("text", ["", "abc", "0", "1:2:3:4", "-5", "x-01"])
def test_slurm_time_refuses_nonsense(text):
    with pytest.raises(UserError, match="--slurm-time"):
        se.parse_slurm_time(text)


def test_slurm_args():
    assert se.parse_slurm_args(["account=abc", "--qos=high", "exclude=n1,n2"]) == {
        "account": "abc",
        "qos": "high",
        "exclude": "n1,n2",
    }
    with pytest.raises(UserError, match="KEY=VALUE"):
        se.parse_slurm_args(["account"])


def test_auto_executor_follows_sbatch_on_path(monkeypatch):
    monkeypatch.setattr(se.shutil, "which", lambda name: None)
    assert se.resolve_kind("auto") == "local"
    with pytest.raises(UserError, match="sbatch"):
        se.resolve_kind("slurm")
    monkeypatch.setattr(se.shutil, "which", lambda name: "/usr/bin/" + name)
    assert se.resolve_kind("auto") == "slurm"
    with pytest.raises(UserError, match="--executor"):
        se.resolve_kind("kubernetes")


def _run(root: Path, name: str, files: dict[str, object]) -> Path:
    folder = root / "scene" / "static" / name
    folder.mkdir(parents=True)
    for fname, content in files.items():
        (folder / fname).write_text(json.dumps(content))
    return folder


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_status_reads_run_folders_and_jobs(tmp_path, monkeypatch):
    host = socket.gethostname()
    job = {"executor": "slurm", "state": "submitted", "log": "/logs/7.err"}
    _run(tmp_path, "a-done", {"config.json": {}, "DONE": {"mean": {"psnr": 20.5}}, "job.json": {"jobs": [
        {**job, "job_id": "5", "state": "done"}]}})  # fmt: skip
    _run(tmp_path, "b-queued", {"job.json": {"jobs": [{**job, "job_id": "7"}]}})
    _run(tmp_path, "c-slurm-running", {"job.json": {"jobs": [{**job, "job_id": "8"}]}})
    _run(tmp_path, "d-cancelled", {"config.json": {}, "job.json": {"jobs": [{**job, "job_id": "9"}]}})
    _run(tmp_path, "e-failed", {"config.json": {}, "job.json": {"jobs": [
        {**job, "job_id": "10", "state": "failed", "error": "ValueError: boom"}]}})  # fmt: skip
    locked = _run(tmp_path, "f-locked", {"config.json": {}})
    _run(tmp_path, "g-local-live", {"job.json": {"jobs": [
        {"executor": "local", "job_id": str(os.getpid()), "host": host, "state": "submitted"}]}})  # fmt: skip
    _run(tmp_path, "h-local-dead", {"config.json": {}, "job.json": {"jobs": [
        {"executor": "local", "job_id": str(_dead_pid()), "host": host, "state": "submitted"}]}})  # fmt: skip
    _run(tmp_path, "i-interrupted", {"config.json": {}})
    (tmp_path / ".sweep-jobs" / "x" / "y").mkdir(parents=True)  # submitit's files: not a run
    asked = []

    def squeue(ids):
        asked.append(sorted(ids))
        return {"7": "PENDING", "8": "RUNNING", "9": "CANCELLED"}  # 9 cancelled: no longer alive

    monkeypatch.setattr(se, "slurm_states", squeue)
    with FolderLock(locked, "run folder"):
        states = {Path(r.run).name: r for r in se.run_states(tmp_path)}
    assert asked == [["7", "8", "9"]]  # one squeue call, only for submitted Slurm jobs
    got = {name: r.state for name, r in states.items()}
    assert got == {
        "a-done": "done",
        "b-queued": "queued",
        "c-slurm-running": "running",
        "d-cancelled": "failed",
        "e-failed": "failed",
        "f-locked": "running",
        "g-local-live": "running",
        "h-local-dead": "failed",
        "i-interrupted": "unfinished",
    }
    assert states["a-done"].job_id == "5" and "psnr 20.500" in states["a-done"].detail
    assert "ValueError: boom" in states["e-failed"].detail and "/logs/7.err" in states["e-failed"].detail
    assert f"PID {os.getpid()} on {host}" in states["f-locked"].detail
    assert "cancelled" in states["d-cancelled"].detail


def test_claimed_elsewhere(tmp_path, monkeypatch):
    folder = RunFolder(tmp_path / "s" / "m" / "t")
    assert se.claimed_elsewhere(folder) is None
    folder.root.mkdir(parents=True)
    (folder.root / "job.json").write_text(json.dumps({"jobs": [{"executor": "slurm", "job_id": "3",
                                                                "state": "submitted"}]}))  # fmt: skip
    monkeypatch.setattr(se, "slurm_states", lambda ids: {"3": "PENDING"})
    assert se.claimed_elsewhere(folder) == "slurm job 3 is pending"
    monkeypatch.setattr(se, "slurm_states", lambda ids: {})  # Slurm forgot it: gone
    assert se.claimed_elsewhere(folder) is None
    monkeypatch.setattr(se, "slurm_states", lambda ids: None)  # Slurm cannot be asked: do not run it twice
    assert se.claimed_elsewhere(folder) == "slurm job 3 is unknown"
    with FolderLock(folder.root, "run folder"):
        assert se.claimed_elsewhere(folder).startswith(f"in use by PID {os.getpid()}")


def test_first_error_line_of_a_job_traceback():
    tb = (
        "Job (task=0) failed during processing with trace:\n----------------------\n"
        'Traceback (most recent call last):\n  File "x.py", line 3, in f\n    raise UserError("bad")\n'
        "worldtree.infra.errors.UserError: runs/x/config.json: damaged; re-run with --force\n"
    )
    assert se._first_error_line(tb) == "runs/x/config.json: damaged; re-run with --force"
    assert se._first_error_line("Traceback:\n  File 'a'\nValueError: nope\n") == "ValueError: nope"


@pytest.mark.slow
def test_local_workers_match_in_process_runs_and_report_a_failed_run(tmp_path, write_tiny_scene):
    scene = write_tiny_scene(tmp_path / "scenes" / "tiny", frames=2)
    sweep = [sys.executable, "-m", "benchmarks.cli", "sweep", "--scenes", str(scene), "--grid", "seeds",
             "--method", "static", "--preset", "quick", "--steps", "3", "--device", "cpu",
             "--set", "init_num_points=50"]  # fmt: skip
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    # Seed 2's folder holds a damaged config.json: its job fails, the sweep reports it and goes on.
    bad = tmp_path / "workers" / "tiny" / "static"
    ref = subprocess.run(sweep + ["-o", str(tmp_path / "inproc")], env=env, capture_output=True, text=True)
    assert ref.returncode == 0, ref.stderr
    names = sorted(p.name for p in (tmp_path / "inproc" / "tiny" / "static").iterdir() if p.is_dir())
    assert len(names) == 4
    (bad / names[2]).mkdir(parents=True)
    (bad / names[2] / "config.json").write_text("{not json")
    out = subprocess.run(
        # One torch thread per worker (CPUs // max-parallel), as the in-process runs have (OMP_NUM_THREADS).
        sweep + ["--executor", "local", "--max-parallel", str(max(2, os.cpu_count() or 1)),
                 "-o", str(tmp_path / "workers")],
        env=env, capture_output=True, text=True,
    )  # fmt: skip
    assert out.returncode == 1, out.stdout + out.stderr
    assert "3 done, 0 already finished, 1 failed" in out.stdout
    assert f"failed: tiny seed 2: {bad / names[2] / 'config.json'}: damaged" in out.stdout
    report = json.loads((tmp_path / "workers" / "sweep-seeds.json").read_text())
    assert report["config"]["executor"] == "local"
    for r in report["runs"]:
        assert r["executor"] == "local" and r["job_id"].isdigit() and Path(r["log"]).is_file()
        if r["status"] == "done":
            assert r["device"] == "cpu" and r["host"] == socket.gethostname()
            assert r["wall_s"] > 0 and r["queue_wait_s"] >= 0
            ref_done = tmp_path / "inproc" / "tiny" / "static" / Path(r["folder"]).name / "DONE"
            assert r["mean"] == pytest.approx(json.loads(ref_done.read_text())["mean"], abs=1e-6)
    assert [r["status"] for r in report["runs"]] == ["done", "done", "failed", "done"]
