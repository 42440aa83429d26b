"""Fixtures of the tree tests: small synthetic node states whose motion is known in closed form."""

from __future__ import annotations

import pytest
import torch

from worldtree.dynamic import DynamicGaussians
from worldtree.gaussians import GaussianSet
from worldtree.motion.scaffold import Scaffold, ScaffoldConfig
from worldtree.tree.node import NodeState
from worldtree.tree.tpt import Interval

VELOCITY = torch.tensor([0.01, -0.02, 0.005], dtype=torch.float64)
"""Every scaffold node translates by this much per frame (identity rotations)."""


def translating_scaffold(num_frames: int, num_nodes: int = 6, seed: int = 0) -> Scaffold:
    """Nodes on a 0.05-spaced line, all moving by VELOCITY per node-local frame; no identity mix, so a
    Gaussian moves by exactly ``(t - t_ref) * VELOCITY``."""
    g = torch.Generator().manual_seed(seed)
    base = torch.zeros(num_nodes, 3, dtype=torch.float64)
    base[:, 0] = torch.arange(num_nodes, dtype=torch.float64) * 0.05
    base = base + 0.001 * torch.randn(num_nodes, 3, generator=g, dtype=torch.float64)
    t = torch.arange(num_frames, dtype=torch.float64)
    pos = (base[None] + t[:, None, None] * VELOCITY).float()
    quat = torch.zeros(num_frames, num_nodes, 4)
    quat[..., 0] = 1.0
    cfg = ScaffoldConfig(mix_identity=False)
    return Scaffold(
        pos, quat, torch.zeros(num_nodes), torch.ones(num_frames, num_nodes, dtype=torch.bool), 1.0, cfg
    )


def make_state(index: int, interval: Interval, num_dynamic: int = 600, seed: int = 0) -> NodeState:
    """A node over ``interval``: t_ref cycling over its frames, means near the scaffold at t_ref, random
    opacities and colours, 50 static Gaussians and distinct camera poses per frame."""
    g = torch.Generator().manual_seed(seed)
    n = interval.length
    scf = translating_scaffold(n, seed=seed)
    t_ref = torch.arange(num_dynamic) % n
    anchor = scf.pos.detach()[t_ref, torch.arange(num_dynamic) % scf.M]
    means = anchor + 0.01 * torch.randn(num_dynamic, 3, generator=g)
    params = {
        "means": means,
        "quats": torch.nn.functional.normalize(torch.randn(num_dynamic, 4, generator=g), dim=-1),
        "log_scales": torch.full((num_dynamic, 3), -4.0),
        "opacity_logits": torch.randn(num_dynamic, generator=g) * 3.0,
        "sh0": torch.randn(num_dynamic, 3, generator=g),
        "t_ref": t_ref,
        "skin_corr": 0.01 * torch.randn(num_dynamic, scf.K, generator=g),
    }
    static = GaussianSet.from_tensors(
        torch.randn(50, 3, generator=g), torch.full((50, 3), 0.1), torch.rand(50, generator=g) * 0.9 + 0.05,
        torch.rand(50, 3, generator=g),
    )  # fmt: skip
    w2cs = torch.eye(4).repeat(n, 1, 1)
    w2cs[:, 0, 3] = torch.arange(interval.start, interval.end + 1, dtype=torch.float32)  # pose = global frame
    return NodeState(index, interval, scf, DynamicGaussians(params), static, w2cs)


@pytest.fixture
def root_state() -> NodeState:
    return make_state(1, Interval(0, 59))


@pytest.fixture
def node_factory():
    """``make_state(index, interval, num_dynamic=600, seed=0)``."""
    return make_state


@pytest.fixture
def velocity() -> torch.Tensor:
    return VELOCITY.float()
