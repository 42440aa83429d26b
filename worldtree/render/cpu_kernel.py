"""Compiled CPU backend: C++/OpenMP projection and tile compositing, backward by hand (csrc/rasterize_cpu.cpp).

The extension is built on first use (or ahead of time by :func:`prepare`) and cached; see
:mod:`worldtree.render.kernel_build` for the targets (``native``, ``avx2``, ``portable``), the cache key and the lock that
makes concurrent processes share one build. If no target builds (no compiler, no ninja), :func:`available`
returns False and the caller falls back to the PyTorch reference with one logged warning.
"""

from __future__ import annotations

import logging
import threading

import torch
from torch import Tensor

from worldtree.render import kernel_build

log = logging.getLogger("worldtree.render")

_lock = threading.Lock()
_module = None
_target: str | None = None
_seconds = 0.0
_error: str | None = None


def _describe(e: Exception) -> str:
    text = str(e).strip()
    return f"{type(e).__name__}: {text.splitlines()[-1] if text else ''}"


def _load():
    """The loaded build's ops (:class:`kernel_build.Ops`: forward, backward, project_forward, project_backward), or
    None when no target builds (reason in :func:`build_error`)."""
    global _module, _target, _seconds, _error
    with _lock:
        if _module is not None or _error is not None:
            return _module
        requested = kernel_build.requested_target()
        order = kernel_build.auto_order() if requested == "auto" else (requested,)
        errors = []
        for target in order:
            try:
                built = kernel_build.build(target)
            except Exception as e:  # compiler missing, ninja missing, build error: try the next target
                errors.append(f"{target}: {_describe(e)}")
                continue
            _module, _target, _seconds = built.module, built.target, built.seconds
            if errors:
                log.warning("C++ rasterizer: %s; using the %s build", "; ".join(errors), built.target)
            log.info("C++ rasterizer: %s build %s loaded in %.1f s", built.target, built.name, built.seconds)
            return _module
        _error = "; ".join(errors)
        log.warning("C++ rasterizer unavailable, using the PyTorch reference instead (%s)", _error)
        return None


def available() -> bool:
    """True when the compiled kernel is (or can now be) built and loaded."""
    return _load() is not None


def ops():
    """The loaded build's ops (``ops.forward``, ``ops.arap_forward``, ...), building it if needed; None when no
    target builds."""
    return _load()


def ops_for(*tensors):
    """:func:`ops` when every one of ``tensors`` is float32 on the CPU (the kernels' only dtype and device), else
    None (the caller's tensor version)."""
    if any(t.device.type != "cpu" or t.dtype != torch.float32 for t in tensors):
        return None
    return ops()


def build_error() -> str:
    """Why the build failed ('' when it did not)."""
    _load()
    return _error or ""


def loaded_target() -> str | None:
    """The target in use (one of ``kernel_build.TARGETS``), building it if needed; None when none builds."""
    _load()
    return _target


def prepare() -> tuple[str | None, float]:
    """Build (or load the cached build of) the kernel now, so that a later timed run does not pay for it.

    Returns (target or None when no target builds, seconds spent in this process building or loading).
    """
    _load()
    return _target, _seconds


def use_target(target: str) -> str | None:
    """Switch this process to ``target``'s build (building it if needed); returns the previous target.

    For tests and speed scripts that compare the two builds; raises what the build raises.
    """
    global _module, _target, _seconds, _error
    built = kernel_build.build(target)
    with _lock:
        previous = _target
        _module, _target, _seconds, _error = built.module, built.target, built.seconds, None
    return previous


