"""The WorldTree method end to end through `wtbench run` on a 26-frame tiny analytic scene (smoke schedule):
the default tree, ``--ablate sac`` and ``--ablate tpt`` (against the Base method), and one node's training."""

from __future__ import annotations

import hashlib
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from benchmarks.cli import app
from methods.worldtree import NodeTrainConfig
from worldtree.gaussians import CORE_KEYS
from worldtree.imageio import read_image
from worldtree.infra.config_json import read_config, write_config
from worldtree.render import rasterize
from worldtree.tree.node import NodeState, load_payload
from worldtree.tree.parallel import NodeContext
from worldtree.tree.sac import AncestorPolicy

FRAMES = 26
# Binary rule P = (L + R) // 2 by hand: [0, 25] -> P 12; [0, 11] -> P 5; [12, 25] -> P 18.
INTERVALS = {1: [0, 25], 2: [0, 11], 3: [12, 25], 4: [0, 4], 5: [5, 11], 6: [12, 17], 7: [18, 25]}


def _wtbench(*args: str) -> str:
    res = CliRunner().invoke(app, ["run", *args])
    assert res.exit_code == 0, res.output
    return res.output


@pytest.fixture(scope="module")
def runs(tmp_path_factory, write_tiny_scene):
    tmp = tmp_path_factory.mktemp("wt_runs")
    scene = write_tiny_scene(tmp / "tiny26", frames=FRAMES)
    out = tmp / "runs"
    common = ["--scene", str(scene), "-o", str(out), "--preset", "smoke", "--device", "cpu"]
    said = _wtbench("--method", "worldtree", *common)
    _wtbench("--method", "worldtree", *common, "--ablate", "sac")
    _wtbench("--method", "worldtree", *common, "--ablate", "tpt")
    _wtbench("--method", "base", *common)
    _wtbench("--method", "worldtree", *common, "--depth", "auto")
    # The same without the depth-confidence test, which classical priors fail (nothing measures the moving
    # pixels' depth), so that the tree's growth itself is exercised.
    _wtbench("--method", "worldtree", *common, "--depth", "auto", "--set", "auto_split.min_depth_conf=0")
    folder = out / "tiny26"
    # The default tree grown on the `--ablate tpt` run's root, and Base on the default run's root.
    _wtbench("--method", "worldtree", *common, "--root-from", str(folder / "worldtree" / "smoke-notpt"),
             "--tag", "grown")  # fmt: skip
    _wtbench("--method", "base", *common, "--root-from", str(folder / "worldtree" / "smoke"), "--tag", "grown")
    (grown,) = (p for p in (folder / "worldtree").glob("smoke-depthauto-set*"))
    return {
        "scene": scene,
        "default": folder / "worldtree" / "smoke",
        "sac": folder / "worldtree" / "smoke-nosac",
        "tpt": folder / "worldtree" / "smoke-notpt",
        "base": folder / "base" / "smoke",
        "auto": folder / "worldtree" / "smoke-depthauto",
        "auto_grown": grown,
        "tree_on_tpt": folder / "worldtree" / "grown",
        "base_on_tree": folder / "base" / "grown",
        "default_output": said,
    }


def _stats(folder: Path) -> dict:
    return json.loads((folder / "timing.json").read_text())["method_stats"]


def test_configurations_land_in_their_own_finished_folders(runs):
    for key in ("default", "sac", "tpt", "base"):
        assert (runs[key] / "DONE").is_file(), key
        assert len(list((runs[key] / "renders").glob("*.png"))) == FRAMES
    cfg = json.loads((runs["sac"] / "config.json").read_text())
    assert cfg["options"] == {"ablate": ["sac"]} and cfg["config"]["ablate"] == ["sac"]
    assert "--ablate sac" in (runs["sac"] / "command.txt").read_text()


