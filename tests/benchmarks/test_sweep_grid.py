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
