"""Shared random scenes for the rasterizer tests."""

from __future__ import annotations

import math

import pytest
import torch


def _make_scene(
    n=30, width=40, height=35, dtype=torch.float64, seed=0, spread=0.6, log_scale=-2.0, opacity_lo=0.2
):
    """N Gaussians in front of a camera looking down +z at a random small rotation; tensors require grad."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * spread
    means[:, 2] = means[:, 2] * 0.5 + 3.0
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    log_scales = torch.randn(n, 3, generator=g, dtype=dtype) * 0.4 + log_scale
    opacities = opacity_lo + (1 - opacity_lo) * torch.rand(n, generator=g, dtype=dtype)
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    f = 1.1 * width
    K = torch.tensor([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]], dtype=dtype)
    a = 0.05
    R = torch.tensor(
        [[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]], dtype=dtype
    ) @ torch.tensor([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]], dtype=dtype)
    w2c = torch.eye(4, dtype=dtype)
    w2c[:3, :3] = R
    w2c[:3, 3] = torch.tensor([0.05, -0.03, 0.1], dtype=dtype)
    background = torch.tensor([0.2, 0.5, 0.7], dtype=dtype)
    params = dict(
        means=means,
        quats=quats,
        log_scales=log_scales,
        opacities=opacities,
        colors=colors,
        K=K,
        w2c=w2c,
        background=background,
    )
    for k in ("means", "quats", "log_scales", "opacities", "colors", "w2c", "background"):
        params[k].requires_grad_(True)
    return params, width, height


@pytest.fixture
def make_scene():
    return _make_scene
