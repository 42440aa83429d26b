"""How many CPU cores this process may run on (its affinity mask, not the machine's count)."""

from __future__ import annotations

import os


def available_cores() -> int:
    """CPU cores this process may run on (>= 1): a Slurm or taskset allocation, not the whole machine."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)