class _RasterizeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, background, radii, width, height):
        mod = _load()
        threads = torch.get_num_threads()
        rgb, alpha, depth, final_T, last, _ids, tstart, tcount, recs, refs, gpos = mod.forward(
            means2d, conics, opacities, colors, depths, radii, background, width, height, threads
        )
        # The backward reads the Gaussians from the forward's packed records, not from the inputs.
        ctx.save_for_backward(background, recs, refs, gpos, tstart, tcount, final_T, last)
        ctx.size = (width, height, means2d.shape[0])
        return rgb, alpha, depth

    @staticmethod
    def backward(ctx, g_rgb, g_alpha, g_depth):
        background, recs, refs, gpos, tstart, tcount, final_T, last = ctx.saved_tensors
        width, height, n = ctx.size
        g_rgb = torch.zeros_like(final_T)[..., None].expand(-1, -1, 3) if g_rgb is None else g_rgb
        g_alpha = torch.zeros_like(final_T) if g_alpha is None else g_alpha
        g_depth = torch.zeros_like(final_T) if g_depth is None else g_depth
        g_m, g_con, g_o, g_col, g_z = _load().backward(
            recs,
            refs,
            gpos,
            tstart,
            tcount,
            background,
            final_T,
            last,
            g_rgb.contiguous(),
            g_alpha.contiguous(),
            g_depth.contiguous(),
            n,
            width,
            height,
            torch.get_num_threads(),
        )
        g_bg = (g_rgb * final_T[..., None]).sum((0, 1))
        return g_m, g_con, g_o, g_col, g_z, g_bg, None, None, None


class _ProjectCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, log_scales, w2c, K, keep, width, height, near, eps2d):
        means2d, conics, depths, radii = _load().project_forward(
            means, quats, log_scales, K, w2c, keep, width, height, near, eps2d, torch.get_num_threads()
        )
        ctx.save_for_backward(means, quats, log_scales, w2c, K, radii)
        ctx.args = (width, height, near, eps2d)
        ctx.mark_non_differentiable(radii)
        return means2d, conics, depths, radii

    @staticmethod
    def backward(ctx, g_m2d, g_con, g_z, _g_radii):
        means, quats, log_scales, w2c, K, radii = ctx.saved_tensors
        width, height, near, eps2d = ctx.args
        g_m2d = torch.zeros(means.shape[0], 2, dtype=means.dtype) if g_m2d is None else g_m2d.contiguous()
        g_con = torch.zeros(means.shape[0], 3, dtype=means.dtype) if g_con is None else g_con.contiguous()
        g_z = torch.zeros(means.shape[0], dtype=means.dtype) if g_z is None else g_z.contiguous()
        d_means, d_quats, d_ls, d_w2c = _load().project_backward(
            means, quats, log_scales, K, w2c, radii, g_m2d, g_con, g_z, width, height, near, eps2d,
            torch.get_num_threads(),
        )  # fmt: skip
        return d_means, d_quats, d_ls, d_w2c, None, None, None, None, None, None


def project_cpu(
    means: Tensor,
    quats: Tensor,
    log_scales: Tensor,
    K: Tensor,
    w2c: Tensor,
    width: int,
    height: int,
    near: float,
    eps2d: float,
    keep: Tensor,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """C++ version of :func:`worldtree.render.projection.project_gaussians` (same formulas, hand-written backward).

    Returns means2d [N, 2], conics [N, 3], depths [N], radii [N] int32; differentiable w.r.t. means, quats,
    log_scales and w2c. Computed in double internally, stored in the input dtype.
    """
    return _ProjectCPU.apply(
        means.contiguous(),
        quats.contiguous(),
        log_scales.contiguous(),
        w2c.contiguous(),
        K.detach().contiguous(),
        keep.contiguous(),
        int(width),
        int(height),
        float(near),
        float(eps2d),
    )


def rasterize_cpu(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    depths: Tensor,
    radii: Tensor,
    background: Tensor,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor, Tensor]:
    """Same contract as :func:`worldtree.render.reference.rasterize_reference`, computed by the C++ kernel."""
    return _RasterizeCPU.apply(
        means2d.contiguous(),
        conics.contiguous(),
        opacities.contiguous(),
        colors.contiguous(),
        depths.contiguous(),
        background.contiguous(),
        radii.to(torch.int32).contiguous(),
        int(width),
        int(height),
    )
