"""The README's main job, `wtbench demo`, end to end on a small generated capture (smoke preset)."""

from __future__ import annotations

import pandas as pd

from benchmarks.commands.demo import run_demo


def test_demo_generates_builds_runs_and_tabulates(tmp_path):
    csv = run_demo(tmp_path, ["worldtree"], steps=26, size="128x72", device="cpu", preset="smoke")
    scene = tmp_path / "scenes" / "SynthBalloon"
    assert (scene / "manifest.json").is_file() and len(list((scene / "images").iterdir())) == 26
    table = pd.read_csv(csv)
    assert list(table["method"]) == ["worldtree"]
    psnr = [c for c in table.columns if c.startswith("psnr:")]
    assert psnr and table[psnr[0]].between(5, 60).all()
    assert (tmp_path / "runs" / "SynthBalloon" / "worldtree" / "smoke" / "DONE").is_file()
    # A second call finds every stage done and only re-tabulates.
    assert run_demo(tmp_path, ["worldtree"], steps=26, size="128x72", device="cpu", preset="smoke") == csv
