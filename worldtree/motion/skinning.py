"""Skinning of Gaussians to motion-scaffold nodes: KNN lookup, skinning weights and DQB deformation.

Nodes carry a pose per frame (position [T, M, 3], rotation [T, M, 4] (w, x, y, z)) and a radius ``sigma``
[M] in scene units. A Gaussian at reference time t_ref with mean ``x`` follows its K nearest nodes ``n_k``:

    w_k   = exp(-|x - n_k(t_ref)|^2 / (2 sigma_k^2)) + 1e-6   (+ learned correction; 0 where masked)
    T(t)  = DQB_k(w_k, T_k(t) T_k(t_ref)^-1)                  (see dualquat.blend, identity mix included)
    x(t)  = T(t) x,   rot(t) = q_T(t) rot

Everything is differentiable in PyTorch with respect to the points, node poses, ``sigma`` and the correction;
the neighbour indices are integers and carry no gradient. On a CPU in float32, :func:`deform_dual_planes` (the
scaffold's one-frame path) and :func:`relative_dual` (the table of node motions it blends) run compiled kernels
with hand-written backwards instead of the autograd graph.
"""

from __future__ import annotations

import torch
from torch.autograd.function import once_differentiable

from worldtree.motion import dualquat, se3

__all__ = [
    "deform",
    "deform_dual_neighbours",
    "deform_dual_planes",
    "deform_neighbours",
    "gather_frames",
    "gather_planes",
    "knn",
    "normalize_weights",
    "relative_dual",
    "skinning_weights",
]

WEIGHT_FLOOR = 1e-6
"""Added to every unmasked Gaussian kernel value (MoSca), so a point never has all-zero raw weights."""


