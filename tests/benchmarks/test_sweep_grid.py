"""`wtbench sweep`: grid contents, scene discovery, and a sweep that goes on past failures."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from benchmarks.runner.sweep import GridPoint, find_scenes, grid_points, run_sweep
from worldtree.errors import UserError


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
    got = [pt.options.get("ablate", []) for pt in grid_points("paper-ablation")]
    assert got == expected
    assert len({pt.label for pt in grid_points("paper-ablation")}) == 9


def test_depth_and_chain_grids():
    assert [pt.options for pt in grid_points("depth")] == [{"depth": d} for d in range(5)]
    assert [pt.options["chain_length"] for pt in grid_points("chain")] == [0, 1, 2, 3, 4]
    assert all(pt.options["depth"] == 4 for pt in grid_points("chain"))
    with pytest.raises(UserError, match="unknown grid"):
        grid_points("nope")


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
    # The static method refuses tree options, so every run of the depth grid fails: the sweep must try
    # all five, report each, write the JSON report and exit 1.
    scene = write_tiny_scene(tmp_path / "scenes" / "tiny", frames=2)
    out = subprocess.run(
        [sys.executable, "-m", "benchmarks.cli", "sweep", "--scenes", str(scene.parent), "--grid", "depth",
         "--method", "static", "--preset", "quick", "-o", str(tmp_path / "runs")],
        capture_output=True, text=True,
    )  # fmt: skip
    assert out.returncode == 1, out.stderr
    assert "0 done, 0 already finished, 5 failed" in out.stdout
    report = json.loads((tmp_path / "runs" / "sweep-depth.json").read_text())
    assert [r["status"] for r in report["runs"]] == ["failed"] * 5
    assert all("depth" in r["error"] for r in report["runs"])
