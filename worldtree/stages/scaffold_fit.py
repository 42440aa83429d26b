"""Scaffold fit: refine the node trajectories against the lifted dynamic tracks before the photometric fit.

Each node of :func:`worldtree.motion.scaffold.build_scaffold` is one dynamic track; its trajectory starts as
the lifted track with gaps filled (linear in time, held at the ends). This stage minimises

    lambda_data * mean_{observed (t, m)} |x_m(t) - y_m(t)| / unit  +  motion regularisers (ARAP, vel, acc)

with Adam over node positions and rotations, so filled gaps and depth noise are smoothed by the ARAP,
velocity and acceleration terms while observed positions are kept (``unit`` = the scaffold's unit length).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from worldtree.infra import stop_request, thread_governor
from worldtree.motion.regularizers import MotionLossConfig, motion_losses
from worldtree.motion.scaffold import Scaffold
from worldtree.optim import adam_fused


@dataclass
class ScaffoldFitConfig:
    """Geometric scaffold fit settings (not given by the paper; MoSca runs a similar stage)."""

    steps: int = 1000
    """Adam steps (0 keeps the built trajectories)."""
    lr_pos: float = 1e-3
    """Node position learning rate, in scaffold units (times ``unit``)."""
    lr_quat: float = 1e-3
    """Node rotation learning rate."""
    lambda_data: float = 1.0
    """Weight of the distance to the observed (lifted) positions, in units."""
    motion: MotionLossConfig = field(default_factory=MotionLossConfig)
    """Regulariser weights."""


def fit_scaffold(
    scaffold: Scaffold, observed_pos: torch.Tensor, observed: torch.Tensor, cfg: ScaffoldFitConfig,
    on_log: Callable[[dict[str, float]], None] | None = None,
) -> list[dict[str, float]]:  # fmt: skip
    """Optimise ``scaffold.pos`` and ``scaffold.quat`` in place; returns the loss every 100 steps.

    Args:
        observed_pos: [T, M, 3] lifted positions of the nodes' tracks (anything where not observed).
        observed: [T, M] bool.
        on_log: called with each record of the returned list as it is made (progress: at 160 frames and
            480x270 the paper preset's 1,000 steps take minutes).
    """
    history: list[dict[str, float]] = []
    if scaffold.M == 0 or cfg.steps <= 0:
        return history
    unit = scaffold.unit
    opt = torch.optim.Adam(
        [{"params": [scaffold.pos], "lr": cfg.lr_pos * unit}, {"params": [scaffold.quat], "lr": cfg.lr_quat}],
        fused=adam_fused([scaffold.pos, scaffold.quat]),
    )
    target = observed_pos.detach().to(scaffold.pos)
    w = observed.to(scaffold.pos.dtype)
    graphs = scaffold.arap_graphs()
    for step in range(cfg.steps):
        stop_request.check()  # a stop whose exception was lost elsewhere (worldtree.infra.stop_request)
        thread_governor.tick()  # the torch team follows the free cores
        d = torch.sqrt(((scaffold.pos - target) ** 2).sum(-1) + 1e-12) / unit
        data = (d * w).sum() / w.sum().clamp_min(1.0)
        ml = motion_losses(scaffold.pos, scaffold.quat, graphs, cfg.motion)
        loss = cfg.lambda_data * data + ml.total
        if not torch.isfinite(loss):
            break
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if step % 100 == 0 or step == cfg.steps - 1:
            history.append(
                {"step": step, "data_units": float(data.detach()), "motion": float(ml.total.detach())}
            )
            if on_log is not None:
                on_log(history[-1])
    scaffold.pos.grad = None
    scaffold.quat.grad = None
    return history
