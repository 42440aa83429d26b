"""The `nvls` command line: exit codes, one-line errors, and the commands chained end to end."""

from __future__ import annotations

import subprocess
import sys


def _nvls(*args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "nvidia_ls.cli", *map(str, args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=300,
    )


def test_cli_synth_build_verify_info(tmp_path):
    raw = tmp_path / "Rig"
    r = _nvls("synth", raw, "--cameras", 4, "--steps", 5, "--width", 48, "--height", 32, "--supersample", 1)
    assert r.returncode == 0, r.stderr
    assert (raw / "mv_images" / "00004" / "cam04.png").is_file() and (
        raw / "gt" / "poses_bounds.npy"
    ).is_file()
    r = _nvls("build", raw, "-o", tmp_path / "out", "--poses", raw / "gt" / "poses_bounds.npy", "--frames", 4)
    assert r.returncode == 0, r.stderr
    scene = tmp_path / "out" / "Rig"
    assert len(list((scene / "images").glob("*.png"))) == 4
    r = _nvls("verify", scene)
    assert r.returncode == 0 and "ok" in r.stderr
    r = _nvls("info", scene)
    assert r.returncode == 0 and "training frames" in r.stdout and "Rig" in r.stdout
    # Re-running over the existing output asks for --force; with it, it succeeds.
    r = _nvls("build", raw, "-o", tmp_path / "out", "--poses", raw / "gt" / "poses_bounds.npy")
    assert r.returncode == 2 and r.stderr.strip().startswith("error:") and "--force" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    r = _nvls("build", raw, "-o", tmp_path / "out", "--poses", raw / "gt" / "poses_bounds.npy", "--force")
    assert r.returncode == 0, r.stderr
    (scene / "gt_images" / "v001_t002.png").write_bytes(b"not a png")
    r = _nvls("verify", scene)
    assert r.returncode == 1 and "gt_images/v001_t002.png: checksum differs" in r.stderr


def test_cli_bad_input_is_one_line(tmp_path):
    r = _nvls("build", tmp_path / "nope", "-o", tmp_path / "out")
    assert r.returncode == 2
    assert r.stderr.strip().startswith("error:") and len(r.stderr.strip().splitlines()) == 1
    assert "Traceback" not in r.stderr
    r = _nvls("synth", tmp_path / "x", "--motion", "wobbly")
    assert r.returncode == 2 and "--motion" in r.stderr
