"""A generic, seeded, resumable training loop; a method plugs in through the small :class:`Trainable` interface.

The loop owns what every method shares: step counting (1-based), backward, the divergence guard (a non-finite
loss or parameter, positions far outside the scene, a loss far above its early level: one-line error), periodic
atomic checkpoints (:mod:`worldtree.checkpoint`) with the RNG states, resuming from the newest checkpoint, a
progress display (step, loss, iterations/s, ETA) and optional TensorBoard scalars. The method owns its model,
optimisers, density control and loss::

    class MyMethod:                       # satisfies Trainable
        def training_step(self, step) -> StepOutput: ...   # forward + loss (no backward)
        def optimizer_step(self, step, out) -> dict: ...   # after backward: optimiser, densification
        def state_dict(self) -> dict: ...                    # everything needed to resume
        def load_state_dict(self, state) -> None: ...

    Trainer(TrainerConfig(steps=1000), MyMethod(...), checkpoint_dir=run / "checkpoints").fit()

Methods with several stages run one Trainer per stage, each with its own checkpoint folder.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import torch

import worldtree
from worldtree.checkpoint import (
    capture_rng_state,
    latest_checkpoint,
    load_checkpoint,
    restore_rng_state,
    save_checkpoint,
)
from worldtree.infra import stop_request, thread_governor
from worldtree.infra.errors import SettingError, UserError
from worldtree.plateau import PlateauDetector


@dataclass
class StepOutput:
    """What a method's forward pass returns to the loop."""

    loss: torch.Tensor
    """Scalar loss to back-propagate."""
    scalars: dict[str, float] = field(default_factory=dict)
    """Extra numbers to log (loss parts, Gaussian count, ...)."""
    info: Any = None
    """Anything the method needs again in ``optimizer_step`` (e.g. the render output)."""


class Trainable(Protocol):
    """The interface a method implements to be trained by :class:`Trainer`."""

    def training_step(self, step: int) -> StepOutput: ...

    def optimizer_step(self, step: int, out: StepOutput) -> dict[str, float]: ...

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> None: ...


