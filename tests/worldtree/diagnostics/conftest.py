"""Shared fixtures for the diagnostics tests: every device this machine has."""

from __future__ import annotations

import pytest
import torch

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    """Each available device in turn (CPU always; CUDA where present)."""
    return torch.device(request.param)
