"""The generic loop: interrupted + resumed training is bit-identical to an uninterrupted run; checkpoints are
atomic and pruned; a non-finite loss stops the run before the optimiser sees it."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from worldtree.checkpoint import list_checkpoints, load_checkpoint, save_checkpoint, seed_everything
from worldtree.infra.errors import UserError
from worldtree.optim import ExponentialLR, GroupedAdam
from worldtree.trainer import NonFiniteLossError, StepOutput, Trainer, TrainerConfig


class Toy:
    """Noisy linear regression: random batches from a generator, dropout from the global RNG, Adam, and a
    parameter that grows at step 7 (like densification) so that shapes change between checkpoints."""

    def __init__(self, seed: int, fail_at: int | None = None, nan_at: int | None = None):
        seed_everything(seed)
        self.data = torch.Generator().manual_seed(seed + 1)
        self.w = nn.Parameter(torch.randn(4, 3))
        self.opt = self._opt()
        self.fail_at, self.nan_at = fail_at, nan_at
        self.target = torch.linspace(-1, 1, 9).reshape(3, 3)  # fixed: not part of the state

    def _opt(self):
        return GroupedAdam({"w": self.w}, {"w": ExponentialLR(1e-2, 1e-3, 20)}, eps=1e-8)

    def training_step(self, step):
        if step == self.fail_at:
            raise KeyboardInterrupt
        self.opt.set_step(step)
        x = torch.randn(8, 3, generator=self.data)
        drop = (torch.rand(8, 1) > 0.2).float()
        pred = (x * drop) @ self.w[:3] + self.w[3:].sum(0)
        loss = ((pred - x @ self.target) ** 2).mean()
        if step == self.nan_at:
            loss = loss * float("nan")
        return StepOutput(loss=loss, scalars={"rows": float(self.w.shape[0])})

    def optimizer_step(self, step, out):
        self.opt.step()
        self.opt.zero_grad()
        if step == 7:
            with torch.no_grad():
                new = nn.Parameter(torch.cat([self.w, self.w[3:] * 0.5]))
            self.opt.replace_param("w", new, lambda _k, m: torch.cat([m, torch.zeros_like(m[3:])]))
            self.w = new
        return {}

    def state_dict(self):
        return {"w": self.w.detach().clone(), "opt": self.opt.state_dict()}

    def load_state_dict(self, st):
        self.w = nn.Parameter(st["w"].clone())
        self.opt = self._opt()
        self.opt.load_state_dict(st["opt"])


def _fit(task, folder, steps=20, every=5):
    cfg = TrainerConfig(steps=steps, checkpoint_every=every, keep_checkpoints=2)
    return Trainer(cfg, task, checkpoint_dir=folder, generators={"data": task.data}, progress=False).fit()


def test_resume_is_bit_identical(tmp_path):
    ref = Toy(seed=3)
    _fit(ref, tmp_path / "a")
    interrupted = Toy(seed=3, fail_at=13)
    with pytest.raises(KeyboardInterrupt):
        _fit(interrupted, tmp_path / "b")
    assert [s for s, _ in list_checkpoints(tmp_path / "b")] == [5, 10]
    resumed = Toy(seed=99)  # a different seed: everything must come from the checkpoint
    summary = _fit(resumed, tmp_path / "b")
    assert summary.start_step == 10 and summary.end_step == 20 and summary.steps_run == 10
    assert resumed.w.shape == (5, 3)
    assert torch.equal(resumed.w.detach(), ref.w.detach())
    ref_m = ref.opt.optimizer.state[ref.w]["exp_avg_sq"]
    assert torch.equal(resumed.opt.optimizer.state[resumed.w]["exp_avg_sq"], ref_m)
    # Only the newest two checkpoints stay, and no temporary files are left behind.
    assert [s for s, _ in list_checkpoints(tmp_path / "b")] == [15, 20]
    assert sorted(p.name for p in (tmp_path / "b").iterdir()) == ["ckpt_0000015.pt", "ckpt_0000020.pt"]
    # A finished run resumes to nothing.
    again = _fit(Toy(seed=3), tmp_path / "b")
    assert again.steps_run == 0 and again.final_loss is None


def test_non_finite_loss_stops_before_the_optimiser(tmp_path):
    task = Toy(seed=0, nan_at=4)
    with pytest.raises(NonFiniteLossError, match="step 4"):
        _fit(task, tmp_path, every=2)
    assert torch.isfinite(task.w).all()
    assert [s for s, _ in list_checkpoints(tmp_path)] == [2]


def test_checkpoint_roundtrip_and_damaged_file(tmp_path):
    p = save_checkpoint(tmp_path, 7, {"x": torch.arange(3), "nested": {"a": [1, 2.5, "s"]}})
    back = load_checkpoint(p)
    assert (
        back["step"] == 7 and torch.equal(back["x"], torch.arange(3)) and back["nested"]["a"] == [1, 2.5, "s"]
    )
    p.write_bytes(p.read_bytes()[:20])
    with pytest.raises(UserError, match="unreadable checkpoint"):
        load_checkpoint(p)


def test_negative_steps_rejected():
    with pytest.raises(UserError):
        Trainer(TrainerConfig(steps=-1), Toy(0))


def test_a_stop_whose_exception_was_lost_is_raised_by_the_next_step(tmp_path):
    """A signal handler's exception raised inside a callback whose errors Python only prints is lost; the stop
    it recorded is raised by the next training step, and leaving the handlers forgets it."""
    import signal

    from worldtree.infra import stop_request
    from worldtree.infra.cli_runner import Terminated, signals_raise

    class Swallowing(Toy):
        steps: list[int] = []

        def training_step(self, step):
            self.steps.append(step)
            if step == 4:
                try:
                    signal.raise_signal(signal.SIGTERM)  # the handler records the stop and raises...
                except Terminated:
                    pass  # ...and the exception is lost, as in a weakref callback
            return super().training_step(step)

    before = signal.getsignal(signal.SIGTERM)
    task = Swallowing(seed=1)
    with pytest.raises(Terminated), signals_raise():
        _fit(task, tmp_path / "a")
    assert task.steps == [1, 2, 3, 4]  # step 4 finished, step 5 never started
    assert signal.getsignal(signal.SIGTERM) == before
    stop_request.check()  # forgotten on the way out: nothing raised