class DensifiedGaussianTrainable:
    """Shared :class:`Trainable` plumbing for one densified Gaussian set trained on shuffled frames.

    A subclass provides ``gaussians`` (GaussianSet), ``optimizer`` (GroupedAdam), ``strategy_state`` (dict),
    ``queue`` (list of frame indices), ``order`` (torch.Generator), ``cfg.strategy`` (DensifyStrategy),
    ``frame_count`` (training frames) and ``_make_optimizer()``; it writes ``training_step`` itself.
    """

    def _next_frame(self) -> int:
        # Every frame once per epoch, in a seeded order that a checkpoint restores (the queue is saved).
        if not self.queue:
            self.queue = torch.randperm(self.frame_count, generator=self.order).tolist()
        return self.queue.pop()

    def optimizer_step(self, step: int, out: StepOutput) -> dict[str, float]:
        self.optimizer.step()
        self.optimizer.zero_grad()
        self.cfg.strategy.step_post_backward(
            self.gaussians, self.optimizer, self.strategy_state, step, out.info
        )
        return {"gaussians": float(len(self.gaussians))}

    def state_dict(self) -> dict[str, Any]:
        st = self.strategy_state
        return {
            "gaussians": {k: v.detach().cpu() for k, v in self.gaussians.params.items()},
            "optimizer": self.optimizer.state_dict(),
            "strategy": {k: (v.cpu() if isinstance(v, torch.Tensor) else v) for k, v in st.items()},
            "queue": list(self.queue),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.gaussians.load_params(state["gaussians"])
        self.optimizer = self._make_optimizer()
        self.optimizer.load_state_dict(state["optimizer"])
        dev = self.gaussians.means.device
        self.strategy_state = {
            k: (v.to(dev) if isinstance(v, torch.Tensor) else v) for k, v in state["strategy"].items()
        }
        self.queue = [int(i) for i in state["queue"]]


@dataclass
class TrainerConfig:
    """Settings of the loop itself (the method's settings live in its own config)."""

    steps: int = 30_000
    """Total optimisation steps (1-based: the last step is ``steps``)."""
    checkpoint_every: int = 1000
    """Save a checkpoint every this many steps (and always at the last step); 0 = only at the end."""
    keep_checkpoints: int = 2
    """Newest checkpoints to keep on disk."""
    log_every: int = 50
    """Period of TensorBoard scalars and, when the output is not a terminal, of plain progress lines."""


@dataclass
class TrainContext:
    """Where and how a method's training runs (given by the driver, e.g. ``wtbench run``)."""

    checkpoint_dir: Path | None = None
    """Folder for periodic checkpoints (a multi-stage method uses one sub-folder per stage); None = none."""
    tensorboard_dir: Path | None = None
    """Write TensorBoard scalars there; None = no TensorBoard."""
    progress: bool = True
    """Show progress."""
    resume: bool = True
    """Continue from the newest checkpoint in ``checkpoint_dir`` when there is one."""


@dataclass
class TrainSummary:
    """What a call to :meth:`Trainer.fit` did."""

    start_step: int
    """Last step already done before this call (0 for a fresh run, the checkpoint's step when resumed)."""
    end_step: int
    """Last step done after this call."""
    wall_s: float
    """Seconds spent in this call's training steps."""
    final_loss: float | None
    """Loss of the last step run in this call, None when no step ran."""
    total_wall_s: float = 0.0
    """Training seconds of every session that led to ``end_step`` (checkpointed time plus this call's)."""

    @property
    def steps_run(self) -> int:
        return self.end_step - self.start_step

    @property
    def it_per_s(self) -> float:
        """Iterations per second over every session (this call alone when nothing was checkpointed)."""
        if self.total_wall_s > 0:
            return self.end_step / self.total_wall_s
        return self.steps_run / self.wall_s if self.wall_s > 0 else 0.0


class TrainingDivergedError(UserError, RuntimeError):
    """The fit blew up (settings such as a huge learning rate or loss weight); the CLIs print it as one
    ``error:`` line and the run is not marked finished."""


class NonFiniteLossError(TrainingDivergedError):
    """The loss became NaN or Inf; the optimiser is not stepped with it."""


# Positions (parameter groups of these names) further than this many scene extents from the origin mean the
# fit has diverged: a scene is about one extent across, and a Gaussian that far away is never seen again.
POSITION_GROUPS = ("means", "node_pos")
DIVERGED_EXTENTS = 1e6
# A training loss whose running mean climbs this many times above its early level (the median of the first
# EARLY_STEPS steps of a session, at least LOSS_FLOOR) has diverged; photometric losses stay within a few x.
LOSS_BLOWUP = 50.0
EARLY_STEPS = 20
LOSS_FLOOR = 1e-3
# Parameters are checked every this many steps (and before every checkpoint): a reduction over every tensor.
CHECK_EVERY = 10


class DivergenceGuard:
    """Detects a diverging fit from its losses and parameters (see the constants above).

    The parameters are found in the task's optimisers (:class:`worldtree.optim.GroupedAdam` or
    ``torch.optim.Optimizer`` attributes); the scale of positions is the task's ``extent`` attribute when it
    has one, else the largest position before the first step.
    """

    def __init__(self, task: Any, description: str):
        self.task = task
        self.description = description
        self.extent = getattr(task, "extent", None)
        if self.extent is None:
            far = [float(p.detach().abs().max()) for n, p in _positions(task) if p.numel()]
            self.extent = max([*far, 1e-6]) if far else None
        self.early: list[float] = []
        self.running: float | None = None

    def _fail(self, step: int, why: str) -> None:
        raise TrainingDivergedError(
            f"{self.description}: training diverged at step {step} ({why}); lower the learning rates or loss "
            "weights you changed (--set ...) and re-run with --force"
        )

    def check_loss(self, step: int, loss: float) -> None:
        """Refuse a non-finite loss, or a running mean far above the early level."""
        if not math.isfinite(loss):
            raise NonFiniteLossError(
                f"{self.description}: training diverged at step {step} (loss is {loss}); lower the learning "
                "rates or loss weights you changed (--set ...), or check the inputs, and re-run with --force"
            )
        if len(self.early) < EARLY_STEPS:
            self.early.append(loss)
            return
        self.running = loss if self.running is None else 0.9 * self.running + 0.1 * loss
        ref = max(sorted(self.early)[len(self.early) // 2], LOSS_FLOOR)
        if self.running > LOSS_BLOWUP * ref:
            self._fail(step, f"loss {self.running:.4g}, {self.running / ref:.0f}x its early level {ref:.4g}")

    def check_parameters(self, step: int) -> None:
        """Refuse non-finite parameters, and positions beyond ``DIVERGED_EXTENTS`` scene extents."""
        for name, p in _parameters(self.task):
            with torch.no_grad():
                if p.numel() == 0:
                    continue
                if not bool(torch.isfinite(p).all()):
                    self._fail(step, f"parameter {name} holds NaN or Inf")
                if name.rsplit(".", 1)[-1] in POSITION_GROUPS:
                    far = float(p.abs().max())
                    if self.extent is None:
                        self.extent = max(far, 1e-6)  # no extent given: the positions' first scale
                    if far > DIVERGED_EXTENTS * self.extent:
                        self._fail(
                            step,
                            f"{name} reached {far:.3g}, over {DIVERGED_EXTENTS:g} x the scene extent "
                            f"{self.extent:.3g}",
                        )


def _positions(task: Any) -> list[tuple[str, torch.Tensor]]:
    return [(n, p) for n, p in _parameters(task) if n.rsplit(".", 1)[-1] in POSITION_GROUPS]


def _parameters(task: Any) -> list[tuple[str, torch.Tensor]]:
    """``(optimiser attribute.group name, tensor)`` of every parameter the task's optimisers hold."""
    out = []
    for attr, value in vars(task).items():
        opt = getattr(value, "optimizer", value)  # GroupedAdam wraps a torch optimiser
        if not isinstance(opt, torch.optim.Optimizer):
            continue
        for i, group in enumerate(opt.param_groups):
            for p in group["params"]:
                out.append((f"{attr}.{group.get('name', i)}", p))
    return out


class Trainer:
    """Run ``task`` for ``cfg.steps`` steps with checkpoints in ``checkpoint_dir`` (None: no checkpoints).

    Args:
        cfg: loop settings.
        task: the method being trained.
        checkpoint_dir: folder for checkpoints; resuming reads the newest one found there.
        generators: extra ``torch.Generator`` objects whose states the checkpoints carry (e.g. data order).
        tensorboard_dir: write TensorBoard scalars there (needs the ``tensorboard`` package).
        progress: show progress at all.
        description: label of the progress display.
        stop: early-stop rule state (:mod:`worldtree.plateau`); the fit ends after the step at which it fires
            (checkpointed, so a resumed fit does not continue), otherwise at ``cfg.steps``.
    """

    def __init__(
        self,
        cfg: TrainerConfig,
        task: Trainable,
        checkpoint_dir: str | Path | None = None,
        generators: dict[str, torch.Generator] | None = None,
        tensorboard_dir: str | Path | None = None,
        progress: bool = True,
        description: str = "train",
        stop: PlateauDetector | None = None,
    ):
        if cfg.steps < 0:
            raise SettingError.of_field(cfg, "steps", "must be >= 0")
        self.cfg = cfg
        self.task = task
        self.checkpoint_dir = Path(checkpoint_dir) if checkpoint_dir is not None else None
        self.generators = generators or {}
        self.tensorboard_dir = tensorboard_dir
        self.progress = progress
        self.description = description
        self.stop = stop
        self._prior_seconds = 0.0

    def resume(self) -> int:
        """Load the newest checkpoint if any; return its step (0 when starting fresh)."""
        if self.checkpoint_dir is None:
            return 0
        path = latest_checkpoint(self.checkpoint_dir)
        if path is None:
            return 0
        ckpt = load_checkpoint(path)
        self.task.load_state_dict(ckpt["task"])
        restore_rng_state(ckpt["rng"], self.generators)
        self._prior_seconds = float(ckpt.get("train_seconds", 0.0))
        if self.stop is not None and ckpt.get("plateau") is not None:
            self.stop.load_state_dict(ckpt["plateau"])
        return int(ckpt["step"])

    def save(self, step: int, seconds: float) -> None:
        """Checkpoint the task after ``step``; ``seconds`` = training time of every session so far."""
        if self.checkpoint_dir is None:
            return
        payload = {
            "task": self.task.state_dict(),
            "rng": capture_rng_state(self.generators),
            "version": worldtree.__version__,
            "train_seconds": float(seconds),
            "plateau": self.stop.state_dict() if self.stop is not None else None,
        }
        save_checkpoint(self.checkpoint_dir, step, payload, keep=self.cfg.keep_checkpoints)

    def fit(self, resume: bool = True) -> TrainSummary:
        """Train from the newest checkpoint (when ``resume``) or from scratch up to ``cfg.steps``."""
        self._prior_seconds = 0.0
        start = self.resume() if resume else 0
        total = self.cfg.steps
        writer = _tensorboard_writer(self.tensorboard_dir)
        report = Progress(self.description, start, total, self.progress, self.cfg.log_every)
        last_loss: float | None = None
        t0 = time.perf_counter()
        step = start
        if self.stop is not None and self.stop.stopped_at is not None:
            total = start  # resumed after the plateau rule had stopped the fit: nothing left to do
        guard = DivergenceGuard(self.task, self.description)
        try:
            for step in range(start + 1, total + 1):
                stop_request.check()  # a Ctrl-C / SIGTERM whose exception was lost elsewhere stops here
                thread_governor.tick()  # the torch team follows the free cores
                out = self.task.training_step(step)
                loss_value = float(out.loss.detach())
                guard.check_loss(step, loss_value)  # before backward: a non-finite loss never steps
                out.loss.backward()
                extra = self.task.optimizer_step(step, out) or {}
                last_loss = loss_value
                scalars = {"loss": loss_value, **out.scalars, **extra}
                report.update(step, scalars)
                if writer is not None and (step % self.cfg.log_every == 0 or step == total):
                    for k, v in scalars.items():
                        writer.add_scalar(f"{self.description}/{k}", v, step)
                every = self.cfg.checkpoint_every
                done = self.stop is not None and self.stop.update(step, loss_value)
                save = done or step == total or (every > 0 and step % every == 0)
                if save or step % CHECK_EVERY == 0 or step == start + 1:
                    guard.check_parameters(step)  # a diverged model is never checkpointed
                if save:
                    self.save(step, self._prior_seconds + time.perf_counter() - t0)
                if done:
                    break
        finally:
            report.close()
            if writer is not None:
                writer.close()
        wall = time.perf_counter() - t0
        return TrainSummary(
            start_step=start,
            end_step=max(step, start),
            wall_s=wall,
            final_loss=last_loss,
            total_wall_s=self._prior_seconds + wall,
        )


def check_tensorboard() -> None:
    """Raise :class:`UserError` unless TensorBoard logging can work (the ``tensorboard`` package imports)."""
    try:
        from torch.utils.tensorboard import SummaryWriter  # noqa: F401
    except ImportError as e:
        raise UserError(
            "--tensorboard needs the tensorboard package; install it with "
            "`pip install 'worldtree-bench[tensorboard]'` or drop the option"
        ) from e


def _tensorboard_writer(log_dir: str | Path | None):
    if log_dir is None:
        return None
    check_tensorboard()
    from torch.utils.tensorboard import SummaryWriter

    return SummaryWriter(log_dir=str(log_dir))


class Progress:
    """Rich progress bar on a terminal; plain lines every ``log_every`` steps otherwise; nothing if disabled.
    ``update(step, {"loss": ..., ...})`` after a step, ``close()`` at the end (the Trainer's, and a stage's own
    loop)."""

    def __init__(self, description: str, start: int, total: int, enabled: bool, log_every: int):
        self.enabled = enabled
        self.total = total
        self.start = start
        self.log_every = max(log_every, 1)
        self.description = description
        self.t0 = time.perf_counter()
        self.bar = None
        if not enabled:
            return
        from rich.console import Console

        console = Console(stderr=True)
        if console.is_terminal:
            from rich.progress import BarColumn, Progress, TextColumn

            self.bar = Progress(
                TextColumn("[bold]{task.description}"),
                BarColumn(bar_width=20),
                TextColumn("{task.fields[text]}"),
                console=console,
            )
            self.bar.start()
            self.task_id = self.bar.add_task(description, total=total, completed=start, text="")
        elif start > 0:
            print(f"{description}: resuming after step {start}/{total}", file=sys.stderr)

    def update(self, step: int, scalars: dict[str, float]) -> None:
        if not self.enabled:
            return
        elapsed = time.perf_counter() - self.t0
        rate = (step - self.start) / elapsed if elapsed > 0 else 0.0
        eta = _clock((self.total - step) / rate) if rate > 0 else "?"
        extra = " ".join(f"{k} {_fmt(v)}" for k, v in scalars.items() if k != "loss")
        text = f"step {step}/{self.total}  loss {scalars['loss']:.4f}  {rate:.1f} it/s  ETA {eta}  {extra}"
        if self.bar is not None:
            self.bar.update(self.task_id, completed=step, text=text)
        elif step % self.log_every == 0 or step == self.total:
            print(f"{self.description}: {text}", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()


def _clock(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


def _fmt(v: float) -> str:
    if isinstance(v, int) or float(v).is_integer():
        return str(int(v))
    return f"{v:.4g}"
