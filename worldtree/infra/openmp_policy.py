"""How OpenMP threads wait between parallel regions: sleep (``PASSIVE``) on an oversubscribed machine.

PyTorch's CPU operators and the C++ rasterizer run their parallel loops on OpenMP threads. Between two loops
GNU OpenMP's threads spin (busy-wait) for a while by default, which costs nothing on an idle machine but, when
more runnable processes than cores compete, burns the time slices the working threads need (measurements:
docs/running.md, "Limits").

The policy is read once, when the OpenMP runtime starts (the first ``import torch``), so the command-line entry
points call :func:`configure` before importing torch. A policy the user set is never changed.
"""

from __future__ import annotations

import os
import sys
from collections.abc import MutableMapping

__all__ = ["choose", "configure"]

VARIABLE = "OMP_WAIT_POLICY"


def choose(load_1min: float, cpus: int, environ: MutableMapping[str, str]) -> str | None:
    """``"PASSIVE"`` when the machine is oversubscribed (1-minute load average above the CPU count) and
    ``environ`` has no ``OMP_WAIT_POLICY``; None (keep the runtime's default) otherwise."""
    if VARIABLE in environ:
        return None
    return "PASSIVE" if float(load_1min) > max(int(cpus), 1) else None


def configure(environ: MutableMapping[str, str] | None = None) -> str | None:
    """Set ``OMP_WAIT_POLICY`` by :func:`choose` for this process and its children, before torch is imported.

    Returns the policy set, or None when nothing was changed (already set, torch already imported so the
    runtime has read it, or the load average cannot be read)."""
    env = os.environ if environ is None else environ
    if "torch" in sys.modules:
        return None
    try:
        load = os.getloadavg()[0]
    except OSError:
        return None
    policy = choose(load, os.cpu_count() or 1, env)
    if policy is not None:
        env[VARIABLE] = policy
    return policy
