"""`--ablate ba|sw` reaches the Base config through `wtbench run`'s option path; tree options are refused."""

from __future__ import annotations

import dataclasses

import pytest

from benchmarks.runner.runs import _method_options, run_tag
from methods.base import BaseConfig
from methods.worldtree import WorldTreeConfig
from worldtree.errors import UserError


def _apply(cfg, method, options):
    return dataclasses.replace(cfg, **_method_options(cfg, method, options))


def test_base_accepts_ablate_ba_and_sw():
    cfg = _apply(BaseConfig(), "base", {"ablate": ["sw", "ba"]})
    assert cfg.ablate_ba and cfg.ablate_sw and cfg.ablate == ("ba", "sw")
    assert not _apply(BaseConfig(), "base", {"ablate": ["sw"]}).ablate_ba
    # The two spellings agree both ways.
    assert BaseConfig(ablate_ba=True).ablate == ("ba",)
    assert run_tag("quick", {}, {"ablate": ["ba"]}) != run_tag("quick", {}, {})


def test_base_refuses_tree_ablations_and_options():
    with pytest.raises(UserError, match="--ablate tpt: choose among ba, sw"):
        _apply(BaseConfig(), "base", {"ablate": ["tpt"]})
    with pytest.raises(UserError, match="--depth"):
        _apply(BaseConfig(), "base", {"depth": 1})


def test_worldtree_accepts_all_four():
    cfg = _apply(WorldTreeConfig(), "worldtree", {"ablate": ["sac", "tpt", "sw", "ba"]})
    assert cfg.ablate == ("ba", "sw", "tpt", "sac") and cfg.ablate_ba and cfg.ablate_sw
