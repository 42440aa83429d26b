"""The method registry: lookup, listing, and the rules a registration must follow."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from methods.registry import CommonConfig, MethodSpec, get_method, list_methods, register_method
from methods.static3dgs import StaticConfig
from worldtree.infra.errors import UserError


def test_static_is_registered_with_presets():
    spec = get_method("static")
    assert spec in list_methods() and spec.config_cls is StaticConfig
    quick, paper = spec.config("quick"), spec.config("paper")
    assert (
        paper.steps == 30_000 and paper.strategy.refine_start == 500 and paper.strategy.refine_stop == 15_000
    )
    assert paper.strategy.reset_every == 3000 and paper.strategy.grow_grad2d == 2e-4
    assert quick.steps == 1500 and quick.downscale == 2 and quick.strategy.refine_every == 100
    with pytest.raises(UserError, match="has presets paper, quick"):
        spec.config("nope")


def test_unknown_method_lists_registered_ones():
    with pytest.raises(UserError, match="choose one of: .*static"):
        get_method("nope")


def test_registration_rules():
    @dataclass
    class NoCommon:
        x: int = 1

    def build(cfg, scene, device):
        raise AssertionError

    with pytest.raises(TypeError, match="common fields"):
        register_method(MethodSpec("bad1", "", NoCommon, {"quick": NoCommon, "paper": NoCommon}, build))
    with pytest.raises(TypeError, match="'paper' preset"):
        register_method(MethodSpec("bad2", "", CommonConfig, {"quick": CommonConfig}, build))
    assert all(s.name not in ("bad1", "bad2") for s in list_methods())
