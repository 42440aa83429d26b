"""Backend selection for :func:`worldtree.render.rasterize`; the choice is logged once per device type."""

from __future__ import annotations

import logging

import torch

from worldtree.infra.errors import UserError

log = logging.getLogger("worldtree.render")

BACKENDS = ("auto", "cpu", "reference", "gsplat")
_logged: set[tuple[str, str]] = set()


def gsplat_available() -> bool:
    """True when the optional gsplat package imports (it only runs on CUDA)."""
    try:
        import gsplat  # noqa: F401
    except Exception:  # gsplat may fail at import time for many reasons (no nvcc, ABI mismatch)
        return False
    return True


def resolve_backend(backend: str, device: torch.device, dtype: torch.dtype = torch.float32) -> str:
    """Map the requested backend name to the one that will run on ``device``: "cpu", "reference" or "gsplat".

    "auto": CUDA -> gsplat when importable and the dtype is float32, else reference; CPU -> the compiled kernel, else (no compiler,
    failed build) the reference with one logged warning. A forced backend that cannot run raises UserError.
    """
    from worldtree.render import cpu_kernel

    if backend not in BACKENDS:
        raise UserError(f"rasterizer backend {backend!r} is unknown; use one of {', '.join(BACKENDS)}")
    if backend == "auto":
        if device.type == "cuda":
            chosen = "gsplat" if dtype == torch.float32 and gsplat_available() else "reference"
        elif device.type == "cpu":
            chosen = "cpu" if cpu_kernel.available() else "reference"
        else:
            chosen = "reference"
    else:
        chosen = backend
        if backend == "cpu":
            if device.type != "cpu":
                raise UserError(
                    f"rasterizer backend 'cpu' needs CPU tensors, got {device}; use backend='auto'"
                )
            if not cpu_kernel.available():
                raise UserError(
                    f"rasterizer backend 'cpu': the C++ kernel did not build ({cpu_kernel.build_error()}); "
                    "install a C++ compiler and ninja, or use backend='reference'"
                )
        elif backend == "gsplat" and (
            device.type != "cuda" or dtype != torch.float32 or not gsplat_available()
        ):
            raise UserError(
                "rasterizer backend 'gsplat' needs float32 CUDA tensors and the gsplat package "
                "(pip install 'worldtree-bench[cuda]'); use backend='auto'"
            )
    key = (device.type, chosen)
    if key not in _logged:
        _logged.add(key)
        log.info("rasterizer backend on %s: %s (requested %s)", device.type, chosen, backend)
    return chosen
