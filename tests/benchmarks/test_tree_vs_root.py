"""`benchmarks.speed.tree_vs_root`: the tree grid's table from run folders, checked against hand-made runs whose
scores, CPU seconds and auto decisions are known."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.speed.tree_vs_root import collect, grown, table


def _run(rf, root: Path, scene: str, tag: str, depth, mpsnr: float, psnr: float, cpu_s: float, tree: dict | None,
         ablate: tuple[str, ...] = ()) -> None:  # fmt: skip
    """A finished WorldTree run folder in the real format (``rf.write_run``, the ``runs_fixture`` fixture); its
    CPU seconds as counted are ``cpu_s`` for training plus the fixture's 0.5 s of loading (scoring is left out)."""
    stats = {"num_gaussians": 1000, **({"tree": tree} if tree is not None else {})}
    rf.write_run(root, scene, "worldtree", tag, {"mpsnr": mpsnr, "psnr": psnr},
                 config={"depth": depth, "ablate": list(ablate)}, train_cpu_s=cpu_s, method_stats=stats)  # fmt: skip


def _leaf_tree(reason: str) -> dict:
    return {"nodes": [1], "auto": {"1": {"split": False, "reason": reason, "applied": False}}}


def _grown_tree(n: int) -> dict:
    return {"nodes": list(range(1, n + 1)), "auto": {"1": {"split": True, "reason": "excess 0.03 >= 0.004"}}}


def _scene_a(rf, root: Path) -> None:
    """Scene a, the whole grid: the tree gains, auto grows three nodes."""
    _run(rf, root, "a", "quick-depth0", 0, 20.0, 25.0, 60.0, None)
    _run(rf, root, "a", "quick-depth1", 1, 20.4, 25.1, 90.0, _grown_tree(3))
    _run(rf, root, "a", "quick-depth2", 2, 20.9, 25.0, 150.0, _grown_tree(7))
    _run(rf, root, "a", "quick-depthauto", "auto", 20.5, 25.0, 120.0, _grown_tree(3))


@pytest.fixture
def runs(tmp_path: Path, runs_fixture) -> Path:
    # Scene a: the tree gains, auto grows three nodes; scene b: auto keeps the root for want of a measured depth.
    _scene_a(runs_fixture, tmp_path)
    # The root of scene b by ablation.
    _run(runs_fixture, tmp_path, "b", "quick-tpt", 2, 18.0, 24.0, 70.0, None, ablate=("tpt",))
    _run(runs_fixture, tmp_path, "b", "quick-depth1", 1, 18.16, 24.0, 100.0, _grown_tree(3))
    _run(runs_fixture, tmp_path, "b", "quick-depth2", 2, 17.9, 23.9, 140.0, _grown_tree(7))
    _run(runs_fixture, tmp_path, "b", "quick-depthauto", "auto", 18.0, 24.0, 56.0,
         _leaf_tree("depth unmeasured: mean depth confidence 0 on the moving pixels < 0.5"))  # fmt: skip
    return tmp_path


def test_grown_names_a_kept_root_by_its_reason_and_a_tree_by_its_nodes():
    assert grown({"method_stats": {"tree": _leaf_tree("near-static: 7.2 px < 16")}}) == "leaf: near-static"
    assert grown({"method_stats": {"tree": _grown_tree(5)}}) == "5 nodes"
    # A split whose children were all dropped leaves the root alone, not a leaf by auto's decision.
    dropped = {"nodes": [1], "auto": {"1": {"split": True, "reason": "excess 0.03 >= 0.004"}}}
    assert grown({"method_stats": {"tree": dropped}}) == "1 node"
    assert grown({"method_stats": {}}) == ""
    assert grown({}) == ""


def test_collect_reads_depths_including_the_ablated_root(runs: Path):
    data = collect([runs])
    assert sorted(data) == ["a", "b"]
    assert sorted(data["b"]) == ["0", "1", "2", "auto"]  # ablate tpt counts as depth 0
    assert data["b"]["auto"][0]["grown"] == "leaf: depth unmeasured"
    # CPU seconds leave out the scoring (eval), as `wtbench table` counts them: loading 0.5 + training 150.
    assert data["a"]["2"][0]["cpu_s"] == pytest.approx(150.5)


def test_table_gains_shares_and_means_by_hand(runs: Path):
    rows = {r.split("|")[1].strip(): [c.strip() for c in r.split("|")[1:-1]] for r in table(collect([runs]), 0.05)
            .splitlines()[2:]}  # fmt: skip
    a, b, mean = rows["a"], rows["b"], rows["**mean of 2**"]
    # a: d1 - root 0.4, d2 - root 0.9, auto - best fixed (d2) -0.4, auto CPU 120.5 / 150.5.
    assert a[5:8] == ["+0.40", "+0.90", "-0.40"]
    assert a[10] == "80%"
    assert a[12] == "3 nodes"
    # b: the best fixed depth is depth 1 (18.16); depth 2 loses 0.1 > the 0.05 noise and is flagged.
    assert b[5:8] == ["+0.16", "-0.10 (below)", "-0.16"]
    assert b[10] == "40%"  # 56.5 / 140.5
    assert b[12] == "leaf: depth unmeasured"
    assert mean[5:8] == ["+0.28", "+0.40", "-0.28"]
    assert mean[10] == "60%"


def test_a_depth_not_run_reads_dash_and_means_skip_it(tmp_path: Path, runs_fixture):
    # Scene a has the whole grid; scene c only its root and depth 2 (no depth 1, no auto).
    _scene_a(runs_fixture, tmp_path)
    _run(runs_fixture, tmp_path, "c", "quick-depth0", 0, 15.0, 21.0, 40.0, None)
    _run(runs_fixture, tmp_path, "c", "quick-depth2", 2, 15.3, 20.9, 90.0, _grown_tree(7))
    text = table(collect([tmp_path]), 0.05)
    assert "nan" not in text
    rows = {r.split("|")[1].strip(): [c.strip() for c in r.split("|")[1:-1]] for r in text.splitlines()[2:]}
    c, mean = rows["c"], rows["**mean of 2**"]
    assert c[1:5] == ["15.00", "-", "15.30", "-"]
    assert c[5:8] == ["-", "+0.30", "-"]  # auto - best fixed: no auto
    assert c[9] == "40 / - / 90 / -" and c[10] == "-"
    # Means over the scenes that have the figure: d1 and auto from a alone, d2 from both (0.9 and 0.3).
    assert mean[5:8] == ["+0.40", "+0.60", "-0.40"]
    assert mean[10] == "80%"
