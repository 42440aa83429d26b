"""The README's main job, `wtbench demo`, end to end on a small generated capture (smoke preset)."""

from __future__ import annotations

import json

import pandas as pd

from benchmarks.commands.demo import run_demo, tree_summary


def test_demo_generates_builds_runs_and_tabulates(tmp_path, capsys):
    csv = run_demo(tmp_path, ["worldtree"], steps=26, size="128x72", device="cpu", preset="smoke")
    scene = tmp_path / "scenes" / "SynthBalloon"
    assert (scene / "manifest.json").is_file() and len(list((scene / "images").iterdir())) == 26
    table = pd.read_csv(csv)
    assert list(table["method"]) == ["worldtree"]
    psnr = [c for c in table.columns if c.startswith("psnr:")]
    assert psnr and table[psnr[0]].between(5, 60).all()
    # WorldTree runs with --depth auto by default, and the demo prints the tree it chose.
    run = tmp_path / "runs" / "SynthBalloon" / "worldtree" / "smoke-depthauto"
    assert (run / "DONE").is_file()
    assert json.loads((run / "config.json").read_text())["config"]["auto_depth"] is True
    assert "--depth auto chose tree depth" in capsys.readouterr().out
    # A second call finds every stage done and only re-tabulates.
    assert run_demo(tmp_path, ["worldtree"], steps=26, size="128x72", device="cpu", preset="smoke") == csv
    # --gt-priors: exact priors written once into the scene and imported by a method that uses priors.
    run_demo(tmp_path, ["base"], steps=26, size="128x72", device="cpu", preset="smoke", gt_priors=True)
    assert (scene / "gt_priors" / "gt_priors.json").is_file()
    runs = [p for p in (tmp_path / "runs" / "SynthBalloon" / "base").iterdir() if not p.name.startswith(".")]
    assert len(runs) == 1 and "-set" in runs[0].name and (runs[0] / "DONE").is_file()
    assert "depth" not in runs[0].name  # Base grows no tree: --depth is not given to it
    record = pd.read_json(runs[0] / "config.json", typ="series")
    assert set(record["imported_priors"]) == {"masks", "tracks", "depth_maps"}


def _timing(tmp_path, tree):
    path = tmp_path / "timing.json"
    path.write_text(json.dumps({"method_stats": {"tree": tree}}))
    return path


def test_tree_summary_depth_nodes_leaves_and_reasons(tmp_path):
    # Nodes 1, 2, 3, 6, 7 of a binary tree: 6 and 7 are the children of 3, so the deepest is at depth 2 and the
    # leaves are 2, 6 and 7 (worked out by hand).
    intervals = {"1": [0, 39], "2": [0, 18], "3": [19, 39], "6": [19, 28], "7": [29, 39]}
    auto = {"1": {"split": True, "applied": True, "reason": "excess 0.07 >= 0.01"},
            "2": {"split": False, "applied": False, "reason": "near-static"},
            "3": {"split": True, "applied": True, "reason": "excess 0.07 >= 0.01"},
            "6": {"split": True, "applied": False, "reason": "excess 0.05 >= 0.01"},
            "7": {"split": False, "applied": False, "reason": "interval"}}  # fmt: skip
    line = tree_summary(_timing(tmp_path, {"nodes": [1, 2, 3, 6, 7], "intervals": intervals, "auto": auto}))
    assert line.startswith(
        "--depth auto chose tree depth 2, 5 nodes, leaves over frames 0-18, 19-28, 29-39 ("
    )
    # Node 6 met the criterion but was not split (applied False): it is reported as the leaf it is.
    assert "node 2: leaf (near-static)" in line and "node 6: leaf (excess 0.05" in line
    assert "node 3: split (" in line
    # A fixed depth records no decisions; the root alone is depth 0.
    assert tree_summary(_timing(tmp_path, {"nodes": [1, 2, 3], "intervals": intervals})) == (
        "tree depth 1, 3 nodes, leaves over frames 0-18, 19-39"
    )
    # A one-sided split: node 2 was not trained, so the root renders frames 0-18 (the record's "renders").
    one_sided = {
        "nodes": [1, 3],
        "intervals": {"1": [0, 39], "3": [19, 39]},
        "renders": {"1": [[0, 18]], "3": [[19, 39]]},
        "auto": {"1": {"split": True, "applied": True, "reason": "excess 0.03 >= 0.01",
                       "children": {"2": {"train": False, "reason": "not trained: near-static"},
                                    "3": {"train": True, "reason": "trained: excess 0.05 >= 0.01"}}},
                 "3": {"split": True, "applied": False, "reason": "excess 0.03 >= 0.01; not split: no child"}},
    }  # fmt: skip
    line = tree_summary(_timing(tmp_path, one_sided))
    assert line.startswith("--depth auto chose tree depth 1, 2 nodes, frames rendered by node 1: 0-18, node 3: 19-39 (")
    assert "node 2: not trained: near-static" in line and "node 3: leaf (excess 0.03" in line
    assert "node 3: trained" not in line  # only the children left out are named
    root = {"nodes": [1], "auto": {"1": {"split": False, "applied": False, "reason": "near-static"}}}
    assert (
        tree_summary(_timing(tmp_path, root))
        == "--depth auto chose tree depth 0, 1 node (node 1: leaf (near-static))"
    )


def test_kernel_build_runs_beside_the_demo_and_hands_back_its_result_or_error(monkeypatch):
    import threading

    import pytest

    from benchmarks.commands import demo
    from worldtree.render import cpu_kernel

    started, release = threading.Event(), threading.Event()

    def slow_prepare():
        started.set()
        release.wait(10)
        return "native", 1.5

    monkeypatch.setattr(cpu_kernel, "prepare", slow_prepare)
    build = demo._KernelBuild()
    # The build is under way while the caller goes on (the capture and scene build run meanwhile).
    assert started.wait(10) and build._thread.is_alive()
    release.set()
    assert build.result() == ("native", 1.5)

    def failing_prepare():
        raise RuntimeError("compiler exploded")

    monkeypatch.setattr(cpu_kernel, "prepare", failing_prepare)
    with pytest.raises(RuntimeError, match="compiler exploded"):
        demo._KernelBuild().result()
