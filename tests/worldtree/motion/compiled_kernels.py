"""Helpers for the tests of the compiled motion kernels: skip where the library does not build, and check that a
computation gives the same bits at several torch thread counts."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest
import torch


def require_kernel() -> None:
    """Skip the calling test, with the build's error as the reason, where the compiled library does not build."""
    from worldtree.render import cpu_kernel

    if not cpu_kernel.available():
        pytest.skip(f"the compiled kernel does not build here: {cpu_kernel.build_error()}")


def assert_same_bits_at_thread_counts(fn: Callable[[], list[Any]], counts: tuple[int, ...] = (1, 2)) -> None:
    """``fn()`` (a list of tensors) once at each torch thread count of ``counts`` gives equal tensors, bit for bit;
    the process's count is restored afterwards."""
    before = torch.get_num_threads()
    try:
        runs = []
        for n in counts:
            torch.set_num_threads(n)
            runs.append(fn())
    finally:
        torch.set_num_threads(before)
    for other in runs[1:]:
        for a, b in zip(runs[0], other, strict=True):
            assert torch.equal(a, b)
