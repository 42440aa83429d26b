"""Camera helpers shared by the stages: se(3) deltas on world-to-camera poses, centres, Sim(3) transforms.

Poses are OpenCV world-to-camera matrices ``w2c`` [..., 4, 4] (x right, y down, z forward). A pose delta is a
twist ``xi = (rho, omega)`` [..., 6] (translation first, rotation vector in radians, as
:func:`worldtree.motion.se3.exp`) applied on the camera side: ``w2c' = exp(xi) w2c``, so ``xi = 0`` is the
identity and ``omega`` rotates the camera about its own centre-independent axes.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from worldtree.motion import se3


def apply_delta(xi: torch.Tensor, w2c: torch.Tensor) -> torch.Tensor:
    """``exp(xi) @ w2c``: twists ``xi`` [..., 6] on poses ``w2c`` [..., 4, 4] -> [..., 4, 4] (differentiable)."""
    q, t = se3.exp(xi)
    return se3.to_matrix(q, t).to(w2c.dtype) @ w2c


def centres(w2c: torch.Tensor) -> torch.Tensor:
    """Camera centres ``-R^T t`` [..., 3] of poses ``w2c`` [..., 4, 4] (world units)."""
    R, t = w2c[..., :3, :3], w2c[..., :3, 3]
    return -(R.transpose(-1, -2) @ t[..., None])[..., 0]


def rotation_angle_deg(Ra: torch.Tensor, Rb: torch.Tensor) -> torch.Tensor:
    """Geodesic angle in degrees between rotation matrices ``Ra``, ``Rb`` [..., 3, 3]."""
    tr = (Ra.transpose(-1, -2) @ Rb).diagonal(dim1=-2, dim2=-1).sum(-1)
    return torch.rad2deg(torch.arccos(((tr - 1.0) / 2.0).clamp(-1.0, 1.0)))


@dataclass
class Sim3:
    """A similarity ``x -> scale * R x + t`` between two world frames (``R`` [3, 3], ``t`` [3])."""

    scale: float
    R: torch.Tensor
    t: torch.Tensor

    @staticmethod
    def identity(dtype=torch.float32, device: torch.device | str = "cpu") -> Sim3:
        return Sim3(1.0, torch.eye(3, dtype=dtype, device=device), torch.zeros(3, dtype=dtype, device=device))

    def apply_points(self, x: torch.Tensor) -> torch.Tensor:
        """Map points ``x`` [..., 3] from the source frame to the target frame."""
        return self.scale * x @ self.R.T.to(x) + self.t.to(x)

    def apply_w2c(self, w2c: torch.Tensor) -> torch.Tensor:
        """The same camera expressed in the target frame: ``w2c`` [..., 4, 4] -> [..., 4, 4].

        A camera with rotation ``Rc`` (world-to-camera) and centre ``c`` gets rotation ``Rc R^T`` and centre
        ``scale R c + t``; its image of mapped points is unchanged (depths are multiplied by ``scale``).
        """
        R = self.R.to(w2c)
        Rc = w2c[..., :3, :3] @ R.T
        c = self.apply_points(centres(w2c))
        out = torch.zeros_like(w2c)
        out[..., :3, :3] = Rc
        out[..., :3, 3] = -(Rc @ c[..., None])[..., 0]
        out[..., 3, 3] = 1.0
        return out

    def to_dict(self) -> dict:
        return {
            "scale": float(self.scale),
            "R": self.R.detach().cpu().tolist(),
            "t": self.t.detach().cpu().tolist(),
        }
