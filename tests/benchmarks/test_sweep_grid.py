"""`wtbench sweep`: grid contents, scene discovery, and a sweep that goes on past failures."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from benchmarks.runner.sweep import GridPoint, find_scenes, grid_points, resolve_grid, run_sweep
from methods.registry import get_method
from worldtree.infra.errors import UserError

WORLDTREE = get_method("worldtree")


def test_paper_ablation_grid_is_the_papers_nine_rows():
    # Rows of the paper's ablation table as (BA, SW, TPT, SAC) switches, written out by hand.
    table = [
        (0, 0, 0, 0), (0, 0, 1, 0), (0, 0, 1, 1),
        (1, 0, 0, 0), (1, 0, 1, 0), (1, 0, 1, 1),
        (1, 1, 0, 0), (1, 1, 1, 0), (1, 1, 1, 1),
    ]  # fmt: skip
    names = ("ba", "sw", "tpt", "sac")
    expected = []
    for row in table:
        off = {n for n, on in zip(names, row, strict=True) if not on}
        if "tpt" in off:
            off.discard("sac")  # root only: --ablate tpt alone says SAC is unused
        expected.append(sorted(off))
    got = [pt.options.get("ablate", []) for pt in grid_points("paper-ablation", WORLDTREE)]
    assert got == expected
    assert len({pt.label for pt in grid_points("paper-ablation", WORLDTREE)}) == 9


def test_depth_and_chain_grids():
    assert [pt.options for pt in grid_points("depth", WORLDTREE)] == [{"depth": d} for d in range(5)]
    assert [pt.options["chain_length"] for pt in grid_points("chain", WORLDTREE)] == [0, 1, 2, 3, 4]
    assert all(pt.options["depth"] == 4 for pt in grid_points("chain", WORLDTREE))
    with pytest.raises(UserError, match="unknown grid"):
        grid_points("nope", WORLDTREE)
    with pytest.raises(UserError, match="unknown grid of method 'static'"):
        grid_points("depth", get_method("static"))


def test_grid_names_its_method_and_a_method_its_first_grid():
    assert resolve_grid(None, "paper-ablation") == ("worldtree", "paper-ablation")
    assert resolve_grid("worldtree", None) == ("worldtree", "paper-ablation")
    assert resolve_grid("static", "seeds") == ("static", "seeds")
    with pytest.raises(UserError, match=r"^--grid seeds: every method has it; name one with --method$"):
        resolve_grid(None, "seeds")
    with pytest.raises(UserError, match=r"^--method static: has no grid of its own; give --grid seeds$"):
        resolve_grid("static", None)
    with pytest.raises(UserError, match=r"^--grid depth: method 'static' has the grids seeds$"):
        resolve_grid("static", "depth")
    with pytest.raises(
        UserError, match=r"^`wtbench sweep` needs --grid NAME .*worldtree: paper-ablation, depth"
    ):
        resolve_grid(None, None)


def test_find_scenes(tmp_path):
    for name in ("b", "a"):
        (tmp_path / "scenes" / name).mkdir(parents=True)
        (tmp_path / "scenes" / name / "cameras.json").write_text("{}")
    assert [p.name for p in find_scenes([tmp_path / "scenes"])] == ["a", "b"]
    assert find_scenes([tmp_path / "scenes" / "a"]) == [tmp_path / "scenes" / "a"]
    with pytest.raises(UserError, match="no scene folder"):
        find_scenes([tmp_path])
    with pytest.raises(UserError, match="no such folder"):
        find_scenes([tmp_path / "missing"])


def test_sweep_goes_on_past_a_failed_run(tmp_path):
    calls = []

    def execute(req):
        calls.append(req)
        if req[1].label == "bad":
            raise RuntimeError("exploded\nsecond line")
        return SimpleNamespace(
            skipped=req[1].label == "old", folder=SimpleNamespace(root=tmp_path), mean={"psnr": 1}
        )

    points = [GridPoint("bad", {}), GridPoint("old", {}), GridPoint("new", {"depth": 1})]
    scenes = [Path("s1"), Path("s2")]
    out = run_sweep(scenes, points, lambda s, p: (s, p), execute, log=lambda _: None)
    assert len(calls) == 6
    assert [o.status for o in out] == ["failed", "skipped", "done"] * 2
    assert out[0].error == "RuntimeError: exploded"


def test_cli_reports_failures_and_exits_nonzero(tmp_path, write_tiny_scene):
    # The scene's training images are gone, so every run of the seeds grid fails when it loads the scene:
    # the sweep must try all four, report each, write the JSON report and exit 1.
    scene = write_tiny_scene(tmp_path / "scenes" / "tiny", frames=2)
    for image in (scene / "images").iterdir():
        image.unlink()
    out = subprocess.run(
        [sys.executable, "-m", "benchmarks.cli", "sweep", "--scenes", str(scene.parent), "--grid", "seeds",
         "--method", "static", "--preset", "quick", "--device", "cpu", "-o", str(tmp_path / "runs")],
        capture_output=True, text=True,
    )  # fmt: skip
    assert out.returncode == 1, out.stderr
    assert "0 done, 0 already finished, 4 failed" in out.stdout
    report = json.loads((tmp_path / "runs" / "sweep-seeds.json").read_text())
    assert [r["status"] for r in report["runs"]] == ["failed"] * 4
    assert all("images" in r["error"] for r in report["runs"]), report["runs"][0]["error"]


def test_cli_refuses_a_grid_the_method_does_not_have(tmp_path, write_tiny_scene):
    scene = write_tiny_scene(tmp_path / "scenes" / "tiny", frames=2)
    out = subprocess.run(
        [sys.executable, "-m", "benchmarks.cli", "sweep", "--scenes", str(scene.parent), "--grid", "depth",
         "--method", "static", "--preset", "quick", "-o", str(tmp_path / "runs")],
        capture_output=True, text=True,
    )  # fmt: skip
    assert (
        out.returncode == 2
        and out.stderr.strip() == "error: --grid depth: method 'static' has the grids seeds"
    )
    assert not (tmp_path / "runs").exists()


def _dry_run(scene_dir: Path, runs: Path, *args: str) -> list[str]:
    out = subprocess.run(
        [sys.executable, "-m", "benchmarks.cli", "sweep", "--scenes", str(scene_dir), "--method", "worldtree",
         "--preset", "smoke", "--device", "cpu", "-o", str(runs), "--share-root", "--dry-run", *args],
        capture_output=True, text=True,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    return out.stdout.splitlines()


def test_share_root_lends_each_root_to_the_runs_that_train_it_alike(tmp_path, write_tiny_scene):
    """The paper's ablation grid has three roots (BA/SW off-off, on-off, on-on), each trained once and lent to
    the two rows with the same BA/SW; the tree grid trains one root for its four depths; seeds share none."""
    write_tiny_scene(tmp_path / "scenes" / "tiny", frames=6)
    runs = tmp_path / "runs"
    lines = _dry_run(tmp_path / "scenes", runs, "--grid", "paper-ablation")
    assert len(lines) == 9
    for group in (lines[0:3], lines[3:6], lines[6:9]):
        own = group[0].split(":")[1].split("{")[0].strip()
        assert "root from" not in group[0], group[0]
        tag = {"BA- SW- TPT- SAC-": "smoke-noba-nosw-notpt", "BA+ SW- TPT- SAC-": "smoke-nosw-notpt",
               "BA+ SW+ TPT- SAC-": "smoke-notpt"}[own]  # fmt: skip
        for line in group[1:]:
            assert line.endswith(f"root from {runs / 'tiny' / 'worldtree' / tag}"), line
    lines = _dry_run(tmp_path / "scenes", runs, "--grid", "tree")
    assert "root from" not in lines[0] and all(line.endswith("smoke-depth0") for line in lines[1:])
    assert not any("root from" in line for line in _dry_run(tmp_path / "scenes", runs, "--grid", "seeds"))
    assert not runs.exists()


def test_a_sweep_sharing_roots_trains_each_once(tmp_path, write_tiny_scene):
    """In process: depth 0 trains its root, depths 1, 2 and auto take it (recorded, and counted in their time),
    and a second sweep skips them all."""
    from benchmarks.reporting.results import cost_metrics

    scene = write_tiny_scene(tmp_path / "scenes" / "tiny", frames=6)
    runs = tmp_path / "runs"
    cmd = [sys.executable, "-m", "benchmarks.cli", "sweep", "--scenes", str(scene.parent), "--grid", "tree",
           "--method", "worldtree", "--preset", "smoke", "--device", "cpu", "-o", str(runs), "--share-root"]  # fmt: skip
    out = subprocess.run([*cmd, "--steps", "20"], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert "4 done" in out.stdout
    folder = runs / "tiny" / "worldtree"
    root = folder / "smoke-steps20-depth0"
    assert not (root / "checkpoints" / "root_from.json").exists()
    for d in (1, 2, "auto"):
        run = folder / f"smoke-steps20-depth{d}"
        timing = json.loads((run / "timing.json").read_text())
        assert timing["root_from"]["run"] == str(root.resolve()), d
        assert timing["train"]["steps_this_session"] == 0  # the root's fit was lent, finished
        assert f"--root-from {root}" in (run / "command.txt").read_text()
        assert cost_metrics(timing, None)["cpu_time_s"] > sum(timing["root_from"]["stages_cpu_s"].values()) > 0
    assert json.loads((runs / "sweep-tree.json").read_text())["config"]["share_root"] is True
    again = subprocess.run([*cmd, "--steps", "20"], capture_output=True, text=True)
    assert again.returncode == 0 and "0 done, 4 already finished" in again.stdout, again.stderr
