"""Pick the compute device at run time; nothing in the project hard-codes one."""

from __future__ import annotations

import torch

from worldtree.infra.errors import SettingError


def pick_device(requested: str | None = None) -> torch.device:
    """Return ``requested`` ("cpu", "cuda", "cuda:1", "auto"/None) as a usable :class:`torch.device`.

    "auto" and None choose CUDA when available, else the CPU. Asking for CUDA on a machine without it is a
    :class:`~worldtree.infra.errors.SettingError` rather than a late crash.
    """
    if requested in (None, "", "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(requested)
    except (RuntimeError, TypeError) as e:
        why = "not a device name; use auto, cpu, cuda or cuda:N"
        raise SettingError("device", repr(requested), why) from e
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise SettingError("device", requested, "CUDA is not available on this machine; use cpu")
    return dev
