"""A two-row rig and balls drawn as outline masks, for the object-depth tests (size + path)."""

from __future__ import annotations

import numpy as np
import torch

H, W = 90, 160
F = 120.0
K = torch.tensor([[F, 0.0, 79.5], [0.0, F, 44.5], [0.0, 0.0, 1.0]], dtype=torch.float64)
RADIUS = 0.12


def rig(T: int) -> torch.Tensor:
    """``[T, 4, 4]`` cameras of a two-row rig visited in a ping-pong order, looking along +z: they accelerate
    at every frame, which is what measures an object's depth scale."""
    out = []
    for t in range(T):
        k = t % 10
        cam = k if k < 6 else 10 - k
        w2c = torch.eye(4, dtype=torch.float64)
        w2c[:3, 3] = -torch.tensor([0.1 * cam - 0.25, 0.06 * (t % 2), 0.0], dtype=torch.float64)
        out.append(w2c)
    return torch.stack(out)


def straight_path(T: int) -> torch.Tensor:
    """World centres ``[T, 1, 3]`` of one ball moving at constant velocity in front of :func:`rig` (towards
    +x and away from it): the case whose depth size and path pin."""
    t = torch.arange(T, dtype=torch.float64)[:, None]
    start = torch.tensor([-0.3, 0.0, 1.6], dtype=torch.float64)
    return (start + t * torch.tensor([0.03, 0.004, 0.02], dtype=torch.float64))[:, None]


def draw(centres: torch.Tensor, w2cs: torch.Tensor) -> tuple[torch.Tensor, np.ndarray, np.ndarray]:
    """Outline masks ``[T, H, W]`` of balls of ``RADIUS`` at world ``centres`` [T, O, 3] (each a disc of
    radius ``F R / z`` at its projected centre), their centres' camera depths [T, O] and pixels [T, O, 2]."""
    T = centres.shape[0]
    cam = centres @ w2cs[:, :3, :3].transpose(1, 2) + w2cs[:, None, :3, 3]
    z = cam[..., 2]
    uv = cam[..., :2] / z[..., None] * F + K[:2, 2]
    v, u = np.mgrid[0:H, 0:W]
    masks = np.zeros((T, H, W), bool)
    for t in range(T):
        for o in range(centres.shape[1]):
            r = F * RADIUS / float(z[t, o])
            masks[t] |= (u - float(uv[t, o, 0])) ** 2 + (v - float(uv[t, o, 1])) ** 2 <= r * r
    return torch.from_numpy(masks), z.numpy(), uv.numpy()
