"""Early stop: the plateau rule fires where its definition says on hand-made loss curves, never while the loss
still falls, never before ``min_steps``; the trainer stops there, checkpoints, and a resumed fit adds no step."""

from __future__ import annotations

import torch
from torch import nn

from worldtree.optim import ConstantLR, GroupedAdam
from worldtree.plateau import PlateauDetector, PlateauRule
from worldtree.trainer import StepOutput, Trainer, TrainerConfig


def _run(rule: PlateauRule, losses: list[float], window: int) -> int | None:
    det = PlateauDetector(rule, window)
    for step, v in enumerate(losses, start=1):
        if det.update(step, v):
            return step
    return None


def test_falling_loss_never_stops():
    rule = PlateauRule(enabled=True, rel_tol=0.01, patience=2)
    assert _run(rule, [0.98**k for k in range(1000)], window=10) is None  # ~18 % better per window


def test_flat_loss_stops_after_patience_windows():
    rule = PlateauRule(enabled=True, rel_tol=0.01, patience=2)
    # Falls for 5 windows of 10, then flat: windows 6 and 7 do not improve on window 5 -> stop at step 70.
    losses = [1.0 - 0.1 * (k // 10) for k in range(50)] + [0.6] * 100
    assert _run(rule, losses, window=10) == 70


def test_min_steps():
    flat = [1.0] * 200
    assert _run(PlateauRule(enabled=True, patience=1, min_steps=95), flat, window=10) == 100
    det = PlateauRule(patience=1, min_window=10).detector(frames=4, min_steps=35)
    assert det.window == 10 and det.rule.min_steps == 35


def test_non_finite_loss_is_no_improvement():
    rule = PlateauRule(enabled=True, patience=1)
    assert _run(rule, [1.0] * 10 + [float("nan")] * 10, window=10) == 20


class _Flat:
    def __init__(self):
        self.w = nn.Parameter(torch.zeros(1))
        self.opt = GroupedAdam({"w": self.w}, {"w": ConstantLR(0.0)})
        self.steps = 0

    def training_step(self, step):
        self.steps += 1
        return StepOutput(loss=(self.w - 1.0).pow(2).sum())

    def optimizer_step(self, step, out):
        self.opt.step()
        self.opt.zero_grad()
        return {}

    def state_dict(self):
        return {"w": self.w.detach().clone()}

    def load_state_dict(self, st):
        self.w.data.copy_(st["w"])


def test_trainer_stops_and_resume_adds_nothing(tmp_path):
    rule = PlateauRule(enabled=True, patience=2, min_window=5)
    task = _Flat()
    det = PlateauDetector(rule, rule.window(3))
    s = Trainer(TrainerConfig(steps=100, checkpoint_every=0), task, tmp_path, progress=False, stop=det).fit()
    assert s.end_step == 15 and task.steps == 15 and det.stopped_at == 15  # windows 2 and 3 do not improve
    task2 = _Flat()
    det2 = PlateauDetector(rule, rule.window(3))
    s2 = Trainer(
        TrainerConfig(steps=100, checkpoint_every=0), task2, tmp_path, progress=False, stop=det2
    ).fit()
    assert s2.end_step == 15 and task2.steps == 0 and det2.stopped_at == 15
