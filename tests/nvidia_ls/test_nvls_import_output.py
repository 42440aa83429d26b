"""What `nvls import` prints: the `run with its priors:` command is one line at any terminal width (a log
wraps nothing), and Ctrl-C says what a re-run does without talking of checkpoints nvls does not have."""

from __future__ import annotations

import os
import shlex
import subprocess
import sys

import pytest

from benchmarks.fixtures.planar_scene import PlanarScene, PlanarSceneConfig
from nvidia_ls.importer import OPTIONAL_WHY
from tests.nvidia_ls.dynamicnerf_export import export_dynamicnerf


def test_run_command_is_one_line_in_a_narrow_log(tmp_path):
    src = tmp_path / "src"
    export_dynamicnerf(PlanarScene(PlanarSceneConfig(width=40, height=24, num_frames=3, supersample=1)), src)
    out = tmp_path / ("a-long-folder-name-" * 4) / "scenes"
    env = {**os.environ, "COLUMNS": "80"}
    r = subprocess.run(
        [sys.executable, "-m", "nvidia_ls.cli", "import", str(src), "-o", str(out)],
        capture_output=True, text=True, timeout=300, env=env,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    line = next(ln for ln in r.stderr.splitlines() if ln.startswith("run with its priors: "))
    assert len(line) > 80  # long enough that an 80-column console would have wrapped it
    argv = shlex.split(line.removeprefix("run with its priors: "))
    assert argv[:3] == ["wtbench", "run", "--scene"] and argv[3] == str(out / "src")
    assert argv[argv.index("--masks") + 1] == str(out / "src" / "imported" / "masks")
    assert "--depth-maps" not in argv  # relative disparity: offered on its own line, not suggested
    opt = next(ln for ln in r.stderr.splitlines() if ln.startswith("not suggested, "))
    assert ": " not in OPTIONAL_WHY  # the line's one ": " comes before the command
    full = shlex.split(opt.partition(": ")[2])
    assert full[: len(argv)] == argv and full[full.index("--depth-maps") + 1] == str(out / "src" / "imported" / "disp")
    assert "priors.depth_import.fit_shift=false" in full


def test_ctrl_c_during_an_import_names_no_checkpoint(tmp_path, monkeypatch, capsys):
    import nvidia_ls.importer
    from nvidia_ls import cli

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(nvidia_ls.importer, "import_scene", interrupted)
    monkeypatch.setattr(sys, "argv", ["nvls", "import", str(tmp_path), "-o", str(tmp_path / "o")])
    with pytest.raises(SystemExit) as e:
        cli.main()
    assert e.value.code == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert (
        err[-1].startswith("interrupted:") and "checkpoint" not in err[-1] and "Traceback" not in "".join(err)
    )
