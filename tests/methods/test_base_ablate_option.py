"""`--ablate ba|sw` reaches the Base config through `wtbench run`'s option path; tree options are refused."""

from __future__ import annotations

import dataclasses

import pytest

from benchmarks.runner.runs import method_option_fields, run_tag
from methods.base import BaseConfig
from methods.registry import get_method
from methods.worldtree import WorldTreeConfig
from worldtree.infra.errors import UserError


def _apply(cfg, method, options):
    return dataclasses.replace(cfg, **method_option_fields(get_method(method), options))


def test_base_accepts_ablate_ba_and_sw():
    cfg = _apply(BaseConfig(), "base", {"ablate": ["sw", "ba"]})
    assert cfg.ablate == ("ba", "sw")
    assert _apply(BaseConfig(), "base", {"ablate": ["sw"]}).ablate == ("sw",)
    assert run_tag("quick", {}, {"ablate": ["ba"]}) != run_tag("quick", {}, {})


def _stage_names(method_cls, cfg):
    m = method_cls.__new__(method_cls)
    m.cfg = cfg
    return [(st.name, st.run.__name__) for st in m.stages()]


def test_ablation_replaces_the_named_stage_only():
    from methods.base import BaseMethod, stage_ba_ablated, stage_sw_ablated

    full = _stage_names(BaseMethod, BaseConfig())
    assert [n for n, _ in full] == ["priors", "ba", "sw", "motion", "scaffold", "photometric", "test_pose"]
    no_ba = _stage_names(BaseMethod, BaseConfig(ablate=("ba",)))
    assert no_ba[1] == ("ba", stage_ba_ablated.__name__) and no_ba[:1] + no_ba[2:] == full[:1] + full[2:]
    assert _stage_names(BaseMethod, BaseConfig(ablate=("ba", "sw")))[2] == ("sw", stage_sw_ablated.__name__)


def test_prune_stage_runs_with_the_budget_only():
    from methods.base import BaseMethod

    on = BaseConfig(budget=dataclasses.replace(BaseConfig().budget, enabled=True))
    names = [n for n, _ in _stage_names(BaseMethod, on)]
    assert names[names.index("photometric") + 1] == "prune"
    assert "prune" not in [n for n, _ in _stage_names(BaseMethod, BaseConfig())]


def test_worldtree_grows_its_tree_before_the_test_pose():
    from methods.worldtree import WorldTreeMethod, stage_tree_no_ancestors, stage_tree_root_only

    names = _stage_names(WorldTreeMethod, WorldTreeConfig())
    assert [n for n, _ in names][-3:] == ["photometric", "tree", "test_pose"]
    assert ("tree", stage_tree_no_ancestors.__name__) in _stage_names(
        WorldTreeMethod, WorldTreeConfig(ablate=("sac",))
    )
    # tpt wins over sac: with both, no tree grows.
    both = _stage_names(WorldTreeMethod, WorldTreeConfig(ablate=("sac", "tpt")))
    assert ("tree", stage_tree_root_only.__name__) in both


def test_base_refuses_tree_ablations_and_options():
    # The library names the field; `wtbench run --ablate tpt` names the option (test_worldtree_config.py).
    with pytest.raises(UserError, match="^BaseConfig.ablate tpt: choose among ba, sw$"):
        _apply(BaseConfig(), "base", {"ablate": ["tpt"]})
    with pytest.raises(
        UserError,
        match=r"^--depth: method 'base' has no such option; drop it or use it with --method worldtree$",
    ):
        _apply(BaseConfig(), "base", {"depth": 1})
    with pytest.raises(
        UserError,
        match=r"^--ablate: method 'static' has no such option; drop it or use it with --method base or worldtree$",
    ):
        method_option_fields(get_method("static"), {"ablate": ["ba"]})


def test_worldtree_accepts_all_four():
    cfg = _apply(WorldTreeConfig(), "worldtree", {"ablate": ["sac", "tpt", "sw", "ba"]})
    assert cfg.ablate == ("ba", "sw", "tpt", "sac")
