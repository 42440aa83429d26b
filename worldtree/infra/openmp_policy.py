"""How OpenMP threads wait between parallel regions: sleep (``PASSIVE``) unless the user chose otherwise.

PyTorch's CPU operators and the C++ rasterizer run their parallel loops on OpenMP threads. Between two loops
GNU OpenMP's threads spin (busy-wait) for a while by default, which costs nothing on an idle machine but, when
more runnable processes than cores compete, burns the time slices the working threads need (measurements:
docs/running.md, "Limits"). Jobs started together see no load at start-up, so the policy does not depend
on it: threads sleep whatever the load (one run alone is as fast either way, same docs).

The policy is read once, when the OpenMP runtime starts (the first ``import torch``), so the command-line entry
points call :func:`configure` before importing torch. A policy the user set is never changed.
"""

from __future__ import annotations

import os
import sys
from collections.abc import MutableMapping

__all__ = ["choose", "configure"]

VARIABLE = "OMP_WAIT_POLICY"


def choose(environ: MutableMapping[str, str]) -> str | None:
    """``"PASSIVE"`` when ``environ`` has no ``OMP_WAIT_POLICY``; None (the user's setting stands) otherwise."""
    return None if VARIABLE in environ else "PASSIVE"


def configure(environ: MutableMapping[str, str] | None = None) -> str | None:
    """Set ``OMP_WAIT_POLICY`` by :func:`choose` for this process and its children, before torch is imported.

    Returns the policy set, or None when nothing was changed (already set, or torch already imported so the
    runtime has read it)."""
    env = os.environ if environ is None else environ
    if "torch" in sys.modules:
        return None
    policy = choose(env)
    if policy is not None:
        env[VARIABLE] = policy
    return policy
