"""How OpenMP threads wait between parallel loops: a short spin, then sleep, unless the user chose.

Rule: when neither ``OMP_WAIT_POLICY`` nor ``GOMP_SPINCOUNT`` is set, the command-line entry points set
``OMP_WAIT_POLICY=PASSIVE`` and ``GOMP_SPINCOUNT=10000`` (GNU OpenMP, which PyTorch's Linux wheels use: about
0.1 ms of spinning before a waiting thread sleeps; other OpenMP runtimes read only the policy and sleep at
once). A variable the user set is never changed, and then neither is the other one.

Why both: a thread that sleeps at once costs a wake-up per parallel loop, about a millisecond on a virtual
machine whose idle cores halt, which halved the training speed of an idle 2-core machine; a thread that spins
for the runtime's default (about 3 ms) or for ever burns the cores other processes need when the machine is
shared. The short spin covers the gaps between the loops of one training step; sharing is handled by taking
torch's team down to one thread while anything else runs (:mod:`worldtree.infra.thread_governor`).
Measurements: docs/running.md, "Limits".

The variables are read once, when the OpenMP runtime starts (the first ``import torch``), so the entry points
call :func:`configure` before importing torch.
"""

from __future__ import annotations

import os
import sys
from collections.abc import MutableMapping

__all__ = ["SPINCOUNT", "choose", "configure"]

VARIABLE = "OMP_WAIT_POLICY"
SPIN_VARIABLE = "GOMP_SPINCOUNT"
SPINCOUNT = "10000"


def choose(environ: MutableMapping[str, str]) -> dict[str, str]:
    """The variables to set: both of the module's when ``environ`` has neither, none otherwise."""
    if VARIABLE in environ or SPIN_VARIABLE in environ:
        return {}
    return {VARIABLE: "PASSIVE", SPIN_VARIABLE: SPINCOUNT}


def configure(environ: MutableMapping[str, str] | None = None) -> dict[str, str] | None:
    """Set :func:`choose`'s variables for this process and its children, before torch is imported.

    Returns the variables set, or None when nothing was changed (the user chose, or torch is already imported
    so the runtime has read its settings)."""
    env = os.environ if environ is None else environ
    if "torch" in sys.modules:
        return None
    chosen = choose(env)
    env.update(chosen)
    return chosen or None
