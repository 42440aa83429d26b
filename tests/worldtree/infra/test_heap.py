"""Freed tensors give their memory back to the system once released (glibc's heap keeps it otherwise)."""

from __future__ import annotations

import os
import sys

import pytest
import torch

from worldtree.infra.heap import release_freed_memory


def _rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/statm (Linux)")
def test_freed_frame_caches_leave_the_resident_size():
    first = torch.ones(3, 270, 480)
    del first  # glibc raises its mmap threshold past a freed block's size: later ones come from the heap
    release_freed_memory()
    before = _rss_mib()
    # Per-frame statistics as a fit caches them (1.5 MB each, ~300 MB), interleaved with small tensors that
    # stay alive, as the rest of a run's allocations do: the freed blocks sit below live ones in the heap.
    big, small = [], []
    for _ in range(200):
        big.append(torch.ones(3, 270, 480))
        small.append(torch.ones(64))
    grown = _rss_mib()
    assert grown - before > 250  # the cache was resident
    big.clear()
    if not release_freed_memory():
        pytest.skip("this C library has no malloc_trim")
    after = _rss_mib()
    assert after - before < 60, (before, grown, after)  # back within a small margin of the start
    del small
