"""worldtree.infra.config_json: typed settings written as JSON come back equal, with their types (tuples, nested and
optional dataclasses); unknown keys are refused."""

from __future__ import annotations

import dataclasses
import json

import pytest

from worldtree.budget import BudgetConfig
from worldtree.infra.config_json import from_dict, read_config, write_config
from worldtree.plateau import PlateauRule
from worldtree.tree.adaptive import AutoSplitConfig
from worldtree.tree.sac import AncestorPolicy


def test_node_settings_round_trip(tmp_path):
    from methods.registry import get_method
    from methods.worldtree import NodeTrainConfig

    wt = get_method("worldtree").config("quick")
    cfg = NodeTrainConfig(
        photometric=wt.photometric, layer_steps=(7, 5), policy=AncestorPolicy(optimised_nearest=1),
        no_ancestors=False, extent=2.5, checkpoint_every=3, log_every=1, min_len=9, auto=AutoSplitConfig(),
        budget=BudgetConfig(enabled=True), inherit_opacity=0.25, early_stop=PlateauRule(enabled=True),
    )  # fmt: skip
    write_config(tmp_path / "c.json", cfg)
    back = read_config(tmp_path / "c.json", NodeTrainConfig)
    assert back == cfg  # dataclass equality: every value, nested ones included
    assert isinstance(back.layer_steps, tuple) and isinstance(back.policy.gaussian_params, tuple)
    assert isinstance(back.photometric.static_strategy, type(cfg.photometric.static_strategy))
    # Optional members stay None; the file is plain JSON a person can read.
    none = dataclasses.replace(cfg, auto=None, budget=None, early_stop=None)
    write_config(tmp_path / "n.json", none)
    assert read_config(tmp_path / "n.json", NodeTrainConfig) == none
    assert json.loads((tmp_path / "n.json").read_text())["auto"] is None


def test_unknown_settings_and_int_for_float():
    with pytest.raises(ValueError, match=r"AncestorPolicy: unknown settings \['nearest'\]"):
        from_dict(AncestorPolicy, {"nearest": 3})
    rule = from_dict(PlateauRule, {"rel_tol": 0, "patience": 3})  # JSON 0 for a float field
    assert rule == PlateauRule(rel_tol=0.0, patience=3) and isinstance(rule.rel_tol, float)


def test_method_configs_round_trip_with_derived_fields(tmp_path):
    """Every method's preset comes back equal; a derived field (``init=False``, e.g. WorldTreeConfig.auto_depth)
    is written with the rest and skipped when read, the config setting it again."""
    from methods.registry import list_methods

    for spec in list_methods():
        cfg = spec.config("quick")
        write_config(tmp_path / f"{spec.name}.json", cfg)
        assert read_config(tmp_path / f"{spec.name}.json", spec.config_cls) == cfg
    assert "auto_depth" in json.loads((tmp_path / "worldtree.json").read_text())
