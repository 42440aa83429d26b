"""`nvls build` leaves nothing behind and checks its output path and options up front: -o under a regular
file, --force over a file, stale temporaries of a killed build, out-of-range options, images smaller than the
SSIM window, the permissions of new folders, and one builder per scene."""

from __future__ import annotations

import math
import os
import shutil
import signal
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from nvidia_ls.build import MIN_SIZE, BuildConfig, build_scene
from nvidia_ls.masks import MaskConfig
from worldtree.infra.errors import UserError


@pytest.fixture
def raw(tiny_raw, tmp_path) -> Path:
    dst = tmp_path / "Raw"
    shutil.copytree(tiny_raw, dst)
    return dst


def _cfg(raw: Path, **kw) -> BuildConfig:
    return BuildConfig(poses=raw / "gt" / "poses_bounds.npy", **kw)


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "nvidia_ls.cli", *args], capture_output=True, text=True)


def _one_line_error(out: subprocess.CompletedProcess, needle: str) -> None:
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and len(lines) == 1, out.stderr
    assert lines[0].startswith("error: ") and needle in lines[0], out.stderr


@pytest.mark.parametrize("under", ["", "sub"])
def test_output_under_a_regular_file_is_refused_before_any_work(raw, tmp_path, under):
    blocker = tmp_path / "file"
    blocker.write_text("keep")
    out = blocker / under if under else blocker
    res = _cli("build", str(raw), "-o", str(out), "--poses", str(raw / "gt" / "poses_bounds.npy"))
    _one_line_error(res, "is a file")
    assert blocker.read_text() == "keep" and sorted(p.name for p in tmp_path.iterdir()) == ["Raw", "file"]


def test_force_over_a_file_leaves_no_old_copy(raw, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "Raw").write_text("a file where the scene goes")
    with pytest.raises(UserError, match="already exists; pass --force"):
        build_scene(raw, out, _cfg(raw))
    # --force replaces only a scene folder nvls made: a user's file is kept (issue #30).
    with pytest.raises(UserError, match="is a file, not a scene folder this tool made"):
        build_scene(raw, out, _cfg(raw, force=True))
    assert (out / "Raw").read_text() == "a file where the scene goes"
    (out / "Raw").unlink()
    build_scene(raw, out, _cfg(raw))
    scene = build_scene(raw, out, _cfg(raw, force=True))  # over its own scene folder
    assert (scene / "cameras.json").is_file()
    assert sorted(p.name for p in out.iterdir() if not p.name.endswith((".lock", ".owner"))) == ["Raw"]


def test_stale_temporaries_of_a_killed_build_are_removed_by_the_next_build(raw, tmp_path):
    out = tmp_path / "out"
    stale = out / ".Raw.k3x_9a0q.partial"
    (stale / "images").mkdir(parents=True)
    (out / ".Raw.old").write_text("left by a killed --force")
    other = out / ".Raw.b.k3x_9a0q.partial"  # another scene's ("Raw.b") temporary: not ours to remove
    other.mkdir()
    notes: list[str] = []
    build_scene(raw, out, _cfg(raw), log=notes.append)
    assert not stale.exists() and not (out / ".Raw.old").exists() and other.is_dir()
    assert sum("left by an interrupted build" in n for n in notes) == 2


@pytest.mark.parametrize(
    ("kw", "needle"),
    [
        ({"mask": MaskConfig(threshold=-5)}, "MaskConfig.threshold -5"),
        ({"mask": MaskConfig(threshold=256)}, "MaskConfig.threshold 256"),
        ({"mask": MaskConfig(threshold=math.nan)}, "MaskConfig.threshold nan"),
        ({"mask": MaskConfig(blur=4)}, "odd kernel"),
        ({"size": (MIN_SIZE - 1, MIN_SIZE - 1)}, f"at least {MIN_SIZE}x{MIN_SIZE}"),
        ({"sfm_tries": 0}, "BuildConfig.sfm_tries 0"),
        ({"sfm_threads": 0}, "BuildConfig.sfm_threads 0"),
        ({"test_camera": 0}, "BuildConfig.test_camera 0"),
        ({"num_cameras": 1}, "BuildConfig.num_cameras 1"),
        ({"seed": -1}, "BuildConfig.seed -1"),
    ],
)
def test_out_of_range_options_are_refused(raw, tmp_path, kw, needle):
    with pytest.raises(UserError, match=needle.replace("+", r"\+")) as e:
        build_scene(raw, tmp_path / "out", _cfg(raw, **kw))
    assert "\n" not in str(e.value) and not (tmp_path / "out").exists()


