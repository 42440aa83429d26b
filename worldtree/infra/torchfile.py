"""Torch files: written atomically, read with ``weights_only=True`` and one-line errors.

Every ``.pt`` the toolkit writes (checkpoints, models, node states, BA results, the tree's context) goes through
these two functions, so a partial write never lands and a damaged or missing file is reported, not traced.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import torch

from worldtree.infra.atomic import atomic_write_bytes
from worldtree.infra.errors import UserError


def save_torch(path: str | Path, obj: Any) -> None:
    """``torch.save`` ``obj`` to ``path`` through a temporary file and a rename."""
    buf = io.BytesIO()
    torch.save(obj, buf)
    atomic_write_bytes(path, buf.getvalue())


def load_torch(path: str | Path, device: torch.device | str, *, missing: str, unreadable: str) -> Any:
    """Read a file written by :func:`save_torch` (tensors onto ``device``; plain data only).

    A missing file raises ``UserError("PATH: <missing>")``; one torch cannot read raises
    ``UserError("PATH: <unreadable>")`` with ``{error}`` in ``unreadable`` replaced by the exception's type.
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: {missing}")
    try:
        return torch.load(path, map_location=device, weights_only=True)
    except Exception as e:  # torch raises several types for damaged files
        raise UserError(f"{path}: {unreadable.format(error=type(e).__name__)}") from e
