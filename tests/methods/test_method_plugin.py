"""A method from another installed package: the docs' example (docs/examples/frame_copy.py) as a package of its
own, found through its `wtbench.methods` entry point, runs and sweeps its own grid with its own option, with no
change to this repository.

The package is "installed" as pip would leave it in a site folder: the module beside a ``.dist-info`` holding
its metadata and ``entry_points.txt``, on ``PYTHONPATH`` of the `wtbench` subprocesses (importlib.metadata
finds it there; nothing is installed into the running environment).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from worldtree.imageio import read_image

EXAMPLE = Path(__file__).resolve().parents[2] / "docs" / "examples" / "frame_copy.py"

PYPROJECT = """\
[project]
name = "frame-copy-method"
version = "0.1"
dependencies = ["worldtree-bench"]

[project.entry-points."wtbench.methods"]
frame-copy = "frame_copy_method"
"""


def install_example(site: Path) -> Path:
    """The example as package ``frame_copy_method`` (its source tree with a pyproject.toml, and its installed
    form under ``site``); returns ``site``."""
    src = site.parent / "frame-copy-method"
    (src / "frame_copy_method").mkdir(parents=True)
    (src / "frame_copy_method" / "__init__.py").write_text(EXAMPLE.read_text())
    (src / "pyproject.toml").write_text(PYPROJECT)
    site.mkdir()
    (site / "frame_copy_method").symlink_to(src / "frame_copy_method", target_is_directory=True)
    info = site / "frame_copy_method-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: frame-copy-method\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[wtbench.methods]\nframe-copy = frame_copy_method\n")
    return site


@pytest.fixture(scope="module")
def plugin_env(tmp_path_factory):
    site = install_example(tmp_path_factory.mktemp("plugin") / "site")
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(site), *sys.path]))


def wtbench(env, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "benchmarks.cli", *args], capture_output=True, text=True, env=env, cwd=cwd
    )


def test_installed_method_is_listed_with_its_option_and_grid(plugin_env, tmp_path):
    listed = wtbench(plugin_env, "run", "--list", cwd=tmp_path)
    assert listed.returncode == 0, listed.stderr
    assert "frame-copy" in listed.stdout and "options: --lag" in listed.stdout
    assert "lags" in wtbench(plugin_env, "sweep", "--list", cwd=tmp_path).stdout
    helped = wtbench(plugin_env, "run", "--help", cwd=tmp_path).stdout
    assert "--lag" in helped and "frame-copy: Show the" in helped
    # Without the package on the path, the same command knows no such method or option.
    plain = dict(plugin_env, PYTHONPATH=os.pathsep.join(sys.path))
    assert "frame-copy" not in wtbench(plain, "run", "--list", cwd=tmp_path).stdout


def test_installed_method_runs_and_sweeps_its_own_grid(plugin_env, tmp_path, write_tiny_scene):
    scene = write_tiny_scene(tmp_path / "scenes" / "tiny", frames=4)
    common = ["--preset", "quick", "--device", "cpu", "-o", "runs"]
    run = wtbench(plugin_env, "run", "--method", "frame-copy", "--scene", str(scene), "--lag", "1", *common,
                  cwd=tmp_path)  # fmt: skip
    assert run.returncode == 0, run.stderr
    folder = tmp_path / "runs" / "tiny" / "frame-copy" / "quick-lag1"
    assert (folder / "DONE").is_file(), run.stdout
    assert json.loads((folder / "config.json").read_text())["config"]["lag"] == 1
    # Its renders are the training frames one time earlier (the first one: itself).
    meta = json.loads((scene / "cameras.json").read_text())
    files = {fr["time"]: fr["file"] for fr in meta["frames"]}
    for t in files:
        got = read_image(folder / "renders" / f"v001_t{t:03d}.png").astype(int)
        assert np.abs(got - read_image(scene / files[max(t - 1, 0)]).astype(int)).max() <= 1

    swept = wtbench(
        plugin_env, "sweep", "--scenes", str(scene.parent), "--grid", "lags", *common, cwd=tmp_path
    )
    assert swept.returncode == 0, swept.stderr
    assert "sweep lags: 2 done, 1 already finished, 0 failed" in swept.stdout
    report = json.loads((tmp_path / "runs" / "sweep-lags.json").read_text())
    assert report["config"]["method"] == "frame-copy"
    assert [Path(r["folder"]).name for r in report["runs"]] == ["quick-lag0", "quick-lag1", "quick-lag2"]


def test_a_broken_plugin_breaks_no_other_method(tmp_path):
    site = tmp_path / "site"
    site.mkdir()
    (site / "broken_method.py").write_text("raise ImportError('needs a library that is not installed')\n")
    info = site / "broken_method-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: broken-method\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[wtbench.methods]\nbroken = broken_method\n")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(site), *sys.path]))
    listed = wtbench(env, "run", "--list", cwd=tmp_path)
    assert listed.returncode == 0 and "worldtree" in listed.stdout
    assert "method plug-in 'broken' not loaded (broken_method: ImportError: needs a library" in listed.stderr
    asked = wtbench(env, "run", "--method", "broken", "--scene", str(tmp_path), cwd=tmp_path)
    assert asked.returncode == 2
    assert asked.stderr.strip().splitlines()[-1] == (
        "error: --method broken: its plug-in failed to load (broken_method: ImportError: needs a library that is "
        "not installed); fix or uninstall it"
    )


def test_installed_method_scores_leave_one_out(plugin_env, tmp_path, write_tiny_scene):
    """`benchmarks.evaluation.leave_one_out` with the plug-in: it has no `render_between`, so the time between
    two kept frames is drawn by its `render` of the nearer one (halfway: the later); its own setting through
    `--set NAME:KEY=VALUE`."""
    from skimage.metrics import peak_signal_noise_ratio

    scene = write_tiny_scene(tmp_path / "scenes" / "tiny", frames=4)
    meta = json.loads((scene / "cameras.json").read_text())
    image = {fr["index"]: read_image(scene / fr["file"]) for fr in meta["frames"]}
    for label, sets in (("lag0", []), ("lag1", ["--set", "frame-copy:lag=1"])):
        done = subprocess.run(
            [sys.executable, "-m", "benchmarks.evaluation.leave_one_out", str(scene), "--frames", "1,2",
             "--methods", "frame-copy", "--preset", "quick", "--device", "cpu", "-o", "loo", "--label", label,
             *sets],
            capture_output=True, text=True, env=plugin_env, cwd=tmp_path,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr
    rows = {(r["label"], r["k"]): r for r in json.loads((tmp_path / "loo" / "loo.json").read_text())["runs"]}
    assert len(rows) == 4
    for k in (1, 2):
        # Kept frames k-1 and k+1; frame k's time is halfway: lag 0 draws the later kept frame, lag 1 the earlier.
        for label, shown in (("lag0", k + 1), ("lag1", k - 1)):
            row = rows[(label, k)]
            want = peak_signal_noise_ratio(image[k], image[shown], data_range=255)
            assert abs(row["psnr"] - want) < 1e-9 and row["method"] == "frame-copy" and "tree" not in row
        assert rows[("lag0", k)]["psnr_train_neighbours"] == {"prev": float("inf"), "next": float("inf")}
