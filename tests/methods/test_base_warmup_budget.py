"""With the Gaussian budget on, the static warm-up stops growing at one view's full budget."""

from __future__ import annotations

import dataclasses

from methods.base import BaseConfig, paper_config, warmup_config
from worldtree.budget import BudgetConfig


def test_paper_preset_keeps_the_budget_on_unless_told_otherwise():
    assert paper_config().root_budget_on() and paper_config().budget_on()
    assert not paper_config(budget=BudgetConfig(enabled=False)).budget_on()


def test_budget_off_leaves_the_warm_up_uncapped():
    c = paper_config(budget=BudgetConfig(enabled=False))
    assert not c.root_budget_on()
    sw = warmup_config(c, 6000, 90, 160)
    assert sw.steps == 6000
    assert sw.strategy == c.sw.strategy
    assert "sw.strategy.max_gaussians" not in c.ignored_settings()


def test_budget_on_caps_the_warm_up_at_gaussians_per_pixel_times_the_view():
    c = paper_config(budget=BudgetConfig(enabled=True, gaussians_per_pixel=0.5))
    sw = warmup_config(c, 1234, 90, 160)
    assert sw.steps == 1234
    assert sw.strategy.max_gaussians == 0.5 * 90 * 160  # closed form: the full budget, no error scaling
    # Everything else of the strategy is the preset's.
    assert dataclasses.replace(sw.strategy, max_gaussians=0) == dataclasses.replace(
        c.sw.strategy, max_gaussians=0
    )
    assert "sw.strategy.max_gaussians" in c.ignored_settings()


def test_budget_override_is_the_cap():
    c = dataclasses.replace(BaseConfig(), budget=BudgetConfig(enabled=True, override=777))
    assert warmup_config(c, 10, 270, 480).strategy.max_gaussians == 777
