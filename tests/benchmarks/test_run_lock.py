"""`wtbench run` and the run-folder lock: a second writer (``--force`` included) is refused while another
process holds the folder, and a rejected request leaves nothing behind."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys

import pytest
import torch

from benchmarks.runner.runs import RunRequest, execute, run_tag
from worldtree.infra.errors import UserError
from worldtree.infra.folder_lock import is_locked

HOLD = """
import sys, time
from worldtree.infra.folder_lock import FolderLock
lock = FolderLock(sys.argv[1], "run folder").acquire()
print("held", flush=True)
time.sleep(120)
"""


def _request(scene, runs, **kw) -> RunRequest:
    return RunRequest(
        scene=scene, method="static", runs_dir=runs, preset="quick", device="cpu", overrides={"steps": 2},
        progress=False, **kw,
    )  # fmt: skip


def test_a_held_run_folder_refuses_a_second_writer_and_force_and_is_taken_when_the_holder_dies(
    scene, tmp_path, small_quick
):
    req = _request(scene, tmp_path)
    first = execute(req)
    folder = tmp_path / "tiny" / "static" / run_tag("quick", {"steps": 2})
    assert first.folder.root == folder and (folder / "DONE").is_file()
    stamp = (folder / "DONE").stat().st_mtime_ns
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(folder)], stdout=subprocess.PIPE, env=env, text=True
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        for forced in (False, True):
            with pytest.raises(UserError, match=rf"in use by PID {holder.pid} on "):
                execute(dataclasses.replace(req, force=forced))
        # --force deleted nothing of the held folder.
        assert (folder / "DONE").stat().st_mtime_ns == stamp and (folder / "checkpoints").is_dir()
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    # The dead holder's lock is the kernel's to release; the next --force takes it and starts again.
    again = execute(dataclasses.replace(req, force=True))
    assert not again.skipped and (folder / "DONE").stat().st_mtime_ns != stamp
    assert not is_locked(folder)


def _one_frame_scene(tmp_path, write_tiny_scene):
    return write_tiny_scene(tmp_path / "one", frames=1)


@pytest.mark.parametrize("case", ["cuda_without_cuda", "too_few_frames", "bad_cameras_json", "out_under_file"])
def test_a_rejected_run_leaves_no_run_folder(case, scene, tmp_path, small_quick, write_tiny_scene):
    runs = tmp_path / "runs"
    req = _request(scene, runs)
    if case == "cuda_without_cuda":
        if torch.cuda.is_available():
            pytest.skip("CUDA is available here")
        req = dataclasses.replace(req, device="cuda")
        needle = "CUDA is not available"
    elif case == "too_few_frames":
        req = dataclasses.replace(req, scene=_one_frame_scene(tmp_path, write_tiny_scene), method="base")
        needle = "training frame"
    elif case == "bad_cameras_json":
        bad = write_tiny_scene(tmp_path / "bad", frames=2)
        meta = json.loads((bad / "cameras.json").read_text())
        meta["frames"][1]["camera"] = 99
        (bad / "cameras.json").write_text(json.dumps(meta))
        req = dataclasses.replace(req, scene=bad)
        needle = "camera 99"
    else:
        (tmp_path / "file").write_text("x")
        runs = tmp_path / "file" / "runs"
        req = dataclasses.replace(req, runs_dir=runs)
        needle = "is a file"
    with pytest.raises(UserError, match=needle):
        execute(req)
    assert not runs.exists(), sorted(str(p) for p in runs.rglob("*"))


def test_a_second_sweep_into_the_same_report_is_refused(tmp_path, write_tiny_scene):
    from typer.testing import CliRunner

    from benchmarks.cli import app

    scene = write_tiny_scene(tmp_path / "scenes" / "tiny", frames=2)
    report = tmp_path / "runs" / "sweep-seeds.json"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD.replace('"run folder"', '"sweep report"'), str(report)],
        stdout=subprocess.PIPE, env=env, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout.readline().strip() == "held"
        args = ["sweep", "--scenes", str(scene.parent), "--grid", "seeds", "--method", "static"]
        args += ["--preset", "quick", "-o", str(tmp_path / "runs")]
        with pytest.raises(UserError, match=rf"sweep report is in use by PID {holder.pid} on "):
            CliRunner().invoke(app, args, catch_exceptions=False)
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    assert not report.exists() and not (tmp_path / "runs" / "tiny").exists()
