"""WorldTree config (ablations, validation, per-layer steps) and the `wtbench run` method options: tags,
refusal on methods without the option, one-line errors. No training."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import pytest
from typer.testing import CliRunner

from benchmarks.cli import app
from benchmarks.runner.runs import run_tag
from methods.registry import get_method
from methods.worldtree import WorldTreeConfig
from worldtree.infra.errors import UserError


def test_ablations_are_normalised_and_have_one_spelling():
    cfg = WorldTreeConfig(ablate=("sac", "ba"))
    assert cfg.ablate == ("ba", "sac")
    sw_off = WorldTreeConfig(sw=dataclasses.replace(WorldTreeConfig().sw, enabled=False))
    assert sw_off.ablate == ("sw",) and sw_off == WorldTreeConfig(ablate=("sw",))
    assert dataclasses.replace(cfg, ablate=("tpt",)).tree_depth == 0
    assert WorldTreeConfig(depth=3).tree_depth == 3


def test_per_layer_steps_and_tree_settings():
    cfg = WorldTreeConfig(layer_steps=(200, 100), depth=4, split="gradient", ancestors_optimised=1)
    assert [cfg.steps_at(d) for d in (1, 2, 3, 4)] == [200, 100, 100, 100]
    tc = cfg.tree_config()
    assert tc.depth == 4 and tc.split == "gradient" and tc.inherit.policy.optimised_nearest == 1
    paper = get_method("worldtree").config("paper")
    assert paper.steps == 4000 and paper.layer_steps == (2000, 2000) and paper.depth == 2
    assert paper.inherit_caps == (5000, 2000) and paper.dynamic_max_init == 30_000


@pytest.mark.parametrize(
    "kw",
    [{"ablate": ("foo",)}, {"depth": -1}, {"chain_length": -2}, {"split": "median"}, {"layer_steps": ()}],
)
def test_bad_values_are_user_errors(kw):
    with pytest.raises(UserError):
        WorldTreeConfig(**kw)


def test_run_tags_differ_per_configuration():
    tree = get_method("worldtree").options

    def tag(overrides, opts=None):
        return run_tag("quick", overrides, opts, None, tree)

    tags = {
        tag({}, opts)
        for opts in (
            {},
            {"ablate": ["sac"]},
            {"ablate": ["tpt"]},
            {"ablate": ["ba", "sw"]},
            {"depth": 3},
            {"chain_length": 1},
            {"split": "flow"},
            {"sequential": True},
        )
    }
    assert len(tags) == 8
    assert tag({"steps": 5}, {"ablate": ["sw", "ba"], "depth": 1}) == "quick-steps5-noba-nosw-depth1"
    assert tag({}, {"ablate": ["sw", "ba"]}) == tag({}, {"ablate": ["ba", "sw"]})
    assert tag({}, {"sequential": True, "split": "flow", "depth": "auto"}) == "quick-depthauto-splitflow-seq"
    assert tag({"steps": 5}) == "quick-steps5"


@pytest.mark.parametrize(
    "method,extra,needle",
    [
        ("base", ["--depth", "3"], "--depth: method 'base' has no such option"),
        ("worldtree", ["--ablate", "foo"], "--ablate foo"),
        ("worldtree", ["--split", "median"], "--split median"),
    ],
)
def test_cli_refuses_bad_options_before_running(tmp_path, method, extra, needle, write_tiny_scene):
    scene = write_tiny_scene(tmp_path / "tiny")
    args = [
        "run",
        "--method",
        method,
        "--scene",
        str(scene),
        "-o",
        str(tmp_path / "runs"),
        "--preset",
        "smoke",
    ]
    res = CliRunner().invoke(app, args + extra)
    assert isinstance(res.exception, UserError) and needle in str(res.exception)
    assert not any((tmp_path / "runs").rglob("config.json"))


def test_cli_option_error_is_one_line(tmp_path, write_tiny_scene):
    scene = write_tiny_scene(tmp_path / "tiny")
    out = subprocess.run(
        [sys.executable, "-m", "benchmarks.cli", "run", "--method", "worldtree", "--scene", str(scene),
         "--preset", "smoke", "--chain-length", "-1", "-o", str(tmp_path / "runs")],
        capture_output=True,
        text=True,
    )  # fmt: skip
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: --chain-length -1"), out.stderr


def test_node_steps_follow_the_roots_steps_per_frame_under_depth_auto():
    from methods.worldtree import NodeTrainConfig
    from worldtree.stages.photometric import PhotometricConfig
    from worldtree.tree.sac import AncestorPolicy

    ncfg = NodeTrainConfig(PhotometricConfig(), (300, 300), AncestorPolicy(), False, 1.0, 100, 50,
                           steps_per_frame=600 / 40)  # fmt: skip
    # The quick preset's root: 600 steps over 40 frames = 15 per frame; worked out by hand.
    assert [ncfg.node_steps(1, 20), ncfg.node_steps(1, 21), ncfg.node_steps(2, 10), ncfg.node_steps(2, 11)] == [
        300, 300, 150, 165,
    ]  # fmt: skip
    assert ncfg.node_steps(2, 7) == 105 and ncfg.node_steps(2, 0) == 1
    free = dataclasses.replace(ncfg, steps_per_frame=None)
    assert free.node_steps(2, 10) == 300 and free.node_steps(1, 3) == 300
    # On with --depth auto, off for fixed depths, overridable either way.
    quick = get_method("worldtree").config("quick")
    assert not quick.node_steps_per_frame_on()
    assert dataclasses.replace(quick, depth="auto").node_steps_per_frame_on()
    assert not dataclasses.replace(quick, depth="auto", node_steps_per_frame=False).node_steps_per_frame_on()
    assert dataclasses.replace(quick, node_steps_per_frame=True).node_steps_per_frame_on()
    assert "node_steps_per_frame" in dataclasses.replace(quick, depth=0).ignored_settings()


def test_depth_auto_budgets_the_children_and_not_the_root():
    """``--depth auto`` turns the Gaussian budget and early stop on for the children only; the root trains as for
    a fixed depth unless ``budget.enabled`` / ``early_stop.enabled`` say otherwise; Base follows its settings."""
    from methods.base import BaseConfig
    from worldtree.budget import BudgetConfig
    from worldtree.plateau import PlateauRule

    auto = WorldTreeConfig(depth="auto")
    assert auto.budget_on() and auto.early_stop_on()
    assert not auto.root_budget_on() and not auto.root_early_stop_on()
    on = dataclasses.replace(auto, budget=BudgetConfig(enabled=True), early_stop=PlateauRule(enabled=True))
    assert on.root_budget_on() and on.root_early_stop_on()
    fixed = WorldTreeConfig(depth=2)
    assert not fixed.budget_on() and not fixed.root_budget_on()
    base = BaseConfig(budget=BudgetConfig(enabled=True), early_stop=PlateauRule(enabled=True))
    assert base.root_budget_on() and base.root_early_stop_on()
    assert not BaseConfig().root_budget_on()
