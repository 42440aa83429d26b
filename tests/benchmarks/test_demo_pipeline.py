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
    # --gt-priors: exact priors written once into the scene and imported by a method that uses priors.
    run_demo(tmp_path, ["base"], steps=26, size="128x72", device="cpu", preset="smoke", gt_priors=True)
    assert (scene / "gt_priors" / "gt_priors.json").is_file()
    runs = [p for p in (tmp_path / "runs" / "SynthBalloon" / "base").iterdir() if not p.name.startswith(".")]
    assert len(runs) == 1 and "-set" in runs[0].name and (runs[0] / "DONE").is_file()
    record = pd.read_json(runs[0] / "config.json", typ="series")
    assert set(record["imported_priors"]) == {"masks", "tracks", "depth_maps"}
