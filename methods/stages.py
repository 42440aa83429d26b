"""A method as an explicit, ordered list of named stage functions over one typed state.

A stage is ``Stage(name, fn)`` with ``fn(state) -> None``: it reads what earlier stages left in the state and
adds its own results. :func:`run_stages` calls them in order, each timed by the method's
:class:`worldtree.infra.timing.StageClock` (reported as ``method_stats.stages_s`` in ``timing.json``; the run's own
clock times the method's whole ``fit`` as its ``train`` stage). An ablation replaces a stage by another of the same
name or removes it (:class:`Ablation`); the config names ablations in one place, its ``ablate`` tuple.
A run resumes at stage boundaries: a stage that trains checkpoints under the run's checkpoint folder and picks
up there, the others are cheap to repeat or cache their result (priors, BA).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from worldtree.infra.timing import StageClock


@dataclass(frozen=True)
class Stage:
    """One named step of a method."""

    name: str
    """Name in ``timing.json`` (``stages_s``) and in the method's stats."""
    run: Callable[[Any], None]
    """``run(state)``: reads and fills in the method's state."""


@dataclass(frozen=True)
class Ablation:
    """What ablating one name does: the stage called ``stage`` is replaced by ``replacement`` (None: removed)."""

    stage: str
    replacement: Stage | None = None


def with_ablations(
    stages: Sequence[Stage], ablations: Mapping[str, Ablation], ablate: Iterable[str]
) -> list[Stage]:
    """``stages`` with each ablation of ``ablate`` applied, in the order of ``ablations`` (a later one wins
    over an earlier one that touches the same stage). An unknown name is a ``KeyError`` (configs check names)."""
    chosen = set(ablate)
    unknown = chosen - set(ablations)
    if unknown:
        raise KeyError(f"no such ablation: {sorted(unknown)}")
    out = list(stages)
    for name, ab in ablations.items():
        if name not in chosen:
            continue
        idx = [i for i, st in enumerate(out) if st.name == ab.stage]
        for i in reversed(idx):
            if ab.replacement is None:
                del out[i]
            else:
                out[i] = ab.replacement
    return out


def run_stages(stages: Sequence[Stage], state: Any, clock: StageClock) -> None:
    """Call every stage on ``state`` in order, each inside ``clock.stage(name)``. A line on stderr marks each
    stage's start and end (with its wall seconds), so the log of an interrupted run shows where its time went."""
    for st in stages:
        print(f"stage {st.name} ...", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        with clock.stage(st.name):
            st.run(state)
        print(f"stage {st.name} done in {time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)
