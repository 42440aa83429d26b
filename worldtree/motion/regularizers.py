"""Motion regularisers on scaffold node trajectories: ARAP (coordinates and lengths), velocity, acceleration.

All terms take node positions ``pos`` [T, M, 3] (scene units) and rotations ``quat`` [T, M, 4] (w, x, y, z,
any norm) and return scalars that are finite, with finite gradients, for static nodes, M = 0, T = 1 and T = 2
(terms that need more frames than there are return 0). Formulas: ``docs/motion.md``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch.autograd.function import once_differentiable

from worldtree.motion import quaternion as Q
from worldtree.motion._safe import safe_norm
from worldtree.motion.scaffold import ArapGraph

__all__ = [
    "MotionLossConfig",
    "MotionLosses",
    "acceleration_losses",
    "arap_loss",
    "arap_loss_autograd",
    "frame_window",
    "local_coordinates",
    "motion_losses",
    "smoothness_losses",
    "velocity_losses",
]


@dataclass
class MotionLossConfig:
    """Weights of the motion regularisers (REFERENCE section 2) and the ARAP temporal shifts."""

    lambda_arap_coord: float = 0.3
    """ARAP local-coordinate term."""
    lambda_arap_len: float = 0.3
    """ARAP edge-length term."""
    lambda_vel_xyz: float = 5.0
    """Node translation speed."""
    lambda_vel_rot: float = 3.0
    """Node angular speed."""
    lambda_acc_xyz: float = 0.3
    """Node translational acceleration."""
    lambda_acc_rot: float = 0.3
    """Node angular acceleration."""
    arap_shifts: tuple[int, ...] = (2, 4)
    """ARAP compares frame t with frame t + shift for each shift."""
    arap_shift_weights: tuple[float, ...] = (0.5, 0.5)
    """Weight of each shift (REFERENCE gives the shifts only; equal weights are this project's choice)."""

    def __post_init__(self) -> None:
        if len(self.arap_shifts) != len(self.arap_shift_weights):
            raise ValueError("MotionLossConfig: arap_shifts and arap_shift_weights need equal lengths")
        if any(int(s) < 1 for s in self.arap_shifts):
            raise ValueError(f"MotionLossConfig: arap_shifts must be >= 1, got {self.arap_shifts}")
        self.arap_shifts = tuple(int(s) for s in self.arap_shifts)
        self.arap_shift_weights = tuple(float(w) for w in self.arap_shift_weights)


@dataclass
class MotionLosses:
    """Unweighted terms (scalar tensors) and their weighted sum ``total``."""

    arap_coord: torch.Tensor
    arap_len: torch.Tensor
    vel_xyz: torch.Tensor
    vel_rot: torch.Tensor
    acc_xyz: torch.Tensor
    acc_rot: torch.Tensor
    total: torch.Tensor

    def as_floats(self) -> dict[str, float]:
        """The terms as Python floats (for logs)."""
        return {k: float(getattr(self, k).detach()) for k in self.__dataclass_fields__}


def _mean(x: torch.Tensor) -> torch.Tensor:
    """Mean that is 0 (still attached to the graph) for an empty tensor, instead of NaN."""
    return x.sum() / max(x.numel(), 1)


def local_coordinates(
    pos: torch.Tensor, quat: torch.Tensor, nb_idx: torch.Tensor, detach_neighbours: bool = False
) -> torch.Tensor:
    """Each node's position in its neighbours' frames: ``R_j(t)^T (x_i(t) - x_j(t))`` -> [T, M, K, 3].

    ``pos`` [T, M, 3], ``quat`` [T, M, 4], ``nb_idx`` [M, K] (node j = ``nb_idx[i, k]``). With
    ``detach_neighbours`` the neighbours' positions and rotations carry no gradient.
    """
    # Rotation matrices once per node, then gathered per edge: far cheaper than rotating every edge vector
    # by its quaternion (two cross products per edge).
    R = Q.to_matrix(quat)  # [T, M, 3, 3]
    nb_pos, nb_R = pos[:, nb_idx], R[:, nb_idx]
    if detach_neighbours:
        nb_pos, nb_R = nb_pos.detach(), nb_R.detach()
    diff = pos[:, :, None, :] - nb_pos  # [T, M, K, 3]
    return (nb_R * diff[..., :, None]).sum(dim=-2)  # R^T d: component i = sum_j R_ji d_j


def arap_loss(
    pos: torch.Tensor,
    quat: torch.Tensor,
    graph: ArapGraph,
    shifts: tuple[int, ...] = (2, 4),
    shift_weights: tuple[float, ...] = (0.5, 0.5),
) -> tuple[torch.Tensor, torch.Tensor]:
    """As-rigid-as-possible terms over one graph: ``(coord, length)`` scalars (not yet multiplied by
    ``graph.weight``).

    With ``c_ik(t)`` the :func:`local_coordinates` and ``w_ik`` the edge validity normalised over each row,
    for each shift s (skipped when T <= s):
    ``coord += ws * mean_{t,i} sum_k w_ik |c_ik(t) - c_ik(t+s)|`` and
    ``length += ws * mean_{t,i} sum_k w_ik | |c_ik(t)| - |c_ik(t+s)| |``. Both vanish for rigid motion of
    each neighbourhood; the length term ignores the rotations. Norms use a guarded square root (gradient 0 at
    0), so coincident or static nodes are harmless.

    Computed by one autograd node with a hand-written backward over the ``[T, M, K]`` edges (the per-edge
    autograd graph of :func:`arap_loss_autograd`, the same formula, cost several times more on a CPU): on a
    CPU, float32, the compiled kernel (:class:`_ArapCompiled`, ``worldtree/render/csrc/arap_cpu.cpp``)
    when it builds, else :class:`_ArapTerms`; the rotation matrices are differentiated by autograd.
    """
    if len(shifts) != len(shift_weights):
        raise ValueError("arap_loss: shifts and shift_weights need equal lengths")
    if graph.idx.shape[1] == 0 or pos.shape[1] == 0:
        zero = pos.sum() * 0.0 + quat.sum() * 0.0
        return zero, zero
    return _arap_terms(pos, quat, Q.to_matrix(quat), graph, shifts, shift_weights)


def _arap_terms(
    pos: torch.Tensor, quat: torch.Tensor, R: torch.Tensor, graph: ArapGraph,
    shifts: tuple[int, ...], shift_weights: tuple[float, ...],
) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """:func:`arap_loss` of a non-empty graph given ``R = Q.to_matrix(quat)`` [T, M, 3, 3], which
    :func:`motion_losses` computes once for all its graphs."""
    w = graph.valid.to(pos.dtype)
    w = w / w.sum(dim=-1, keepdim=True).clamp(min=1e-12)  # rows with no valid edge contribute 0
    args = (pos, R, graph.idx, w, tuple(shifts), tuple(float(x) for x in shift_weights), graph.detach_neighbours)
    ops = _compiled_ops(pos)
    terms = _ArapCompiled.apply(*args, ops) if ops is not None else _ArapTerms.apply(*args)
    # Keep both inputs in the graph even when every shift is skipped (T <= s), as the autograd version does.
    zero = pos.sum() * 0.0 + quat.sum() * 0.0
    return terms[0] + zero, terms[1] + zero


def arap_loss_autograd(
    pos: torch.Tensor,
    quat: torch.Tensor,
    graph: ArapGraph,
    shifts: tuple[int, ...] = (2, 4),
    shift_weights: tuple[float, ...] = (0.5, 0.5),
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`arap_loss` written edge by edge with autograd (the reference its fused backward is tested
    against; slower)."""
    if len(shifts) != len(shift_weights):
        raise ValueError("arap_loss: shifts and shift_weights need equal lengths")
    zero = pos.sum() * 0.0 + quat.sum() * 0.0
    coord, length = zero, zero
    T = pos.shape[0]
    if graph.idx.shape[1] == 0 or pos.shape[1] == 0:
        return coord, length
    c = local_coordinates(pos, quat, graph.idx, graph.detach_neighbours)
    c_len = safe_norm(c)
    w = graph.valid.to(pos.dtype)
    w = w / w.sum(dim=-1, keepdim=True).clamp(min=1e-12)  # rows with no valid edge contribute 0
    for s, ws in zip(shifts, shift_weights, strict=True):
        if T <= s:
            continue
        d_coord = safe_norm(c[:-s] - c[s:])  # [T-s, M, K]
        d_len = (c_len[:-s] - c_len[s:]).abs()
        coord = coord + ws * _mean((d_coord * w).sum(-1))
        length = length + ws * _mean((d_len * w).sum(-1))
    return coord, length


def _norm3(v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(|v|, mask)`` over the leading axis of ``v`` [3, ...] as :func:`safe_norm` computes it (squared norm
    clamped at the smallest normal number), and where that clamp passes the gradient (as ``torch.clamp``)."""
    sq = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    tiny = torch.finfo(v.dtype).tiny
    return torch.sqrt(sq.clamp(min=tiny)), sq >= tiny


def _rotate_rows(R: torch.Tensor, v: torch.Tensor, transpose: bool) -> torch.Tensor:
    """``R^T v`` (``transpose``) or ``R v`` for component-major ``R`` [9, ...] (entry (a, b) at 3a + b) and
    ``v`` [3, ...] -> [3, ...], written into one buffer. Products and sums are rounded one by one in the
    order of ``(R * v).sum()`` over three terms (no fused multiply-add), as the edge-by-edge version."""
    out = torch.empty_like(v)
    tmp = torch.empty_like(v[0])
    for i in range(3):
        # R^T v: out_i = sum_a R_ai v_a; R v: out_i = sum_b R_ib v_b
        r0, r1, r2 = (R[3 * j + i] for j in range(3)) if transpose else (R[3 * i + j] for j in range(3))
        torch.mul(r0, v[0], out=out[i])
        out[i].add_(torch.mul(r1, v[1], out=tmp)).add_(torch.mul(r2, v[2], out=tmp))
    return out


class _ArapTerms(torch.autograd.Function):
    """``(coord, length)`` of :func:`arap_loss_autograd` from node positions ``pos`` [T, M, 3] and rotation
    matrices ``R`` [T, M, 3, 3]; ``idx`` [M, K] neighbours, ``w`` [M, K] normalised edge weights (constants).

    Gathers node-major (a neighbour's whole trajectory is one row: ``index_select`` forward, ``index_add``
    backward) and computes component-major (``[3, M, K, T]``; rotations ``[9, M, K, T]``), so that every
    elementwise product is between contiguous tensors of one shape: on a CPU several times faster than the
    strided broadcasts and advanced indexing of the edge-by-edge autograd graph."""

    @staticmethod
    def forward(ctx, pos, R, idx, w, shifts, shift_weights, detach_neighbours):
        T, M = pos.shape[:2]
        K = idx.shape[1]
        flat = idx.reshape(-1)
        # Node-major copies for the gathers (rows of 3T / 9T numbers), then component-major for the arithmetic.
        Pm = pos.detach().permute(1, 2, 0).contiguous()  # [M, 3, T]
        Rm = R.detach().permute(1, 2, 3, 0).reshape(M, 9, T)  # [M, 9, T]: entry (a, b) at 3a + b
        nb_R = Rm.index_select(0, flat).view(M, K, 9, T).permute(2, 0, 1, 3).contiguous()  # [9, M, K, T]
        nb_P = Pm.index_select(0, flat).view(M, K, 3, T).permute(2, 0, 1, 3)
        d = Pm.permute(1, 0, 2)[:, :, None, :] - nb_P  # [3, M, K, T]: x_i - x_j
        # c = R_j^T d: c_b = sum_a R_ab d_a
        c = _rotate_rows(nb_R, d, transpose=True)
        c_len, c_ok = _norm3(c)  # [M, K, T]
        coord = pos.new_zeros(())
        length = pos.new_zeros(())
        wk = w[:, :, None]  # [M, K, 1]
        saved = []
        for s, ws in zip(shifts, shift_weights, strict=True):
            if T <= s:
                continue
            e = c[..., :-s] - c[..., s:]
            n_e, ok_e = _norm3(e)
            d_len = c_len[..., :-s] - c_len[..., s:]
            den = max((T - s) * M, 1)
            coord = coord + ws * (n_e * wk).sum() / den
            length = length + ws * (d_len.abs() * wk).sum() / den
            saved.append((s, ws / den, e * (ok_e / n_e), torch.sign(d_len)))
        ctx.saved = saved
        ctx.detach_neighbours = detach_neighbours
        ctx.save_for_backward(idx, w, nb_R, d, c, c_len, c_ok)
        return coord, length

    @staticmethod
    @once_differentiable  # first derivatives only (nothing here needs second ones): an error, not a wrong value
    def backward(ctx, g_coord, g_len):
        idx, w, nb_R, d, c, c_len, c_ok = ctx.saved_tensors
        M, K, T = d.shape[1:]
        g_c = torch.zeros_like(c)
        g_l = torch.zeros_like(c_len)
        wk = w[:, :, None]  # [M, K, 1]
        for s, scale, unit_e, sign_len in ctx.saved:
            u = unit_e * ((g_coord * scale) * wk)
            g_c[..., :-s] += u
            g_c[..., s:] -= u
            v = sign_len * ((g_len * scale) * wk)
            g_l[..., :-s] += v
            g_l[..., s:] -= v
        g_c = g_c + c * (g_l * c_ok / c_len)
        # d c_b / d d_a = R_ab: g_d_a = sum_b R_ab g_c_b
        g_d = _rotate_rows(nb_R, g_c, transpose=False)
        g_P = g_d.sum(dim=2).permute(1, 0, 2)  # [M, 3, T]
        g_R = None
        flat = idx.reshape(-1)
        if not ctx.detach_neighbours:
            g_P = g_P.index_add(0, flat, g_d.permute(1, 2, 0, 3).reshape(M * K, 3, T), alpha=-1)
            if ctx.needs_input_grad[1]:
                g_nb_R = torch.empty((M, K, 9, T), dtype=c.dtype, device=c.device)
                for a in range(3):
                    for b in range(3):
                        torch.mul(d[a], g_c[b], out=g_nb_R[:, :, 3 * a + b])  # d c_b / d R_ab = d_a
                g_R = torch.zeros((M, 9, T), dtype=c.dtype, device=c.device)
                g_R = g_R.index_add(0, flat, g_nb_R.view(M * K, 9, T)).view(M, 3, 3, T).permute(3, 0, 1, 2)
        return g_P.permute(2, 0, 1), g_R, None, None, None, None, None


def _compiled_ops(*tensors: torch.Tensor):
    """The compiled kernels' ops when every tensor can use them (float32 on the CPU, kernel built), else None."""
    from worldtree.render import cpu_kernel  # the rasterizer's extension also holds the motion kernels

    return cpu_kernel.ops_for(*tensors)


class _ArapCompiled(torch.autograd.Function):
    """:class:`_ArapTerms` computed by the compiled kernel (``arap_forward`` / ``arap_backward``): each edge's
    trajectory is read once, every sum in double and in a fixed order (the same values for any thread count),
    nothing kept for the backward but the inputs. Takes ``R`` [T, M, 3, 3] as :class:`_ArapTerms` does and
    hands the kernel node-major copies ([M, T, 3], [M, T, 9]: each edge reads two contiguous trajectories)."""

    @staticmethod
    def forward(ctx, pos, R, idx, w, shifts, shift_weights, detach_neighbours, ops):
        T, M = pos.shape[:2]
        p = pos.detach().transpose(0, 1).contiguous()
        r = R.detach().reshape(T, M, 9).transpose(0, 1).contiguous()
        i = idx.to(torch.int64).contiguous()
        wc = w.detach().to(torch.float32).contiguous()
        threads = torch.get_num_threads()
        coord, length = ops.arap_forward(p, r, i, wc, list(shifts), list(shift_weights), threads)
        ctx.save_for_backward(p, r, i, wc)
        ctx.args = (list(shifts), list(shift_weights), bool(detach_neighbours), threads, ops)
        return coord, length

    @staticmethod
    @once_differentiable
    def backward(ctx, g_coord, g_len):
        p, r, i, wc = ctx.saved_tensors
        shifts, shift_weights, detach, threads, ops = ctx.args
        g_pos, g_R = ops.arap_backward(
            p, r, i, wc, shifts, shift_weights, float(g_coord), float(g_len), detach, threads
        )
        M, T = p.shape[:2]
        g_R = None if detach or not ctx.needs_input_grad[1] else g_R.view(M, T, 3, 3).transpose(0, 1)
        return g_pos.transpose(0, 1), g_R, None, None, None, None, None, None


def velocity_losses(pos: torch.Tensor, quat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(xyz, rot)``: mean node speed ``|x(t+1) - x(t)|`` (scene units per frame) and mean angular speed,
    the geodesic angle between ``q(t)`` and ``q(t+1)`` (radians per frame). 0 when T < 2."""
    if pos.shape[0] < 2:
        z = pos.sum() * 0.0 + quat.sum() * 0.0
        return z, z
    v_xyz = safe_norm(pos[1:] - pos[:-1])
    qc = Q.normalize(quat).movedim(-1, 0).contiguous()  # [4, T, M]: normalised once, components contiguous
    v_rot = Q.angle_between_components(qc[:, :-1], qc[:, 1:])
    return _mean(v_xyz), _mean(v_rot)


def acceleration_losses(pos: torch.Tensor, quat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(xyz, rot)``: mean ``|x(t+2) - 2 x(t+1) + x(t)|`` and mean angle between consecutive frame-to-frame
    rotations ``d(t) = q(t+1) q(t)^-1`` and ``d(t+1)`` (0 for a constant angular velocity, whatever the axis
    is). 0 when T < 3.

    MoSca measures the rotational acceleration as the change of the angular *speed* only; the angle between
    the increments also penalises changes of the rotation axis.
    """
    if pos.shape[0] < 3:
        z = pos.sum() * 0.0 + quat.sum() * 0.0
        return z, z
    a_xyz = safe_norm(pos[2:] - 2.0 * pos[1:-1] + pos[:-2])
    qc = Q.normalize(quat).movedim(-1, 0).contiguous()  # [4, T, M]
    conj = qc[:, :-1] * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=qc.dtype, device=qc.device)[:, None, None]
    d = Q.multiply_components(qc[:, 1:], conj)  # [4, T-1, M]
    a_rot = Q.angle_between_components(d[:, :-1], d[:, 1:])  # products of unit quaternions are unit
    return _mean(a_xyz), _mean(a_rot)


def smoothness_losses(
    pos: torch.Tensor, quat: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(v_xyz, v_rot, a_xyz, a_rot)``: :func:`velocity_losses` and :func:`acceleration_losses` of ``pos``
    [T, M, 3] and ``quat`` [T, M, 4] (0-d tensors; scene units and radians per frame, per frame squared).

    Float32 on the CPU takes the compiled kernel (:class:`_SmoothCompiled`, ``worldtree/render/csrc/
    smooth_cpu.cpp``) when it builds: each node's trajectory in one pass, in double, the same values for any
    thread count; anything else takes :func:`_smoothness_tensor`."""
    ops = _compiled_ops(pos, quat)
    if ops is None:
        return _smoothness_tensor(pos, quat)
    out = _SmoothCompiled.apply(pos, quat, ops)
    return out[0], out[1], out[2], out[3]


def _smoothness_tensor(pos: torch.Tensor, quat: torch.Tensor):
    """:func:`smoothness_losses` written with tensors (any device and dtype; the compiled kernel's reference)."""
    return (*velocity_losses(pos, quat), *acceleration_losses(pos, quat))


class _SmoothCompiled(torch.autograd.Function):
    """:func:`velocity_losses` and :func:`acceleration_losses` by the compiled kernel (``motion_smooth_forward``
    / ``motion_smooth_backward``) as one [4] tensor; only the inputs are kept for the backward."""

    @staticmethod
    def forward(ctx, pos, quat, ops):
        p, q = pos.detach().contiguous(), quat.detach().contiguous()
        threads = torch.get_num_threads()
        ctx.save_for_backward(p, q)
        ctx.args = (threads, ops)
        return ops.motion_smooth_forward(p, q, 1e-12, threads)  # eps: quaternion.normalize's

    @staticmethod
    @once_differentiable  # first derivatives only (nothing here needs second ones): an error, not a wrong value
    def backward(ctx, g):
        p, q = ctx.saved_tensors
        threads, ops = ctx.args
        g_pos, g_quat = ops.motion_smooth_backward(p, q, g.contiguous(), 1e-12, threads)
        return g_pos, g_quat, None


def motion_losses(
    pos: torch.Tensor, quat: torch.Tensor, graphs: list[ArapGraph], cfg: MotionLossConfig | None = None
) -> MotionLosses:
    """All motion regularisers of node trajectories ``pos`` [T, M, 3], ``quat`` [T, M, 4].

    ``graphs`` are ARAP graphs (e.g. :meth:`worldtree.motion.scaffold.Scaffold.arap_graphs`: the base graph
    and the multi-level ones); the ARAP terms are ``sum_g graph.weight * arap_loss(g)``. ``total`` is the
    sum of every term times its ``cfg.lambda_*``.
    """
    cfg = cfg or MotionLossConfig()
    zero = pos.sum() * 0.0 + quat.sum() * 0.0
    coord, length = zero, zero
    R = Q.to_matrix(quat) if any(g.idx.shape[1] and pos.shape[1] for g in graphs) else None
    for g in graphs:
        if R is None or g.idx.shape[1] == 0:
            continue  # an empty graph adds 0 (``zero`` keeps both inputs in the graph)
        gc, gl = _arap_terms(pos, quat, R, g, cfg.arap_shifts, cfg.arap_shift_weights)
        coord = coord + g.weight * gc
        length = length + g.weight * gl
    v_xyz, v_rot, a_xyz, a_rot = smoothness_losses(pos, quat)
    total = (
        cfg.lambda_arap_coord * coord
        + cfg.lambda_arap_len * length
        + cfg.lambda_vel_xyz * v_xyz
        + cfg.lambda_vel_rot * v_rot
        + cfg.lambda_acc_xyz * a_xyz
        + cfg.lambda_acc_rot * a_rot
    )
    return MotionLosses(coord, length, v_xyz, v_rot, a_xyz, a_rot, total)


def frame_window(frames: int, size: int, seed: int, step: int) -> slice:
    """The consecutive frames a step's motion terms see: ``size`` of ``frames``, at a start drawn from
    ``(seed, step)`` alone, so a resumed fit repeats it; every frame when ``size`` is 0 or covers the video.

    Every motion term is a mean over frames, so a window's value estimates the full one at a cost that does
    not grow with the video; frames within ``size`` of either end are drawn a little less often.
    """
    if size <= 0 or size >= frames:
        return slice(None)
    g = torch.Generator().manual_seed(int(seed) * 1_000_003 + int(step))
    a = int(torch.randint(0, frames - size + 1, (1,), generator=g))
    return slice(a, a + size)