def test_default_tree_has_seven_nodes_with_binary_intervals_and_timings(runs):
    st = _stats(runs["default"])
    assert st["num_tree_nodes"] == 7 and st["tree_depth"] == 2
    assert {int(j): iv for j, iv in st["tree"]["intervals"].items()} == INTERVALS
    layers = st["tree"]["layers"]
    assert [lay["depth"] for lay in layers] == [1, 2]
    assert sorted(map(int, layers[0]["nodes_s"])) == [2, 3]
    assert sorted(map(int, layers[1]["nodes_s"])) == [4, 5, 6, 7]
    assert all(lay["wall_s"] > 0 and all(v > 0 for v in lay["nodes_s"].values()) for lay in layers)
    assert st["stages_s"]["tree"] > 0 and st["stages"][-2:] == ["tree", "test_pose"]
    for j in range(1, 8):
        node = NodeState.load(runs["default"] / "model" / "tree" / f"node{j}.pt")
        assert [node.interval.start, node.interval.end] == INTERVALS[j]
        assert [a.node for a in node.chain] == [k for k in (j // 2, j // 4) if k >= 1]
        assert node.scaffold.M == st["num_scaffold_nodes"]
    # Model size: the distinct Gaussians the leaves draw, counted by hashing the bytes of every set they render
    # (their static models, own dynamic Gaussians and ancestor copies): a set held by several leaves counts once.
    root = NodeState.load(runs["default"] / "model" / "tree" / "node1.pt")
    sizes, held = {}, 0
    for j in (4, 5, 6, 7):
        path = runs["default"] / "model" / "tree" / f"node{j}.pt"
        payload = load_payload(path)
        # The leaf renders the root's background unchanged (node_static_lr 0): its file refers to node1.pt's.
        assert payload["static"] is None and payload["static_shared_with"] == 1
        node = NodeState.load(path)
        for k, v in root.static.params.items():
            assert torch.equal(node.static.params[k], v)
        for g in [node.static, node.dynamic, *(a.dynamic for a in node.chain)]:
            digest = hashlib.sha256(b"".join(g.params[k].detach().numpy().tobytes() for k in CORE_KEYS))
            sizes[digest.hexdigest()] = len(g)
            held += len(g)
    distinct = sum(sizes.values())
    assert st["num_gaussians"] == distinct
    assert distinct < held - 3 * len(root.static)  # the background once, not four times


@pytest.mark.parametrize("t", [3, 20])
def test_test_render_is_the_deepest_covering_node_with_its_chain(runs, t):
    folder = runs["default"]
    node = {3: 4, 20: 7}[t]  # deepest nodes holding frames 3 and 20 (INTERVALS)
    st = NodeState.load(folder / "model" / "tree" / f"node{node}.pt")
    meta = json.loads((runs["scene"] / "cameras.json").read_text())
    cam = {c["id"]: c for c in meta["cameras"]}[meta["test_camera"]]
    pose = torch.load(folder / "model" / "scaffold_cameras.pt", weights_only=True)["test_poses"][t]
    with torch.no_grad():
        m, q, ls, o, c = st.gaussians_at(t)
        out = rasterize(m, q, ls, o, c, torch.tensor(cam["K"]).float(), pose.float(), meta["width"],
                        meta["height"])  # fmt: skip
    mine = (out.rgb.clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.int16)
    saved = read_image(folder / "renders" / f"v001_t{t:03d}.png").astype(np.int16)
    assert np.abs(mine - saved).max() <= 1
    # Without its ancestors the node renders something else (the chain is in the picture).
    with torch.no_grad():
        out0 = rasterize(*st.gaussians_at(t, chain_length=0), torch.tensor(cam["K"]).float(), pose.float(),
                         meta["width"], meta["height"])  # fmt: skip
    assert np.abs((out0.rgb.clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.int16) - saved).max() > 1


def test_ablate_sac_keeps_the_tree_without_ancestors(runs):
    st = _stats(runs["sac"])
    assert st["num_tree_nodes"] == 7 and st["ablate"] == ["sac"]
    for j in range(2, 8):
        node = NodeState.load(runs["sac"] / "model" / "tree" / f"node{j}.pt")
        assert node.chain == []
        assert node.interval.start == INTERVALS[j][0]


def test_ablate_tpt_is_the_base_method(runs):
    st = _stats(runs["tpt"])
    assert st["num_tree_nodes"] == 1 and st["tree"]["layers"] == []
    base = _stats(runs["base"])
    assert st["num_gaussians"] == base["num_gaussians"]
    for p in sorted((runs["base"] / "renders").glob("*.png")):
        a = read_image(p).astype(np.int16)
        b = read_image(runs["tpt"] / "renders" / p.name).astype(np.int16)
        assert np.abs(a - b).max() <= 1, p.name


def _same_renders(a: Path, b: Path) -> int:
    """Largest grey-level difference between the test renders of two run folders (which must match by name)."""
    names = sorted(p.name for p in (a / "renders").glob("*.png"))
    assert names == sorted(p.name for p in (b / "renders").glob("*.png")) and names
    return max(int(np.abs(read_image(a / "renders" / n).astype(np.int16) -
                          read_image(b / "renders" / n).astype(np.int16)).max()) for n in names)  # fmt: skip


@pytest.mark.parametrize(("grown", "alone", "lender"), [("tree_on_tpt", "default", "tpt"),
                                                        ("base_on_tree", "base", "default")])  # fmt: skip
def test_a_run_grown_on_another_runs_root_is_the_run_trained_alone(runs, grown, alone, lender):
    """`--root-from`: the lent checkpoints are the lender's files (hard links), the run trains none of those
    stages, and its renders are those of the same configuration trained from scratch."""
    g, a, src = runs[grown], runs[alone], runs[lender]
    assert (g / "DONE").is_file()
    for ck in sorted((src / "checkpoints" / "photometric").glob("ckpt_*.pt")):
        assert (g / "checkpoints" / "photometric" / ck.name).stat().st_ino == ck.stat().st_ino
    timing = json.loads((g / "timing.json").read_text())
    lent = timing["root_from"]
    assert Path(lent["run"]) == src.resolve() and "photometric" in lent["items"]
    ledger = json.loads((src / "checkpoints" / "stage_timing.json").read_text())
    assert lent["stages_s"]["photometric"] == ledger["stages_s"]["photometric"] > 0
    assert timing["train"]["steps_this_session"] == 0  # the root's fit resumed at its end
    assert _same_renders(g, a) == 0
    assert json.loads((g / "metrics.json").read_text())["mean"] == json.loads((a / "metrics.json").read_text())["mean"]


def _flat_tensors(obj, prefix=""):
    """Every tensor of a nested checkpoint dict, by dotted key."""
    if isinstance(obj, torch.Tensor):
        return {prefix: obj}
    if isinstance(obj, dict):
        out = {}
        for k, v in obj.items():
            out.update(_flat_tensors(v, f"{prefix}.{k}"))
        return out
    return {}


def test_every_tree_configuration_trains_the_same_root(runs):
    """What `--root-from` relies on (methods.worldtree.TREE_FIELDS): the tree's settings and the tpt/sac
    ablations leave the root's fit as it is, to the last bit; so does Base."""
    def root(key):
        (ck,) = sorted((runs[key] / "checkpoints" / "photometric").glob("ckpt_*.pt"))[-1:]
        return _flat_tensors(torch.load(ck, map_location="cpu", weights_only=False)["task"]), ck.name

    ref, name = root("tpt")
    assert len(ref) > 10
    for key in ("default", "sac", "auto", "auto_grown", "base"):
        got, got_name = root(key)
        assert got_name == name and got.keys() == ref.keys(), key
        assert all(torch.equal(got[k], ref[k]) for k in ref), key


def test_the_table_counts_a_lent_roots_time(runs):
    from benchmarks.reporting.results import cost_metrics

    timing = json.loads((runs["tree_on_tpt"] / "timing.json").read_text())
    own = dict(timing, root_from=None)
    lent = timing["root_from"]
    got, alone = cost_metrics(timing, None), cost_metrics(own, None)
    assert got["wall_time_s"] == pytest.approx(alone["wall_time_s"] + sum(lent["stages_s"].values()))
    assert got["cpu_time_s"] == pytest.approx(alone["cpu_time_s"] + sum(lent["stages_cpu_s"].values()))


def test_node_training_optimises_the_nearest_ancestors_only(runs, tmp_path):
    """Node 6 (depth 2) retrained with one optimised ancestor: its parent copy (node 3) moves, the root copy
    stays bit-identical, and its own Gaussians move."""
    from methods.worldtree import train_node

    src = runs["default"] / "checkpoints" / "tree"
    tree = tmp_path / "tree"
    (tree / "layer2" / "node6").mkdir(parents=True)
    shutil.copy(src / "context.pt", tree / "context.pt")
    import dataclasses

    from worldtree.tree.sac import AncestorPolicy

    cfg = read_config(src / "node_config.json", NodeTrainConfig)
    cfg = dataclasses.replace(cfg, policy=AncestorPolicy(optimised_nearest=1), checkpoint_every=1000)
    write_config(tree / "node_config.json", cfg)
    payload = load_payload(src / "layer2" / "node6" / "input.pt")
    before = NodeState.from_payload(payload["state"])
    torch.manual_seed(0)
    out = train_node(payload, NodeContext(6, 6, "cpu", 1, str(tree / "layer2" / "node6")))
    after = NodeState.from_payload(out["state"])
    assert [a.node for a in after.chain] == [3, 1]
    assert not torch.equal(after.chain[0].dynamic.params["means"], before.chain[0].dynamic.params["means"])
    assert not torch.equal(after.chain[0].scaffold.pos, before.chain[0].scaffold.pos)
    for k, v in before.chain[1].dynamic.params.items():
        assert torch.equal(after.chain[1].dynamic.params[k], v), k
    assert torch.equal(after.chain[1].scaffold.pos, before.chain[1].scaffold.pos)
    assert not torch.equal(after.dynamic.params["means"], before.dynamic.params["means"])
    # The gradient profile covers the node's frames.
    assert out["profile"].shape == (INTERVALS[6][1] - INTERVALS[6][0] + 1,)
    assert out["stats"]["steps"] == cfg.steps_at(2)


def test_interrupted_node_resumes_to_the_same_result(runs, tmp_path):
    """A node stopped after its step-8 checkpoint (the step-10 one deleted) ends as the uninterrupted run:
    own Gaussians, ancestor copies and gradient profile identical."""
    import dataclasses

    from methods.worldtree import train_node

    src = runs["default"] / "checkpoints" / "tree"
    tree = tmp_path / "tree"
    folder = tree / "layer2" / "node6"
    folder.mkdir(parents=True)
    shutil.copy(src / "context.pt", tree / "context.pt")
    cfg = read_config(src / "node_config.json", NodeTrainConfig)
    cfg = dataclasses.replace(cfg, checkpoint_every=4, layer_steps=(10, 10))
    write_config(tree / "node_config.json", cfg)
    ctx = NodeContext(6, 6, "cpu", 1, str(folder))

    def run():
        torch.manual_seed(6)
        return train_node(load_payload(src / "layer2" / "node6" / "input.pt"), ctx)

    full = run()
    (folder / "checkpoints" / "ckpt_0000010.pt").unlink()
    resumed = run()
    a, b = NodeState.from_payload(full["state"]), NodeState.from_payload(resumed["state"])
    assert resumed["stats"]["steps"] == 10
    assert torch.equal(a.dynamic.params["means"], b.dynamic.params["means"])
    assert torch.equal(a.static.params["means"], b.static.params["means"])
    for x, y in zip(a.chain, b.chain, strict=True):
        assert torch.equal(x.dynamic.params["means"], y.dynamic.params["means"])
        assert torch.equal(x.scaffold.pos, y.scaffold.pos)
    assert torch.equal(full["profile"], resumed["profile"])


def test_frozen_ancestor_memo_trains_the_same_node(runs, tmp_path, monkeypatch):
    """With its ancestors frozen a node deforms each ancestor once per frame and reuses it: the trained node is
    bit-identical to one that deforms them at every step (the memo switched off by a zero memory cap)."""
    import dataclasses

    import methods.worldtree as mw

    src = runs["default"] / "checkpoints" / "tree"
    cfg = read_config(src / "node_config.json", NodeTrainConfig)
    # The depth anchor renders the parent once per frame before training, outside the memo: off here.
    cfg = dataclasses.replace(cfg, policy=AncestorPolicy(optimised_nearest=0), checkpoint_every=1000,
                              layer_steps=(12, 12), lambda_parent_depth=0.0)  # fmt: skip

    def run(name: str):
        tree = tmp_path / name
        (tree / "layer2" / "node6").mkdir(parents=True)
        shutil.copy(src / "context.pt", tree / "context.pt")
        write_config(tree / "node_config.json", cfg)
        torch.manual_seed(6)
        ctx = NodeContext(6, 6, "cpu", 1, str(tree / "layer2" / "node6"))
        return NodeState.from_payload(mw.train_node(load_payload(src / "layer2" / "node6" / "input.pt"),
                                                    ctx)["state"])  # fmt: skip

    calls = []
    real = mw.chain_gaussians_at
    monkeypatch.setattr(mw, "chain_gaussians_at", lambda *a, **k: calls.append(1) or real(*a, **k))
    memo = run("memo")
    memo_calls = len(calls)
    monkeypatch.setattr(mw, "_ANCESTOR_MEMO_BYTES", 0)
    calls.clear()
    plain = run("plain")
    # One deformation per frame of node 6 with the memo; one per step (and more) without it.
    assert memo_calls <= INTERVALS[6][1] - INTERVALS[6][0] + 1 < len(calls)
    for k, v in plain.dynamic.params.items():
        assert torch.equal(memo.dynamic.params[k], v), k
    assert torch.equal(memo.scaffold.pos, plain.scaffold.pos)


def test_depth_auto_keeps_the_root_where_no_prior_measures_the_moving_depth(runs):
    # Classical priors fill the moving pixels' depth from their surroundings (confidence 0 there).
    st = _stats(runs["auto"])
    assert st["tree"]["nodes"] == [1]
    d = st["tree"]["auto"]["1"]
    assert not d["split"] and d["dynamic_depth_conf"] == 0.0 and d["reason"].startswith("depth unmeasured")


def test_a_fixed_depth_tree_says_when_the_moving_depth_is_unmeasured(runs):
    # The same classical priors: the default (depth 2) tree grows, records the prior's confidence on the moving
    # pixels (0, as auto measured it above) and says once why its children may not gain.
    from methods.worldtree import UNMEASURED_NOTE

    assert _stats(runs["default"])["tree"]["moving_depth_conf"] == 0.0
    assert runs["default_output"].count(UNMEASURED_NOTE.format(conf=0.0)) == 1
    assert _stats(runs["auto"])["tree"]["moving_depth_conf"] == 0.0  # recorded where auto kept the root too


def test_depth_auto_grows_the_tree_its_decisions_say(runs):
    st = _stats(runs["auto_grown"])
    cfg = json.loads((runs["auto_grown"] / "config.json").read_text())
    assert cfg["config"]["depth"] == "auto" and cfg["config"]["auto_depth"] is True
    assert cfg["config"]["auto_split"]["min_depth_conf"] == 0.0
    auto = {int(j): d for j, d in st["tree"]["auto"].items()}
    nodes = set(map(int, st["tree"]["nodes"]))
    assert 1 in auto and nodes == set(auto)  # every node has a recorded decision
    for j, d in auto.items():
        assert isinstance(d["reason"], str) and d["reason"]
        # Children exactly where the decision applied (a one-sided split trains one of them).
        assert d["applied"] == (2 * j in nodes or 2 * j + 1 in nodes), j
        moves = d["motion_px"] >= d["motion_min_px"]  # the scaffold's motion was measured for every node
        assert d["dynamic_depth_conf"] is not None  # measured, not tested (min_depth_conf 0)
        assert d["split"] == (
            d["excess"] >= 0.01 and d["dynamic_fraction"] >= 0.002 and d["frames"] >= 12 and moves
        )
        # Each would-be child was tested on this node's fit over its frames; exactly those that passed exist.
        for c, cd in (d.get("children") or {}).items():
            assert (int(c) in nodes) == cd["train"], (j, c)
            moves = cd["motion_px"] >= cd["motion_min_px"]
            assert cd["train"] == (cd["excess"] >= 0.01 and cd["dynamic_fraction"] >= 0.002 and moves)
        if d["applied"]:
            assert set(d["children"]) == {str(2 * j), str(2 * j + 1)}
    # Every frame is rendered by exactly one node (the parent of a one-sided split renders the other half).
    renders = st["tree"].get("renders") or {"1": [[0, FRAMES - 1]]}
    frames = sorted(t for runs_ in renders.values() for a, b in runs_ for t in range(a, b + 1))
    assert frames == list(range(FRAMES))
    # Steps follow the frames: the smoke root's 20 steps over 26 frames, capped by layer_steps (10).
    for ns in st["tree"].get("node_stats", {}).values():
        n = ns["frames"][1] - ns["frames"][0] + 1
        assert ns["steps_max"] == min(10, math.ceil(20 * n / FRAMES)) and ns["steps"] <= ns[
            "steps_max"
        ] + ns.get("steps_refit", 0)
    # Budget and early stop come with --depth auto for the children; the root (the Base stages) trains as for a
    # fixed depth: every step, no budget, no pruning stage.
    ad = st["adaptive"]
    assert not ad["budget_on"] and not ad["early_stop_on"] and ad["steps_taken"] == ad["steps_max"]
    assert "prune" not in ad and "budget" not in ad
    assert "prune" not in st["stages_s"]
    for ns in st["tree"].get("node_stats", {}).values():
        assert "inherit_prune" in ns["adaptive"] and "early_stop" in ns["adaptive"]
        # A child prunes dynamic Gaussians only: the background its test views draw stays the root's, whole.
        assert ns["num_static"] == st["num_static"], ns["node"]
        for rec in (ns["adaptive"]["inherit_prune"], ns["adaptive"]["prune"]):
            assert rec["static_after"] == rec["static_before"]


def test_node_with_budget_auto_and_early_stop_records_its_choices(runs, tmp_path):
    """Node 6 retrained with contribution pruning, the auto criterion and a plateau rule that must fire:
    the kept Gaussians all contribute at least the threshold over the node's frames (checked by a fresh
    contribution pass), the decision is the criterion's on the node's residual, fewer steps than the max."""
    import dataclasses

    from methods.worldtree import train_node
    from worldtree.budget import BudgetConfig, render_contributions
    from worldtree.plateau import PlateauRule
    from worldtree.tree.adaptive import AutoSplitConfig

    src = runs["default"] / "checkpoints" / "tree"
    tree = tmp_path / "tree"
    folder = tree / "layer2" / "node6"
    folder.mkdir(parents=True)
    shutil.copy(src / "context.pt", tree / "context.pt")
    cfg = read_config(src / "node_config.json", NodeTrainConfig)
    rule = PlateauRule(enabled=True, rel_tol=0.5, patience=1, min_window=2)  # fires after two windows
    # No total cap and no deferral of the inherited Gaussians' pruning (both tested in test_budget_prune.py):
    # every negligible Gaussian goes, so every kept one can be checked against the threshold.
    budget = BudgetConfig(enabled=True, prune_total_frac=1e9, prune_min_epochs=0.0)
    cfg = dataclasses.replace(cfg, layer_steps=(40, 40), auto=AutoSplitConfig(), budget=budget,
                              early_stop=rule)  # fmt: skip
    write_config(tree / "node_config.json", cfg)
    torch.manual_seed(6)
    out = train_node(
        load_payload(src / "layer2" / "node6" / "input.pt"), NodeContext(6, 6, "cpu", 1, str(folder))
    )
    stats = out["stats"]
    ad = stats["adaptive"]
    assert stats["steps"] < 40 and ad["early_stop"]["stopped_at"] == stats["steps"]
    # The background is never pruned in a child (test views see parts of it no child frame does).
    assert ad["prune"]["static_after"] == stats["num_static"] == ad["prune"]["static_before"]
    assert ad["inherit_prune"]["static_after"] == ad["inherit_prune"]["static_before"]
    assert ad["prune"]["dynamic_due"] is True
    assert ad["inherit_prune"]["dynamic_after"] <= ad["inherit_prune"]["dynamic_before"]
    assert set(stats["auto_split"]) >= {"split", "reason", "excess", "dynamic_fraction"}
    # Every dynamic Gaussian the node kept contributes at least the threshold over its own frames; some of the
    # background it kept whole does not.
    state = NodeState.from_payload(out["state"])
    ctx = torch.load(tree / "context.pt", weights_only=True)
    iv = state.interval
    H, W = ctx["images"].shape[1:3]
    views = [(iv.start + k, ctx["Ks"][iv.start + k], state.w2cs[k]) for k in range(iv.length)]
    contrib = render_contributions(lambda t: state.gaussians_at(t), views, W, H)
    n_s, n_own = len(state.static), len(state.static) + len(state.dynamic)
    assert bool((contrib[n_s:n_own] >= 1.0 - 1e-3).all())
    assert bool((contrib[:n_s] < 1.0).any())


def test_node_densify_grows_the_childs_own_gaussians_only(runs, tmp_path):
    """`node_densify`: node 6 retrained with a density control that grows every Gaussian with any gradient
    ends with more dynamic Gaussians of its own than without; its background and its ancestors keep their
    counts. The schedule is the root's, scaled to the node's steps."""
    import dataclasses

    from methods.worldtree import scaled_schedule, train_node
    from worldtree.strategy import DensifyStrategy

    grow = DensifyStrategy(grow_grad2d=1e-12, grow_scale3d=1e9, refine_start=10, refine_stop=30, refine_every=10,
                           reset_every=3000)  # fmt: skip
    half = scaled_schedule(grow, 40, 20)
    assert (half.refine_start, half.refine_stop, half.refine_every, half.reset_every) == (5, 15, 5, 0)
    src = runs["default"] / "checkpoints" / "tree"
    base = read_config(src / "node_config.json", NodeTrainConfig)
    counts = {}
    for on in (False, True):
        tree = tmp_path / f"tree{int(on)}"
        folder = tree / "layer2" / "node6"
        folder.mkdir(parents=True)
        shutil.copy(src / "context.pt", tree / "context.pt")
        pcfg = dataclasses.replace(base.photometric, steps=40, dynamic_strategy=grow)
        write_config(tree / "node_config.json", dataclasses.replace(base, photometric=pcfg, layer_steps=(40, 40),
                                                                   node_densify=on))  # fmt: skip
        torch.manual_seed(6)
        out = train_node(load_payload(src / "layer2" / "node6" / "input.pt"), NodeContext(6, 6, "cpu", 1, str(folder)))
        st = out["stats"]
        counts[on] = (st["num_dynamic"], st["num_static"], st["num_ancestor_gaussians"])
    assert counts[True][0] > counts[False][0] > 0
    assert counts[True][1:] == counts[False][1:]


def test_node_training_with_neighbour_coupling_moves_its_scaffold_differently(runs, tmp_path):
    """Node 6 (depth 2, with ancestors drawn behind the carried picture) trained with the neighbour coupling
    every step: it runs, stays finite, and its scaffold ends elsewhere than without the term."""
    import dataclasses

    from methods.worldtree import train_node

    src = runs["default"] / "checkpoints" / "tree"

    def train(weight: float):
        tree = tmp_path / f"tree{weight}"
        (tree / "layer2" / "node6").mkdir(parents=True)
        shutil.copy(src / "context.pt", tree / "context.pt")
        cfg = read_config(src / "node_config.json", NodeTrainConfig)
        phot = dataclasses.replace(cfg.photometric, lambda_couple=weight, couple_every=1)
        write_config(
            tree / "node_config.json", dataclasses.replace(cfg, photometric=phot, checkpoint_every=1000)
        )
        torch.manual_seed(0)
        out = train_node(load_payload(src / "layer2" / "node6" / "input.pt"),
                         NodeContext(6, 6, "cpu", 1, str(tree / "layer2" / "node6")))  # fmt: skip
        return NodeState.from_payload(out["state"])

    off, on = train(0.0), train(1.0)
    assert torch.isfinite(on.scaffold.pos).all()
    assert not torch.equal(on.scaffold.pos, off.scaffold.pos)


def test_node_with_holdout_never_trains_on_its_held_out_frames_and_judges_them(runs, tmp_path):
    """Node 3 ([12, 25], 14 frames) retrained with held-out validation and no refit: the held-out frames get
    no step (the node's per-frame visit count, checkpointed with its gradient profile, is 0 there and not
    elsewhere), and
    the verdict's errors are the halfway predictions of the child and of its parent as it was handed over,
    recomputed here from the saved states."""
    import dataclasses

    from methods.worldtree import _parent_view, train_node
    from worldtree.dynamic import halfway
    from worldtree.tree.build import read_node_input
    from worldtree.tree.validate import HoldoutConfig, holdout_frames

    src = runs["default"] / "checkpoints" / "tree"
    tree = tmp_path / "tree"
    folder = tree / "layer1" / "node3"
    folder.mkdir(parents=True)
    shutil.copy(src / "context.pt", tree / "context.pt")
    cfg = read_config(src / "node_config.json", NodeTrainConfig)
    hcfg = HoldoutConfig(enabled=True, frac=0.2, refit=False)
    write_config(tree / "node_config.json", dataclasses.replace(cfg, layer_steps=(60, 60), holdout=hcfg))
    payload = load_payload(src / "layer1" / "node3" / "input.pt")
    torch.manual_seed(3)
    out = train_node(payload, NodeContext(3, 3, "cpu", 1, str(folder)))
    hold = holdout_frames(14, 0.2)
    assert len(hold) == 3  # round(14 * 0.2) = 3 interior frames
    v = out["stats"]["holdout"]
    assert v["frames"] == hold and out["stats"]["steps_refit"] == 0
    from worldtree.checkpoint import latest_checkpoint, load_checkpoint

    visits = load_checkpoint(latest_checkpoint(folder / "checkpoints"))["task"]["profile"]["count"]
    others = [i for i in range(14) if i not in hold]
    assert bool((visits[hold] == 0).all()) and bool((visits[others] > 0).all())
    # Recompute both models' held-out errors from the saved states.
    ctx = torch.load(tree / "context.pt", weights_only=True)
    start, _ = read_node_input(payload)
    child = NodeState.from_payload(out["state"])
    parent_at = _parent_view(start)
    cache = child.dynamic.attach(child.scaffold)
    H, W = ctx["images"].shape[1:3]
    l1c, l1p = [], []
    for i in hold:
        g = 12 + i
        c = halfway(child.gaussians_at(g - 1, None, cache), child.gaussians_at(g + 1, None, cache),
                    child.gaussians_at(g, None, cache)[3])  # fmt: skip
        p = halfway(parent_at(g - 1), parent_at(g + 1), parent_at(g)[3])
        with torch.no_grad():
            rc = rasterize(*c, ctx["Ks"][g], child.w2cs[i], W, H).rgb.clamp(0, 1)
            rp = rasterize(*p, ctx["Ks"][g], child.w2cs[i], W, H).rgb.clamp(0, 1)
        target = ctx["images"][g].float() / 255.0  # the context holds the frames as uint8
        l1c.append(float((rc - target).abs().mean()))
        l1p.append(float((rp - target).abs().mean()))
    assert v["child_l1"] == pytest.approx(np.mean(l1c), rel=1e-4)
    assert v["parent_l1"] == pytest.approx(np.mean(l1p), rel=1e-4)
    assert v["keep"] == (np.mean(l1c) < np.mean(l1p))


def test_parent_depth_anchor_holds_a_child_where_the_prior_measures_no_depth(runs, tmp_path):
    """Node 6 retrained with and without the depth anchor. Where the depth prior's confidence is 0 the anchored
    child draws its frames' depth nearer its parent's than the free child does; where it is 1 everywhere the
    anchor has nothing to hold and the child trains bit for bit as without it."""
    import dataclasses

    from methods.worldtree import _parent_view, train_node
    from worldtree.tree.build import read_node_input

    src = runs["default"] / "checkpoints" / "tree"
    payload_path = src / "layer2" / "node6" / "input.pt"
    base_cfg = dataclasses.replace(read_config(src / "node_config.json", NodeTrainConfig), checkpoint_every=1000,
                                   layer_steps=(60, 60))  # fmt: skip
    context = torch.load(src / "context.pt", weights_only=True)

    def train(name: str, weight: float, conf: float) -> NodeState:
        tree = tmp_path / name
        (tree / "layer2" / "node6").mkdir(parents=True)
        torch.save({**context, "depth_conf": torch.full_like(context["depth_conf"], conf)}, tree / "context.pt")
        write_config(tree / "node_config.json", dataclasses.replace(base_cfg, lambda_parent_depth=weight))
        torch.manual_seed(6)
        out = train_node(load_payload(payload_path), NodeContext(6, 6, "cpu", 1, str(tree / "layer2" / "node6")))
        return NodeState.from_payload(out["state"])

    free, held, measured = train("free", 0.0, 0.0), train("held", 5.0, 0.0), train("measured", 5.0, 1.0)
    for k, v in free.dynamic.params.items():
        assert torch.equal(measured.dynamic.params[k], v), k
    assert torch.equal(measured.scaffold.pos, free.scaffold.pos)

    start, _ = read_node_input(load_payload(payload_path))
    parent_at = _parent_view(start)
    H, W = context["images"].shape[1:3]
    a, b = INTERVALS[6]

    def departure(node: NodeState) -> float:
        """Mean |depth - parent's depth| / parent's depth over the node's frames, where both are opaque."""
        errs = []
        with torch.no_grad():
            for i, g in enumerate(range(a, b + 1)):
                K, w2c = context["Ks"][g], node.w2cs[i]
                own, par = rasterize(*node.gaussians_at(g), K, w2c, W, H), rasterize(*parent_at(g), K, w2c, W, H)
                ok = (own.alpha > 0.5) & (par.alpha > 0.5)
                d, p = own.depth[ok] / own.alpha[ok], par.depth[ok] / par.alpha[ok]
                errs.append(((d - p).abs() / p).mean())
        return float(torch.stack(errs).mean())

    free_dep, held_dep = departure(free), departure(held)
    assert free_dep > 0.0 and held_dep < 0.8 * free_dep, (free_dep, held_dep)
