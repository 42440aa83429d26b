"""Adam with one named parameter group per tensor, each following its own learning-rate schedule.

Schedules are small frozen dataclasses called with the step number (0-based) and returning a learning rate:

- :class:`ConstantLR`: ``lr(s) = value``.
- :class:`ExponentialLR`: log-linear from ``init`` to ``final`` over ``max_steps`` (3DGS's position schedule),
  ``lr(s) = d(s) * exp((1 - t) ln(init) + t ln(final))`` with ``t = clip(s / max_steps, 0, 1)`` and the
  optional warm-up factor ``d(s) = m + (1 - m) sin(pi/2 * clip(s / delay_steps, 0, 1))`` (``m = delay_mult``).
- :class:`CosineLR`: ``lr(s) = final + (init - final) (1 + cos(pi t)) / 2``.

:class:`GroupedAdam` keeps the name of each group so that density control can swap a tensor for a grown or
shrunk one and carry its Adam moments along (:meth:`GroupedAdam.replace_param`). It takes torch's fused Adam
(one kernel per tensor instead of about ten) wherever torch has one for the tensors (:func:`fused_supported`):
the same update, rounded in another order (last-bit differences), about a third cheaper on a CPU.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass

import torch
from torch import nn


@dataclass(frozen=True)
class ConstantLR:
    """A fixed learning rate."""

    value: float
    """Learning rate at every step."""

    def __call__(self, step: int) -> float:
        return float(self.value)


@dataclass(frozen=True)
class ScaledLR:
    """Another schedule times a constant factor (0 freezes the group: Adam's update is ``lr * ...``)."""

    base: Callable[[int], float]
    """The schedule scaled."""
    scale: float
    """Factor >= 0."""

    def __call__(self, step: int) -> float:
        return float(self.scale) * float(self.base(step))


@dataclass(frozen=True)
class ExponentialLR:
    """Log-linear decay from ``init`` to ``final`` (3DGS's position learning rate), with optional warm-up."""

    init: float
    """Learning rate at step 0."""
    final: float
    """Learning rate at ``max_steps`` and after."""
    max_steps: int
    """Steps over which the rate decays."""
    delay_steps: int = 0
    """Length of the sine warm-up; 0 disables it."""
    delay_mult: float = 1.0
    """Warm-up factor at step 0 (rises to 1 at ``delay_steps``)."""

    def __post_init__(self) -> None:
        if self.init <= 0 or self.final <= 0:
            raise ValueError(f"ExponentialLR needs positive init/final, got {self.init}, {self.final}")
        if self.max_steps < 1:
            raise ValueError(f"ExponentialLR needs max_steps >= 1, got {self.max_steps}")

    def __call__(self, step: int) -> float:
        if step < 0:
            return 0.0
        if self.delay_steps > 0:
            r = min(max(step / self.delay_steps, 0.0), 1.0)
            delay = self.delay_mult + (1.0 - self.delay_mult) * math.sin(0.5 * math.pi * r)
        else:
            delay = 1.0
        t = min(max(step / self.max_steps, 0.0), 1.0)
        return delay * math.exp((1.0 - t) * math.log(self.init) + t * math.log(self.final))


@dataclass(frozen=True)
class CosineLR:
    """Half-cosine from ``init`` to ``final`` over ``max_steps``."""

    init: float
    """Learning rate at step 0."""
    final: float
    """Learning rate at ``max_steps`` and after."""
    max_steps: int
    """Steps over which the rate decays."""

    def __call__(self, step: int) -> float:
        t = min(max(step / max(self.max_steps, 1), 0.0), 1.0)
        return self.final + (self.init - self.final) * 0.5 * (1.0 + math.cos(math.pi * t))


Schedule = Callable[[int], float]


def gaussian_schedules(
    lr_means: float,
    lr_means_final: float,
    steps: int,
    lr_quats: float,
    lr_scales: float,
    lr_opacity: float,
    lr_sh0: float,
) -> dict[str, ConstantLR | ExponentialLR]:
    """Schedules of a Gaussian set's parameter groups as in 3DGS: positions decay exponentially from
    ``lr_means`` to ``lr_means_final`` over ``steps`` (already scaled by the scene extent); the rest are
    constant."""
    return {
        "means": ExponentialLR(lr_means, lr_means_final, max(steps, 1)),
        "quats": ConstantLR(lr_quats),
        "log_scales": ConstantLR(lr_scales),
        "opacity_logits": ConstantLR(lr_opacity),
        "sh0": ConstantLR(lr_sh0),
    }


_FUSED_DEVICES = ("cpu", "cuda")
_FUSED_DTYPES = (torch.float16, torch.bfloat16, torch.float32, torch.float64)


def fused_supported(params: Iterable[torch.Tensor]) -> bool:
    """Whether torch's fused Adam takes every tensor of ``params``: dense floating tensors on one CPU or CUDA
    device (what ``torch.optim.Adam(..., fused=True)`` accepts); ``False`` for none."""
    ps = list(params)
    if not ps:
        return False
    dev = ps[0].device
    return dev.type in _FUSED_DEVICES and all(
        p.device == dev and p.dtype in _FUSED_DTYPES and p.layout == torch.strided for p in ps
    )


def adam_fused(params: Iterable[torch.Tensor], want: bool | None = None) -> bool | None:
    """The ``fused`` argument for ``torch.optim.Adam`` over ``params``: ``True`` when asked, or when not said
    (``want`` None) and :func:`fused_supported`; otherwise ``None``, never ``False``: ``False`` would also turn
    off the multi-tensor (foreach) path torch takes by default on CUDA."""
    if want is None:
        want = fused_supported(params)
    return True if want else None


class GroupedAdam:
    """``torch.optim.Adam`` with one group per named tensor and a learning-rate schedule per group.

    Args:
        params: name -> parameter (each becomes its own group; the name is stored in the group).
        schedules: name -> schedule; every name in ``params`` needs one.
        eps: Adam epsilon (3DGS uses 1e-15 because its gradients are tiny).
        betas: Adam betas.
        fused: torch's fused update; ``None`` takes it where :func:`fused_supported` says so. A checkpoint
            keeps the choice it was made with (``load_state_dict`` restores the saved groups).
    """

    def __init__(
        self,
        params: Mapping[str, nn.Parameter],
        schedules: Mapping[str, Schedule],
        eps: float = 1e-15,
        betas: tuple[float, float] = (0.9, 0.999),
        fused: bool | None = None,
    ):
        missing = [k for k in params if k not in schedules]
        if missing:
            raise ValueError(f"no learning-rate schedule for parameter groups {missing}")
        self.schedules = dict(schedules)
        groups = [{"params": [p], "name": k, "lr": self.schedules[k](0)} for k, p in params.items()]
        self.optimizer = torch.optim.Adam(
            groups, eps=eps, betas=betas, fused=adam_fused(params.values(), fused)
        )

    @property
    def names(self) -> list[str]:
        return [g["name"] for g in self.optimizer.param_groups]

    def group(self, name: str) -> dict:
        for g in self.optimizer.param_groups:
            if g["name"] == name:
                return g
        raise KeyError(name)

    def set_step(self, step: int) -> None:
        """Set every group's learning rate to its schedule's value at ``step``."""
        for g in self.optimizer.param_groups:
            g["lr"] = self.schedules[g["name"]](step)

    def lr(self, name: str) -> float:
        return float(self.group(name)["lr"])

    def step(self) -> None:
        self.optimizer.step()

    def zero_grad(self) -> None:
        self.optimizer.zero_grad(set_to_none=True)

    def replace_param(
        self,
        name: str,
        new_param: nn.Parameter,
        state_fn: Callable[[str, torch.Tensor], torch.Tensor],
    ) -> None:
        """Put ``new_param`` in place of group ``name``'s tensor and move its Adam state.

        ``state_fn(key, value)`` maps each per-element state tensor (``exp_avg``, ``exp_avg_sq``) of the old
        tensor to the new tensor's shape (e.g. index rows, append zeros). The step counter is kept.
        """
        g = self.group(name)
        old = g["params"][0]
        st = self.optimizer.state.pop(old, None)
        g["params"][0] = new_param
        if st is None:
            return
        new_st = {}
        for k, v in st.items():
            if isinstance(v, torch.Tensor) and v.shape == old.shape:
                new_st[k] = state_fn(k, v)
            else:
                new_st[k] = v
        self.optimizer.state[new_param] = new_st

    def state_dict(self) -> dict:
        return self.optimizer.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.optimizer.load_state_dict(state)
