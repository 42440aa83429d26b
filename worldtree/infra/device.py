"""Pick the compute device at run time; nothing in the project hard-codes one."""

from __future__ import annotations

import torch

from worldtree.infra.errors import UserError


def pick_device(requested: str | None = None) -> torch.device:
    """Return ``requested`` ("cpu", "cuda", "cuda:1", "auto"/None) as a usable :class:`torch.device`.

    "auto" and None choose CUDA when available, else the CPU. Asking for CUDA on a machine without it is a
    :class:`UserError` rather than a late crash.
    """
    if requested in (None, "", "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(requested)
    except (RuntimeError, TypeError) as e:
        raise UserError(f"--device {requested!r} is not a device name; use auto, cpu, cuda or cuda:N") from e
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise UserError(f"--device {requested}: CUDA is not available on this machine; use --device cpu")
    return dev