def test_mask_threshold_cli_is_one_line(raw, tmp_path):
    res = _cli("build", str(raw), "-o", str(tmp_path / "out"), "--mask-threshold", "-5")
    _one_line_error(res, "--mask-threshold -5.0: must be within 0..255")
    assert not (tmp_path / "out").exists()


def test_raw_images_smaller_than_the_ssim_window_are_refused(raw, tmp_path):
    import cv2

    for f in (raw / "mv_images").rglob("*.png"):
        cv2.imwrite(str(f), cv2.resize(cv2.imread(str(f)), (16, 9), interpolation=cv2.INTER_AREA))
    with pytest.raises(UserError, match=f"16x9 are smaller than {MIN_SIZE}x{MIN_SIZE}"):
        build_scene(raw, tmp_path / "out", _cfg(raw))
    assert not (tmp_path / "out").exists()


def test_new_folders_and_files_get_the_usual_permissions(raw, tmp_path):
    old = os.umask(0o022)
    try:
        scene = build_scene(raw, tmp_path / "out", _cfg(raw))
    finally:
        os.umask(old)
    assert stat.S_IMODE(scene.stat().st_mode) == 0o755
    assert stat.S_IMODE((scene / "cameras.json").stat().st_mode) == 0o644
    assert stat.S_IMODE((scene / "manifest.json").stat().st_mode) == 0o644


HOLD = """
import sys, time
from worldtree.infra.folder_lock import FolderLock
lock = FolderLock(sys.argv[1], "scene").acquire()
print("held", flush=True)
time.sleep(120)
"""


def test_a_scene_being_built_by_another_process_is_refused(raw, tmp_path):
    out = tmp_path / "out"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(out / "Raw")], stdout=subprocess.PIPE, env=env, text=True
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(UserError, match=rf"this scene is in use by PID {holder.pid} on "):
            build_scene(raw, out, _cfg(raw, force=True))
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    assert not (out / "Raw").exists()


def test_kill_9_at_random_points_of_a_build_then_the_next_build_is_identical_and_clean(raw, tmp_path):
    import json
    import random
    import time

    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path), OMP_NUM_THREADS="1")

    def cmd(out: Path, *extra: str) -> list[str]:
        poses = str(raw / "gt" / "poses_bounds.npy")
        return [
            sys.executable,
            "-m",
            "nvidia_ls.cli",
            "build",
            str(raw),
            "-o",
            str(out),
            "--poses",
            poses,
            *extra,
        ]

    ref = subprocess.run(cmd(tmp_path / "ref"), env=env, capture_output=True, text=True)
    assert ref.returncode == 0, ref.stderr
    out = tmp_path / "out"
    rng = random.Random(13)
    for _ in range(2):  # kill at random moments after the scene's lock exists (the build has begun)
        proc = subprocess.Popen(
            cmd(out, "--force"), env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
        deadline = time.monotonic() + 120
        while not (out / ".Raw.lock").exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.02)
        time.sleep(rng.uniform(0.0, 1.5))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    done = subprocess.run(cmd(out, "--force"), env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr

    def files(root: Path) -> dict:
        return json.loads((root / "Raw" / "manifest.json").read_text())["files"]

    assert files(out) == files(tmp_path / "ref")  # every file of the scene, by sha256
    left = sorted(p.name for p in out.iterdir() if p.name not in ("Raw", ".Raw.lock"))
    assert left == [], left  # no .partial, .old or owner record of the killed builds
