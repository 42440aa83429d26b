"""A diverging fit stops with one line and is never marked finished (issue #30: `--set
photometric.lr_means=1e30` finished with Gaussians at ~1e30 and PSNR 9, marked DONE; `lambda_depth=inf` was
a 56-line traceback)."""

from __future__ import annotations

import math
import os
import re
import subprocess
import sys

import pytest
import torch
from torch import nn

from worldtree.checkpoint import list_checkpoints
from worldtree.infra.errors import UserError
from worldtree.optim import ConstantLR, GroupedAdam
from worldtree.trainer import NonFiniteLossError, StepOutput, Trainer, TrainerConfig, TrainingDivergedError


class Points:
    """Positions pulled towards the origin; ``lr`` sets how wildly Adam moves them, ``loss_growth`` makes the
    reported loss climb by that factor per step, ``inf_at`` writes an Inf into the positions at that step."""

    def __init__(self, lr=1e-2, extent=1.0, loss_growth=1.0, inf_at=None):
        self.means = nn.Parameter(torch.full((5, 3), 0.5))
        self.means.data[0] = 0.25
        self.optimizer = GroupedAdam({"means": self.means}, {"means": ConstantLR(lr)})
        self.extent, self.growth, self.inf_at = extent, loss_growth, inf_at

    def training_step(self, step):
        loss = 1.0 + (self.means[1:] - 0.3).abs().mean()  # row 0 is never used: only its value can blow up
        return StepOutput(loss=loss * self.growth**step)

    def optimizer_step(self, step, out):
        self.optimizer.step()
        self.optimizer.zero_grad()
        if step == self.inf_at:
            with torch.no_grad():
                self.means[0, 0] = math.inf
        return {}

    def state_dict(self):
        return {"means": self.means.detach().clone(), "opt": self.optimizer.state_dict()}

    def load_state_dict(self, st):
        self.means.data.copy_(st["means"])
        self.optimizer.load_state_dict(st["opt"])


def _fit(task, folder, steps=40, every=5):
    return Trainer(TrainerConfig(steps=steps, checkpoint_every=every), task, folder, progress=False,
                   description="toy").fit()  # fmt: skip


def test_sane_fit_is_not_flagged(tmp_path):
    summary = _fit(Points(), tmp_path)
    assert summary.end_step == 40 and [s for s, _ in list_checkpoints(tmp_path)][-1] == 40


def test_exploding_positions_stop_before_a_checkpoint(tmp_path):
    with pytest.raises(TrainingDivergedError) as err:
        _fit(Points(lr=1e9, extent=1.0), tmp_path)
    msg = str(err.value)
    assert isinstance(err.value, UserError) and "\n" not in msg
    assert msg.startswith("toy: training diverged at step 1 (optimizer.means reached")
    assert "x the scene extent 1); lower the learning rates" in msg
    assert list_checkpoints(tmp_path) == []  # the blown-up model was never saved


def test_extent_defaults_to_the_first_scale(tmp_path):
    task = Points(lr=1e9)
    del task.extent
    with pytest.raises(TrainingDivergedError, match="at step 1 .*scene extent 0.5"):
        _fit(task, tmp_path)


def test_non_finite_parameter(tmp_path):
    with pytest.raises(
        TrainingDivergedError, match=r"at step 10 \(parameter optimizer.means holds NaN or Inf\)"
    ):
        _fit(Points(inf_at=8), tmp_path)
    assert [s for s, _ in list_checkpoints(tmp_path)] == [5]


def test_loss_far_above_its_early_level(tmp_path):
    with pytest.raises(TrainingDivergedError, match="x its early level"):
        _fit(Points(loss_growth=1.3), tmp_path, steps=200)


def test_non_finite_loss_is_one_line(tmp_path):
    class Inf(Points):
        def training_step(self, step):
            return StepOutput(loss=super().training_step(step).loss * math.inf)

    with pytest.raises(NonFiniteLossError, match=r"^toy: training diverged at step 1 \(loss is inf\)") as err:
        _fit(Inf(), tmp_path)
    assert isinstance(err.value, UserError)


def test_absurd_learning_rate_run_stops_in_one_line_without_done(scene, tmp_path):
    runs = tmp_path / "runs"
    out = subprocess.run(
        [sys.executable, "-m", "benchmarks.cli", "run", "--method", "base", "--scene", str(scene), "-o", str(runs),
         "--preset", "smoke", "--device", "cpu", "--set", "photometric.lr_means=1e30"],
        capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)),
    )  # fmt: skip
    assert out.returncode == 2, out.stderr
    # Progress ("stage NAME ...", "DESCRIPTION: step i/n ...") and warnings are not errors.
    progress = re.compile(r"^(stage \S+ |([\w .-]+: )?step \d+/\d+ |warning:)")
    errors = [line for line in out.stderr.splitlines() if not progress.match(line)]
    assert len(errors) == 1 and "Traceback" not in out.stderr, out.stderr
    assert errors[0].startswith("error: photometric: training diverged at step ")
    assert "lower the learning rates" in errors[0]
    assert list(runs.rglob("DONE")) == [] and list(runs.rglob("metrics.csv")) == []