def knn(
    query: torch.Tensor, ref: torch.Tensor, k: int, chunk_size: int = 4096
) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``k`` nearest ``ref`` points of each query point, nearest first.

    Args:
        query: [..., 3] points (e.g. Gaussian means at the reference time).
        ref: [M, 3] points (e.g. node positions at the reference time).
        k: neighbours wanted; clamped to M (so M < k gives M columns and M = 0 gives none).
        chunk_size: query rows per ``torch.cdist`` call, bounding memory at ``chunk_size * M`` distances.

    Returns:
        ``(idx, dist2)``: [..., min(k, M)] int64 indices into ``ref`` and the squared distances, recomputed
        exactly from the coordinates (``cdist`` may use a matrix product, which is only good for ranking).
    """
    if ref.dim() != 2 or ref.shape[-1] != 3 or query.shape[-1] != 3:
        raise ValueError(
            f"knn: expected query [..., 3] and ref [M, 3], got {tuple(query.shape)}, {tuple(ref.shape)}"
        )
    if k < 0 or chunk_size < 1:
        raise ValueError(f"knn: k must be >= 0 and chunk_size >= 1, got k={k}, chunk_size={chunk_size}")
    k = min(k, ref.shape[0])
    flat = query.reshape(-1, 3)
    idx = torch.empty((flat.shape[0], k), dtype=torch.long, device=query.device)
    if k > 0:
        with torch.no_grad():
            ref_d = ref.detach()
            for start in range(0, flat.shape[0], chunk_size):
                block = flat[start : start + chunk_size].detach()
                dist = torch.cdist(block, ref_d)
                idx[start : start + chunk_size] = torch.topk(
                    dist, k, dim=-1, largest=False, sorted=True
                ).indices
    idx = idx.reshape(*query.shape[:-1], k)
    diff = query[..., None, :] - ref[idx]
    return idx, (diff * diff).sum(-1)


def skinning_weights(
    points: torch.Tensor,
    nb_pos: torch.Tensor,
    nb_sigma: torch.Tensor,
    valid: torch.Tensor | None = None,
    correction: torch.Tensor | None = None,
    min_sigma: float = 1e-8,
) -> torch.Tensor:
    """Raw (unnormalised) skinning weights [..., K] of points to their K neighbour nodes.

    Args:
        points: [..., 3] positions at the reference time.
        nb_pos: [..., K, 3] neighbour node positions at the same time.
        nb_sigma: [..., K] node radii (scene units); ``sigma`` is floored at ``min_sigma`` (a zero radius
            gives a kernel of 1 at the node and 0 elsewhere, with finite gradients).
        valid: [..., K] bool mask (e.g. graph edges or padded neighbours); False gives weight 0.
        correction: [..., K] learned additive correction, added before masking and normalisation; the
            corrected weight is floored at 0.

    Returns:
        ``exp(-d^2 / (2 sigma^2)) + 1e-6`` (``max(0, ... + correction)`` with a correction), zero where masked. Normalise with
        :func:`normalize_weights`, or pass to :func:`worldtree.motion.dualquat.blend` which does it.
    """
    diff = points[..., None, :] - nb_pos
    return _weights_of_sq_dist((diff * diff).sum(-1), nb_sigma, valid, correction, min_sigma)


def _weights_of_sq_dist(d2, nb_sigma, valid, correction, min_sigma: float = 1e-8) -> torch.Tensor:
    """:func:`skinning_weights` from the squared distances ``d2`` [..., K] (shared by both neighbour layouts)."""
    var2 = 2.0 * nb_sigma.clamp(min=min_sigma) ** 2
    w = torch.exp(-d2 / var2) + WEIGHT_FLOOR  # exponent <= 0: underflows to 0, never overflows
    if correction is not None:
        # A negative weight would make the blend ill-posed (weights cancelling): floor the sum at 0, which
        # drops that neighbour (its gradient is 0 until the correction rises again).
        w = (w + correction).clamp(min=0.0)
    if valid is not None:
        w = torch.where(valid, w, torch.zeros_like(w))
    return w


def normalize_weights(weights: torch.Tensor, eps: float = 1e-12) -> tuple[torch.Tensor, torch.Tensor]:
    """``(weights / W, W)`` with ``W = sum_k weights`` [...]; the division uses ``max(W, eps)``."""
    w_sum = weights.sum(-1)
    return weights / w_sum.clamp(min=eps)[..., None], w_sum


def gather_frames(traj: torch.Tensor, frame: torch.Tensor, knn_idx: torch.Tensor) -> torch.Tensor:
    """Per-neighbour values ``traj[frame, knn_idx]`` [..., K, C] for items with their own frame.

    ``traj`` [T, M, C] (node positions or rotations over time), ``frame`` [...] int frame per item (e.g. each
    Gaussian's reference frame), ``knn_idx`` [..., K]. Use it to build the inputs of
    :func:`deform_neighbours` when Gaussians have different reference times.

    Equals ``traj[frame[..., None], knn_idx]``; computed as one ``index_select`` of rows of the flattened
    ``[T * M, C]`` table, whose backward (``index_add``) a CPU runs several times faster than the accumulating
    ``index_put`` of advanced indexing.
    """
    T, M = traj.shape[:2]
    lin = frame[..., None] * M + knn_idx  # [..., K] row of (frame, node) in the flattened table
    flat = traj.reshape(T * M, *traj.shape[2:]).index_select(0, lin.reshape(-1))
    return flat.view(*lin.shape, *traj.shape[2:])


def gather_planes(traj: torch.Tensor, frame: torch.Tensor, knn_idx: torch.Tensor) -> torch.Tensor:
    """:func:`gather_frames` laid out component-major: ``[C, N, K]`` with ``out[c, n, k] = traj[frame[n],
    knn_idx[n, k], c]`` (``traj`` [T, M, C], ``frame`` [N], ``knn_idx`` [N, K])."""
    T, M, C = traj.shape
    lin = (frame[:, None] * M + knn_idx).reshape(-1)
    planes = traj.reshape(T * M, C).t().contiguous()  # [C, T * M]
    return planes.index_select(1, lin).view(C, *knn_idx.shape)


def relative_dual(
    q_t: torch.Tensor, p_t: torch.Tensor, q_ref: torch.Tensor, p_ref: torch.Tensor, eps: float = 1e-12
) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit dual quaternions ``(real, dual)`` [..., 4] of the node motions ``T(t) T(t_ref)^-1``: the poses at the
    target frame (``q_t`` [..., 4] any norm, ``p_t`` [..., 3] scene units) and at the reference frames (``q_ref``,
    ``p_ref``); leading shapes broadcast. :func:`worldtree.motion.se3.relative` then
    :func:`worldtree.motion.dualquat.from_quat_trans`, guards included (a quaternion with ``|q| <= eps`` is the
    identity, with zero gradient).

    Float32 on the CPU takes the compiled kernel (:class:`_RelativeCompiled`,
    ``worldtree/render/csrc/relative_cpu.cpp``) when it builds: each entry in one pass, in double, rounded once;
    anything else takes :func:`_relative_dual_tensor`.
    """
    shape = torch.broadcast_shapes(q_t.shape[:-1], p_t.shape[:-1], q_ref.shape[:-1], p_ref.shape[:-1])
    ops = _relative_ops(q_t, p_t, q_ref, p_ref)
    if ops is None or len(shape) == 0:
        return _relative_dual_tensor(q_t, p_t, q_ref, p_ref, eps)
    # Broadcast inputs are expanded here, so that autograd's expand backward sums their gradients.
    flat = [x.expand(*shape, x.shape[-1]).reshape(-1, x.shape[-1]) for x in (q_t, p_t, q_ref, p_ref)]
    real, dual = _RelativeCompiled.apply(*flat, float(eps), ops)
    return real.view(*shape, 4), dual.view(*shape, 4)


def _relative_dual_tensor(q_t, p_t, q_ref, p_ref, eps: float = 1e-12) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`relative_dual` written with tensors (any device and dtype; the compiled kernel's reference)."""
    q_rel, t_rel = se3.relative(q_t, p_t, q_ref, p_ref)
    return dualquat.from_quat_trans(q_rel, t_rel)


def _relative_ops(*xs: torch.Tensor):
    """The compiled kernel's ops when every input is a float32 CPU tensor and the kernel builds, else None."""
    from worldtree.render import cpu_kernel  # the rasterizer's extension also holds the motion kernels

    return cpu_kernel.ops_for(*xs)


class _RelativeCompiled(torch.autograd.Function):
    """:func:`_relative_dual_tensor` on ``[U, C]`` inputs computed by the compiled kernel
    (``relative_dual_forward`` / ``relative_dual_backward``); only the inputs are saved (the backward recomputes
    each entry). Every value is per entry, so the results are the same for any thread count."""

    @staticmethod
    def forward(ctx, q_t, p_t, q_ref, p_ref, eps, ops):
        ins = [x.detach().contiguous() for x in (q_t, p_t, q_ref, p_ref)]
        threads = torch.get_num_threads()
        real, dual = ops.relative_dual_forward(*ins, eps, threads)
        ctx.save_for_backward(*ins)
        ctx.args = (eps, threads, ops)
        return real, dual

    @staticmethod
    @once_differentiable  # first derivatives only (nothing here needs second ones): an error, not a wrong value
    def backward(ctx, g_real, g_dual):
        ins = ctx.saved_tensors
        eps, threads, ops = ctx.args
        g_real = torch.zeros_like(ins[0]) if g_real is None else g_real.contiguous()
        g_dual = torch.zeros_like(ins[0]) if g_dual is None else g_dual.contiguous()
        grads = ops.relative_dual_backward(*ins, g_real, g_dual, eps, threads)
        need = ctx.needs_input_grad[:4]
        return (*(g if n else None for g, n in zip(grads, need, strict=True)), None, None)


def deform_dual_planes(
    points: torch.Tensor,
    quats: torch.Tensor,
    nb_pos_ref: torch.Tensor,
    nb_sigma: torch.Tensor,
    nb_real: torch.Tensor,
    nb_dual: torch.Tensor,
    valid: torch.Tensor | None = None,
    correction: torch.Tensor | None = None,
    mix_identity: bool = True,
    eps: float = 1e-12,
    degenerate_tol: float = 1e-6,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`deform_dual_neighbours` with the neighbour inputs component-major: ``nb_pos_ref`` [3, N, K],
    ``nb_real, nb_dual`` [4, N, K] (:func:`gather_planes`); ``points`` [N, 3], ``quats`` [N, 4], ``nb_sigma``,
    ``valid``, ``correction`` [N, K] as there. Same formulas, guards and results.

    Float32 on the CPU (every tensor; K >= 1) takes the compiled kernel (:class:`_DeformCompiled`,
    ``worldtree/render/csrc/skinning_cpu.cpp``) when it builds: one pass per Gaussian, forward and a hand-written
    backward, results within float32 rounding of :func:`_deform_dual_planes_tensor` (the weights and the discrete
    choices in float32 as there, the blend in double). Anything else (CUDA, float64, no build) takes the tensor
    version. Both show a NaN that reaches the blend in the outputs.
    """
    ops = _compiled_ops(points, quats, nb_pos_ref, nb_sigma, nb_real, nb_dual, valid, correction)
    if ops is not None:
        return _DeformCompiled.apply(
            points,
            quats,
            nb_pos_ref,
            nb_sigma,
            nb_real,
            nb_dual,
            correction,
            valid,
            bool(mix_identity),
            float(eps),
            float(degenerate_tol),
            ops,
        )
    return _deform_dual_planes_tensor(
        points, quats, nb_pos_ref, nb_sigma, nb_real, nb_dual, valid, correction, mix_identity, eps, degenerate_tol
    )


def _compiled_ops(points, quats, nb_pos_ref, nb_sigma, nb_real, nb_dual, valid, correction):
    """The compiled kernel's ops when these inputs can use them (float32 CPU tensors of the documented shapes,
    K >= 1, kernel built), else None."""
    floats = [points, quats, nb_pos_ref, nb_sigma, nb_real, nb_dual]
    if correction is not None:
        floats.append(correction)
    if points.dim() != 2 or points.shape[1] != 3 or nb_sigma.dim() != 2:
        return None
    n, k = points.shape[0], nb_sigma.shape[1]
    if k == 0 or nb_sigma.shape[0] != n or quats.shape != (n, 4):
        return None  # K = 0: the tensor version's error (argmax over no neighbour)
    if nb_pos_ref.shape != (3, n, k) or nb_real.shape != (4, n, k) or nb_dual.shape != (4, n, k):
        return None
    for mask in (valid, correction):
        if mask is not None and mask.shape != (n, k):
            return None
    if valid is not None and (valid.dtype != torch.bool or valid.device.type != "cpu"):
        return None
    from worldtree.render import cpu_kernel  # the rasterizer's extension also holds the skinning kernel

    return cpu_kernel.ops_for(*floats)


class _DeformCompiled(torch.autograd.Function):
    """:func:`_deform_dual_planes_tensor` computed by the compiled kernel (``dqb_forward`` / ``dqb_backward``):
    each Gaussian and its K neighbours in one pass, nothing saved for the backward but the inputs (it recomputes
    the blend). Every value is per Gaussian, so the results are the same for any thread count."""

    @staticmethod
    def forward(
        ctx, points, quats, nb_pos_ref, nb_sigma, nb_real, nb_dual, correction, valid, mix, eps, tol, ops
    ):
        empty = points.new_empty(0)
        ins = [x.detach().contiguous() for x in (points, quats, nb_pos_ref, nb_sigma, nb_real, nb_dual)]
        corr = empty if correction is None else correction.detach().contiguous()
        mask = empty.bool() if valid is None else valid.contiguous()
        flags = (valid is not None, correction is not None, mix, eps, tol)
        threads = torch.get_num_threads()
        points_t, quats_t = ops.dqb_forward(*ins, mask, corr, *flags, threads)
        ctx.save_for_backward(*ins, mask, corr)
        ctx.args = (flags, threads, ops)
        return points_t, quats_t

    @staticmethod
    @once_differentiable  # first derivatives only (nothing here needs second ones): an error, not a wrong value
    def backward(ctx, g_points, g_quats):
        *ins, mask, corr = ctx.saved_tensors
        flags, threads, ops = ctx.args
        # Bit i: the gradient of the i-th input (points, quats, nb_pos_ref, nb_sigma, nb_real, nb_dual, correction).
        needs = sum(1 << i for i, need in enumerate(ctx.needs_input_grad[:7]) if need)
        grads = ops.dqb_backward(
            *ins, mask, corr, *flags, g_points.contiguous(), g_quats.contiguous(), needs, threads
        )
        out = [g if (needs >> i) & 1 else None for i, g in enumerate(grads)]
        return (*out, None, None, None, None, None)


def _deform_dual_planes_tensor(
    points: torch.Tensor,
    quats: torch.Tensor,
    nb_pos_ref: torch.Tensor,
    nb_sigma: torch.Tensor,
    nb_real: torch.Tensor,
    nb_dual: torch.Tensor,
    valid: torch.Tensor | None = None,
    correction: torch.Tensor | None = None,
    mix_identity: bool = True,
    eps: float = 1e-12,
    degenerate_tol: float = 1e-6,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`deform_dual_planes` written with tensors (any device and dtype; the compiled kernel's reference).
    Same formulas, guards and results as :func:`deform_dual_neighbours` (the per-neighbour products and sums
    round as there): every per-(Gaussian, neighbour) operation is then between contiguous ``[N, K]`` planes, which
    a CPU runs several times faster than the ``[N, K, 4]`` broadcasts of the other layout."""
    # Skinning weights (:func:`skinning_weights`).
    diff = points.t()[:, :, None] - nb_pos_ref  # [3, N, K]
    d2 = diff[0] * diff[0] + diff[1] * diff[1] + diff[2] * diff[2]
    w = _weights_of_sq_dist(d2, nb_sigma, valid, correction)
    # Dual-quaternion blend (:func:`worldtree.motion.dualquat.blend_dual`), transforms aligned with the pivot.
    n = points.shape[0]
    pivot = w.argmax(dim=-1)[None, :, None]  # [1, N, 1]
    piv_real = torch.gather(nb_real, 2, pivot.expand(4, n, 1))[..., 0]  # [4, N]
    piv_dual = torch.gather(nb_dual, 2, pivot.expand(4, n, 1))[..., 0]
    piv_sign = torch.where(piv_real[0] < 0, -1.0, 1.0).to(nb_real.dtype)  # [N]
    piv_real, piv_dual = piv_real * piv_sign, piv_dual * piv_sign
    dot = (
        nb_real[0] * piv_real[0, :, None]
        + nb_real[1] * piv_real[1, :, None]
        + nb_real[2] * piv_real[2, :, None]
        + nb_real[3] * piv_real[3, :, None]
    )
    sign = torch.where(dot < 0, -1.0, 1.0).to(nb_real.dtype)  # [N, K]
    w_sum = w.sum(dim=-1)  # [N]
    coef = w / w_sum.clamp(min=eps)[:, None]
    b_real = ((nb_real * sign) * coef).sum(dim=-1)  # [4, N]
    b_dual = ((nb_dual * sign) * coef).sum(dim=-1)
    if mix_identity:
        alpha = w_sum.clamp(0.0, 1.0)
        b_real = alpha * b_real + (1.0 - alpha) * torch.tensor(
            [1.0, 0.0, 0.0, 0.0], dtype=b_real.dtype, device=b_real.device
        )[:, None]
        b_dual = alpha * b_dual
    b_real, b_dual = b_real.t(), b_dual.t()  # [N, 4]: per Gaussian from here on
    degenerate = (b_real * b_real).sum(-1, keepdim=True) < degenerate_tol**2
    b_real = torch.where(degenerate, piv_real.t(), b_real)
    b_dual = torch.where(degenerate, piv_dual.t(), b_dual)
    q_b, t_b = dualquat.to_quat_trans(b_real, b_dual, eps)
    # The normalisation's guard (|b_real|^2 > eps^2) is false for a NaN and would put the identity in its place,
    # hiding a NaN node or weight: 0 * |b_real|^2 (NaN there, exactly 0 where it is finite, gradient 0) shows it.
    nan = (b_real * b_real).sum(-1, keepdim=True) * 0.0
    q_b, t_b = q_b + nan, t_b + nan
    return dualquat.apply_points(q_b, t_b, points), dualquat.apply_rotations(q_b, quats)


def deform_neighbours(
    points: torch.Tensor,
    quats: torch.Tensor,
    nb_pos_ref: torch.Tensor,
    nb_sigma: torch.Tensor,
    nb_q_rel: torch.Tensor,
    nb_t_rel: torch.Tensor,
    valid: torch.Tensor | None = None,
    correction: torch.Tensor | None = None,
    mix_identity: bool = True,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Deform points and orientations by DQB of their neighbours' relative transforms (gathered form).

    Args:
        points: [..., 3] Gaussian means at the reference time.
        quats: [..., 4] Gaussian rotations (w, x, y, z), any norm (kept).
        nb_pos_ref: [..., K, 3] neighbour node positions at the reference time (for the weights).
        nb_sigma: [..., K] neighbour radii.
        nb_q_rel, nb_t_rel: [..., K, 4], [..., K, 3] relative transforms ``T_k(t) T_k(t_ref)^-1``
            (:func:`worldtree.motion.se3.relative`).
        valid, correction: see :func:`skinning_weights`.
        mix_identity: see :func:`worldtree.motion.dualquat.blend`.

    Returns:
        ``(points_t [..., 3], quats_t [..., 4])``.
    """
    real, dual = dualquat.from_quat_trans(nb_q_rel, nb_t_rel)
    return _deform_dual(points, quats, nb_pos_ref, nb_sigma, real, dual, valid, correction, mix_identity)


def deform_dual_neighbours(
    points: torch.Tensor,
    quats: torch.Tensor,
    nb_pos_ref: torch.Tensor,
    nb_sigma: torch.Tensor,
    nb_real: torch.Tensor,
    nb_dual: torch.Tensor,
    valid: torch.Tensor | None = None,
    correction: torch.Tensor | None = None,
    mix_identity: bool = True,
) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`deform_neighbours` with the relative transforms already given as unit dual quaternions
    ``nb_real, nb_dual`` [..., K, 4] (:func:`worldtree.motion.dualquat.from_quat_trans`), so a caller can
    convert each node's motion once and gather the results per Gaussian."""
    return _deform_dual(points, quats, nb_pos_ref, nb_sigma, nb_real, nb_dual, valid, correction, mix_identity)


def _deform_dual(points, quats, nb_pos_ref, nb_sigma, nb_real, nb_dual, valid, correction, mix_identity):
    """Shared tail of the deform functions, with neighbour transforms as dual quaternions [..., K, 4]."""
    w = skinning_weights(points, nb_pos_ref, nb_sigma, valid, correction)
    q_b, t_b = dualquat.blend_dual(nb_real, nb_dual, w, mix_identity=mix_identity)
    return dualquat.apply_points(q_b, t_b, points), dualquat.apply_rotations(q_b, quats)


def deform(
    points: torch.Tensor,
    quats: torch.Tensor,
    node_pos_ref: torch.Tensor,
    node_quat_ref: torch.Tensor,
    node_pos_t: torch.Tensor,
    node_quat_t: torch.Tensor,
    sigma: torch.Tensor,
    knn_idx: torch.Tensor,
    valid: torch.Tensor | None = None,
    correction: torch.Tensor | None = None,
    mix_identity: bool = True,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Move Gaussians that share one reference time to time t.

    Args:
        points: [..., 3] Gaussian means at the reference time (scene units).
        quats: [..., 4] Gaussian rotations at the reference time, any norm (the norm is kept).
        node_pos_ref, node_quat_ref: [M, 3], [M, 4] node poses at the reference time (quats any norm).
        node_pos_t, node_quat_t: [M, 3], [M, 4] node poses at the target time.
        sigma: [M] node radii (scene units).
        knn_idx: [..., K] int64 node indices per Gaussian (:func:`knn`).
        valid: [..., K] bool neighbour mask; correction: [..., K] learned weight correction.
        mix_identity: blend with the identity by ``clamp(sum of raw weights, 0, 1)`` (default, MoSca).

    Returns:
        ``(points_t [..., 3], quats_t [..., 4])``. With K = 0 (no nodes) the inputs come back unchanged.
    """
    # Convert once per node, then gather per (Gaussian, neighbour): M conversions instead of N * K.
    real, dual = dualquat.from_quat_trans(*se3.relative(node_quat_t, node_pos_t, node_quat_ref, node_pos_ref))
    return _deform_dual(
        points,
        quats,
        node_pos_ref[knn_idx],
        sigma[knn_idx],
        real[knn_idx],
        dual[knn_idx],
        valid,
        correction,
        mix_identity,
    )
