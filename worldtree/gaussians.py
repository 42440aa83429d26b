"""The Gaussian set: raw trainable parameters, their activations, initialisation, save/load and PLY export.

Parameters are stored raw (unconstrained) and activated when read, as in 3D Gaussian Splatting:

    means          [N, 3]  world positions                     (identity)
    quats          [N, 4]  rotation (w, x, y, z), any norm      (normalised)
    log_scales     [N, 3]  log per-axis standard deviation      (exp -> world units)
    opacity_logits [N]     opacity before the sigmoid           (sigmoid -> [0, 1])
    sh0            [N, 3]  degree-0 spherical-harmonic colour   (rgb = SH_C0 * sh0 + 0.5, clamped at 0)
    shN            [N, K, 3] optional higher SH coefficients, K = (degree + 1)^2 - 1 (view-dependent colour)

Every tensor in :attr:`GaussianSet.params` has the Gaussian index as its first dimension, so the density
control in :mod:`worldtree.strategy` can grow and shrink all of them together; methods with more per-Gaussian
quantities (motion bases, reference times) add entries to the same dict.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
from torch import nn

from worldtree.infra.atomic import atomic_write_bytes
from worldtree.infra.errors import UserError
from worldtree.infra.torchfile import load_torch, save_torch
from worldtree.pixels import unit_float

# Degree-0 real spherical harmonic, 1 / (2 sqrt(pi)); the PLY files of 3DGS viewers use this convention.
SH_C0 = 0.28209479177387814

CORE_KEYS = ("means", "quats", "log_scales", "opacity_logits", "sh0")


def rgb_to_sh0(rgb: torch.Tensor) -> torch.Tensor:
    """Inverse of the degree-0 colour activation: ``[..., 3]`` RGB in [0, 1] -> SH DC coefficients."""
    return (rgb - 0.5) / SH_C0


def inverse_sigmoid(p: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """Logit of ``p`` clamped to ``[eps, 1 - eps]`` so that 0 and 1 stay finite."""
    p = p.clamp(eps, 1.0 - eps)
    return torch.log(p / (1.0 - p))


class GaussianSet(nn.Module):
    """A set of N 3D Gaussians with trainable raw parameters in :attr:`params` (a ``ParameterDict``).

    Construct it from tensors with :meth:`from_tensors`, from points with :meth:`from_points`, or random
    points in camera frustums with :meth:`random_in_frustums`.
    """

    def __init__(self, params: Mapping[str, torch.Tensor]):
        super().__init__()
        missing = [k for k in CORE_KEYS if k not in params]
        if missing:
            raise ValueError(f"GaussianSet needs parameters {missing}")
        n = params["means"].shape[0]
        for k, v in params.items():
            if v.shape[0] != n:
                raise ValueError(f"parameter {k!r} has {v.shape[0]} rows, means has {n}")
        self.params = nn.ParameterDict(
            {
                k: v if isinstance(v, nn.Parameter) else nn.Parameter(v.detach().clone())
                for k, v in params.items()
            }
        )

    # ------------------------------------------------------------------ activations
    def __len__(self) -> int:
        return int(self.params["means"].shape[0])

    @property
    def num(self) -> int:
        """Number of Gaussians N."""
        return len(self)

    @property
    def device(self) -> torch.device:
        return self.params["means"].device

    @property
    def means(self) -> torch.Tensor:
        """``[N, 3]`` world positions."""
        return self.params["means"]

    @property
    def quats(self) -> torch.Tensor:
        """``[N, 4]`` unit quaternions (w, x, y, z); a zero quaternion becomes the identity's direction."""
        q = self.params["quats"]
        return q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)

    @property
    def log_scales(self) -> torch.Tensor:
        """``[N, 3]`` log standard deviations (what the rasterizer takes)."""
        return self.params["log_scales"]

    @property
    def scales(self) -> torch.Tensor:
        """``[N, 3]`` per-axis standard deviations in world units."""
        return torch.exp(self.params["log_scales"])

    @property
    def opacities(self) -> torch.Tensor:
        """``[N]`` opacities in [0, 1]."""
        return torch.sigmoid(self.params["opacity_logits"])

    @property
    def colors(self) -> torch.Tensor:
        """``[N, 3]`` view-independent RGB from the degree-0 SH coefficient, clamped at 0 (3DGS keeps values
        above 1)."""
        return (SH_C0 * self.params["sh0"] + 0.5).clamp_min(0.0)

    @property
    def sh_degree(self) -> int:
        """Highest SH degree stored (0 without ``shN``)."""
        if "shN" not in self.params:
            return 0
        return round(math.sqrt(self.params["shN"].shape[1] + 1)) - 1

    def view_colors(self, cam_center: torch.Tensor, degree: int | None = None) -> torch.Tensor:
        """``[N, 3]`` RGB seen from ``cam_center [3]`` (world), using SH degrees up to ``degree`` (default:
        all stored); ``max(0, sum_k c_k Y_k(d) + 0.5)`` with ``d`` the unit direction camera -> Gaussian."""
        deg = self.sh_degree if degree is None else min(degree, self.sh_degree)
        if deg == 0:
            return self.colors
        d = self.params["means"] - cam_center.to(self.params["means"])
        d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        basis = sh_basis(d, deg)  # [N, (deg+1)^2]
        coeffs = torch.cat([self.params["sh0"][:, None], self.params["shN"][:, : basis.shape[1] - 1]], dim=1)
        return ((basis[..., None] * coeffs).sum(dim=1) + 0.5).clamp_min(0.0)

    def add_sh(self, degree: int) -> None:
        """Add zero ``shN`` coefficients up to ``degree`` (1..3) if the set has none."""
        if degree < 1 or "shN" in self.params:
            return
        if degree > 3:
            raise ValueError(f"SH degree {degree}: at most 3 is supported")
        k = (degree + 1) ** 2 - 1
        self.params["shN"] = nn.Parameter(torch.zeros(len(self), k, 3, device=self.device))

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_tensors(
        cls,
        means: torch.Tensor,
        scales: torch.Tensor,
        opacities: torch.Tensor,
        colors: torch.Tensor,
        quats: torch.Tensor | None = None,
    ) -> GaussianSet:
        """Build from activated values: means ``[N,3]``, scales ``[N,3]`` (std, > 0), opacities ``[N]`` in
        (0, 1), colours ``[N,3]`` RGB, quaternions ``[N,4]`` (identity when None)."""
        n = means.shape[0]
        if quats is None:
            quats = torch.zeros(n, 4, dtype=means.dtype, device=means.device)
            quats[:, 0] = 1.0
        return cls(
            {
                "means": means.float(),
                "quats": quats.float(),
                "log_scales": torch.log(scales.float().clamp_min(1e-12)),
                "opacity_logits": inverse_sigmoid(opacities.float()),
                "sh0": rgb_to_sh0(colors.float()),
            }
        )

    @classmethod
    def from_points(
        cls,
        points: torch.Tensor,
        colors: torch.Tensor | None = None,
        init_opacity: float = 0.1,
        scale_mult: float = 1.0,
    ) -> GaussianSet:
        """Isotropic Gaussians at ``points`` ``[N, 3]``, as 3DGS initialises from SfM points.

        Each scale is the root-mean-square distance to the 3 nearest other points (times ``scale_mult``);
        colours ``[N, 3]`` default to grey; rotations are the identity.
        """
        if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0:
            raise UserError(f"initial points have shape {tuple(points.shape)}; expected a non-empty [N, 3]")
        if not torch.isfinite(points).all():
            raise UserError("initial points contain NaN/Inf; clean the point cloud first")
        n = points.shape[0]
        dist = knn_rms_distance(points.detach().cpu().numpy(), k=3)
        scales = torch.from_numpy(dist).float().to(points.device)[:, None].expand(n, 3) * scale_mult
        if colors is None:
            colors = torch.full((n, 3), 0.5, device=points.device)
        opac = torch.full((n,), float(init_opacity), device=points.device)
        return cls.from_tensors(points, scales.contiguous(), opac, colors.clamp(0.0, 1.0))

    @classmethod
    def random_in_frustums(
        cls,
        num: int,
        Ks: torch.Tensor,
        w2cs: torch.Tensor,
        width: int,
        height: int,
        near: float,
        far: float,
        images: torch.Tensor | None = None,
        init_opacity: float = 0.1,
        generator: torch.Generator | None = None,
    ) -> GaussianSet:
        """``num`` Gaussians at random points inside the training cameras' near/far frustums (no depth used).

        Each point picks a training frame, a pixel and a depth uniform in inverse depth between ``near`` and
        ``far`` (so near content, which covers more pixels, gets more points) and is unprojected with that
        frame's ``Ks [T,3,3]`` and ``w2cs [T,4,4]``. Its colour is the frame's pixel from ``images
        [T,H,W,3]`` when given. Scales come from nearest-neighbour distances as in :meth:`from_points`.
        """
        if num < 1:
            raise UserError(f"init_num_points={num}: must be at least 1")
        if not (0 < near < far) or not math.isfinite(far):
            raise UserError(
                f"scene bounds near={near}, far={far}: need 0 < near < far < inf; fix cameras.json"
            )
        t = Ks.shape[0]
        cpu = torch.device("cpu")
        frame = torch.randint(0, t, (num,), generator=generator, device=cpu)
        u = torch.rand(num, generator=generator, device=cpu) * width
        v = torch.rand(num, generator=generator, device=cpu) * height
        s = torch.rand(num, generator=generator, device=cpu)
        depth = 1.0 / (1.0 / near + s * (1.0 / far - 1.0 / near))
        K = Ks.detach().to(cpu, torch.float64)[frame]
        w2c = w2cs.detach().to(cpu, torch.float64)[frame]
        # Pixel centres sit at integer coordinates in the OpenCV convention; u, v are continuous.
        x = (u.double() - 0.5 - K[:, 0, 2]) / K[:, 0, 0]
        y = (v.double() - 0.5 - K[:, 1, 2]) / K[:, 1, 1]
        cam = torch.stack([x, y, torch.ones_like(x)], -1) * depth.double()[:, None]
        R, tr = w2c[:, :3, :3], w2c[:, :3, 3]
        world = torch.einsum("nji,nj->ni", R, cam - tr)  # R^T (x_cam - t)
        if images is not None:
            px = u.long().clamp(0, width - 1)
            py = v.long().clamp(0, height - 1)
            colors = unit_float(images.detach().to(cpu)[frame, py, px])
        else:
            colors = None
        dev = Ks.device
        return cls.from_points(
            world.float().to(dev),
            None if colors is None else colors.to(dev),
            init_opacity=init_opacity,
        )

    # ------------------------------------------------------------------ persistence
    def save(self, path: str | Path) -> None:
        """Write the raw parameters to ``path`` (a ``torch.save`` dict of CPU tensors), atomically."""
        save_torch(path, {k: v.detach().cpu() for k, v in self.params.items()})

    @staticmethod
    def read_params(path: str | Path, device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
        """The parameter tensors of a file written by :meth:`save` (a clear error for a missing/corrupt file)."""
        return load_torch(
            path,
            device,
            missing="no such model file",
            unreadable="not a readable Gaussian model ({error}); re-run training",
        )

    @classmethod
    def load(cls, path: str | Path, device: torch.device | str = "cpu") -> GaussianSet:
        """Read a file written by :meth:`save`."""
        return cls(cls.read_params(path, device))

    def load_params(self, state: Mapping[str, torch.Tensor]) -> None:
        """Replace every parameter by ``state``'s (shapes may differ: density control changes N)."""
        for k, v in state.items():
            grad = self.params[k].requires_grad if k in self.params else True
            self.params[k] = nn.Parameter(v.detach().clone().to(self.device), requires_grad=grad)

    def write_ply(self, path: str | Path) -> None:
        """Export in the PLY layout read by common 3DGS viewers (binary little-endian, float32 fields
        x y z nx ny nz f_dc_0..2 [f_rest_*] opacity scale_0..2 rot_0..3, raw values)."""
        p = {k: v.detach().cpu().float().numpy() for k, v in self.params.items()}
        n = len(self)
        cols = [
            p["means"],
            np.zeros((n, 3), np.float32),
            p["sh0"],
            p["opacity_logits"][:, None],
            p["log_scales"],
            p["quats"],
        ]
        names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        if "shN" in p:
            # Channel-major like the 3DGS files: all red coefficients, then green, then blue.
            rest = p["shN"].transpose(0, 2, 1).reshape(n, -1)
            cols.insert(3, rest)
            names += [f"f_rest_{i}" for i in range(rest.shape[1])]
        names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
        data = np.ascontiguousarray(np.concatenate(cols, axis=1).astype("<f4"))
        header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {n}\n"
        header += "".join(f"property float {name}\n" for name in names) + "end_header\n"
        atomic_write_bytes(path, header.encode("ascii") + data.tobytes())


def read_ply_vertices(path: str | Path) -> dict[str, np.ndarray]:
    """Read the float32 vertex properties of a binary little-endian PLY as ``{name: [N]}`` (for tests/tools)."""
    raw = Path(path).read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    lines = raw[:end].decode("ascii").splitlines()
    n = next(int(line.split()[2]) for line in lines if line.startswith("element vertex"))
    names = [line.split()[2] for line in lines if line.startswith("property float")]
    arr = np.frombuffer(raw[end : end + 4 * n * len(names)], dtype="<f4").reshape(n, len(names))
    return {name: arr[:, i].copy() for i, name in enumerate(names)}


def knn_rms_distance(points: np.ndarray, k: int = 3) -> np.ndarray:
    """``[N]`` root-mean-square distance of each point ``[N, 3]`` to its ``k`` nearest other points.

    Duplicate points would give 0; a floor of 1e-7 keeps the log-scale finite. With N <= k the available
    neighbours are used; a single point gets 1e-2 (an arbitrary but finite size).
    """
    from scipy.spatial import cKDTree

    n = points.shape[0]
    if n == 1:
        return np.full(1, 1e-2)
    kk = min(k, n - 1)
    dist, _ = cKDTree(points).query(points, k=kk + 1)
    d = np.asarray(dist)[:, 1:]
    return np.sqrt(np.maximum((d**2).mean(axis=1), 1e-14))


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrices ``[..., 3, 3]`` of quaternions ``[..., 4]`` (w, x, y, z), normalised first."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(rows, -1).reshape(*q.shape[:-1], 3, 3)


# Real spherical-harmonic constants (the convention of the 3DGS PLY files).
_SH_C1 = 0.4886025119029199
_SH_C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
_SH_C3 = (
    -0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
    -0.4570457994644658, 1.445305721320277, -0.5900435899266435,
)  # fmt: skip


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """Real SH basis ``[..., (degree + 1)^2]`` at unit directions ``dirs [..., 3]``, degree 0..3."""
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-_SH_C1 * y, _SH_C1 * z, -_SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            _SH_C2[0] * x * y,
            _SH_C2[1] * y * z,
            _SH_C2[2] * (2 * zz - xx - yy),
            _SH_C2[3] * x * z,
            _SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            _SH_C3[0] * y * (3 * xx - yy),
            _SH_C3[1] * x * y * z,
            _SH_C3[2] * y * (4 * zz - xx - yy),
            _SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            _SH_C3[4] * x * (4 * zz - xx - yy),
            _SH_C3[5] * z * (xx - yy),
            _SH_C3[6] * x * (xx - 3 * yy),
        ]
    if degree > 3:
        raise ValueError(f"SH degree {degree}: at most 3 is supported")
    return torch.stack(out, dim=-1)
