"""The package installs, both CLIs list their commands, and shared helpers behave."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from worldtree.imageio import read_image, read_mask, write_image
from worldtree.infra.atomic import atomic_dir, atomic_write_json, remove_stale_temporaries
from worldtree.infra.errors import UserError
from worldtree.infra.hashing import sha256_file, sha256_files


@pytest.mark.parametrize(
    ("module", "commands"),
    [
        ("benchmarks.cli", ["eval", "weights", "run", "sweep", "table", "plot", "prep", "demo"]),
        ("nvidia_ls.cli", ["build", "synth", "verify", "info"]),
    ],
)
def test_cli_help_lists_commands(module, commands):
    out = subprocess.run([sys.executable, "-m", module, "--help"], capture_output=True, text=True, check=True)
    for c in commands:
        assert c in out.stdout


def test_atomic_dir_leaves_nothing_on_failure(tmp_path):
    final = tmp_path / "out"
    with pytest.raises(RuntimeError), atomic_dir(final) as tmp:
        (tmp / "a.txt").write_text("half")
        raise RuntimeError("boom")
    assert not final.exists()
    assert list(tmp_path.iterdir()) == []


def test_atomic_dir_refuses_existing_without_force(tmp_path):
    final = tmp_path / "out"
    final.mkdir()
    (final / "keep").write_text("old")
    with pytest.raises(FileExistsError), atomic_dir(final) as tmp:
        (tmp / "new").write_text("new")
    assert (final / "keep").read_text() == "old"
    with atomic_dir(final, force=True) as tmp:
        (tmp / "new").write_text("new")
    assert sorted(p.name for p in final.iterdir()) == ["new"]


def test_remove_stale_temporaries_takes_what_a_killed_writer_left_and_nothing_else(tmp_path):
    import os
    import tempfile
    from pathlib import Path

    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    # Left by writers killed mid-write: the temporaries exactly as atomic_write_bytes / atomic_dir name them.
    fd, tmp_file = tempfile.mkstemp(prefix=".timing.json.", suffix=".tmp", dir=run)
    os.close(fd)
    fd, ckpt_tmp = tempfile.mkstemp(prefix=".ckpt_8.pt.", suffix=".tmp", dir=run / "checkpoints")
    os.close(fd)
    partial = Path(tempfile.mkdtemp(prefix=".renders.", suffix=".partial", dir=run))
    (partial / "v001_t000.png").write_bytes(b"half")
    (run / ".model.old").mkdir()
    # Kept: finished outputs, names that only look alike, and a lent root's folder behind a link.
    for name in ("timing.json", "a.tmp", ".notes.tmp", ".x.TOOLONG12.tmp", "old"):
        (run / name).write_text("keep")
    lent = tmp_path / "other_run" / "checkpoints"
    lent.mkdir(parents=True)
    fd, foreign = tempfile.mkstemp(prefix=".ckpt_4.pt.", suffix=".tmp", dir=lent)  # another run's live write
    os.close(fd)
    (run / "lent").symlink_to(lent, target_is_directory=True)

    removed = remove_stale_temporaries(run)
    assert removed == sorted(Path(p) for p in (tmp_file, ckpt_tmp, partial, run / ".model.old"))
    assert sorted(p.name for p in run.iterdir()) == [
        ".notes.tmp", ".x.TOOLONG12.tmp", "a.tmp", "checkpoints", "lent", "old", "timing.json"
    ]
    assert list((run / "checkpoints").iterdir()) == [] and Path(foreign).exists()
    assert remove_stale_temporaries(run) == [] and remove_stale_temporaries(tmp_path / "absent") == []


def test_atomic_json_roundtrip(tmp_path):
    atomic_write_json(tmp_path / "r.json", {"a": np.float32(1.5), "b": np.arange(3)})
    assert json.loads((tmp_path / "r.json").read_text()) == {"a": 1.5, "b": [0, 1, 2]}


def test_sha256_matches_hashlib(tmp_path):
    import hashlib

    p = tmp_path / "x.bin"
    p.write_bytes(b"abc" * 1000)
    assert sha256_file(p) == hashlib.sha256(b"abc" * 1000).hexdigest()
    q = tmp_path / "sub"
    q.mkdir()
    (q / "x.bin").write_bytes(b"abc" * 1000)
    assert sha256_files([p]) == sha256_files([q / "x.bin"])


def test_image_roundtrip_and_formats(tmp_path):
    import cv2

    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)
    write_image(tmp_path / "a.png", img)
    np.testing.assert_array_equal(read_image(tmp_path / "a.png"), img)
    # 16-bit: v*257 maps back exactly to v.
    cv2.imwrite(str(tmp_path / "b.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR).astype(np.uint16) * 257)
    np.testing.assert_array_equal(read_image(tmp_path / "b.png"), img)
    # RGBA: alpha is dropped.
    rgba = np.concatenate([cv2.cvtColor(img, cv2.COLOR_RGB2BGR), np.zeros((5, 7, 1), np.uint8)], axis=2)
    cv2.imwrite(str(tmp_path / "c.png"), rgba)
    np.testing.assert_array_equal(read_image(tmp_path / "c.png"), img)
    write_image(tmp_path / "m.png", img[:, :, 0] > 127)
    np.testing.assert_array_equal(read_mask(tmp_path / "m.png"), img[:, :, 0] > 127)


def test_unreadable_image_is_user_error(tmp_path):
    p = tmp_path / "bad.png"
    p.write_bytes(b"\x89PNG not really")
    with pytest.raises(UserError, match="bad.png"):
        read_image(p)
    with pytest.raises(UserError, match="no such image"):
        read_image(tmp_path / "missing.png")


def test_run_cli_exit_codes(capsys):
    import typer

    from worldtree.infra.cli_runner import run_cli

    app = typer.Typer()

    @app.command()
    def fail(kind: str) -> None:
        if kind == "exit":
            raise typer.Exit(3)
        raise UserError("--kind bad: use good")

    @app.command()
    def ok() -> None:
        pass

    import sys

    for argv, code in ((["fail", "exit"], 3), (["fail", "user"], 2), (["ok"], None)):
        sys_argv = sys.argv
        sys.argv = ["prog", *argv]
        try:
            if code is None:
                run_cli(app)
            else:
                with pytest.raises(SystemExit) as e:
                    run_cli(app)
                assert e.value.code == code
        finally:
            sys.argv = sys_argv
    assert "error: --kind bad: use good" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [["prep", "scene", "--no-such-option"], ["run", "--steps", "many"]])
def test_usage_errors_are_one_message_not_a_traceback(argv):
    """An unknown option or a bad value exits 2 with click's usage message and no traceback."""
    import subprocess
    import sys

    code = "import sys; from benchmarks.cli import main; sys.argv = ['wtbench', *sys.argv[1:]]; main()"
    res = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, timeout=120)
    assert res.returncode == 2, res.stderr
    assert "Traceback" not in res.stderr
    assert "Error:" in res.stderr
