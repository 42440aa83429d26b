"""One clock for a run's stages: wall seconds per named stage over every session of a resumable run, and the
CPU seconds this process spent in each (``stages_cpu_s``: all its threads, not its worker processes).

A run interrupted and started again is one run: its time is the sum of its sessions. The clock keeps a ledger
(JSON) that it rewrites at every stage boundary and on the way out of a stage that raised (an interrupt
included), so a resumed session starts from the earlier sessions' totals; only a hard kill loses the time
since the last boundary.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from worldtree.infra.atomic import atomic_write_json

Clock = Callable[[], float]


def _seconds(v: Any) -> float:
    """A ledger entry as seconds; anything but a finite number >= 0 (a damaged ledger) counts as 0."""
    try:
        f = float(v)
    except (TypeError, ValueError):
        return 0.0
    return f if math.isfinite(f) and f >= 0 else 0.0


class StageClock:
    """Times named stages (:meth:`stage`) and parts reported from inside a stage (:meth:`add_part`).

    Args:
        ledger: JSON file carrying the totals across sessions (None: this session only).
        clock: seconds source (monotonic; tests pass a fake one).
        cpu_clock: CPU seconds source (default ``time.process_time``: this process, every thread; on a busy
            or shared machine the CPU time of a stage is what compares between runs, its wall time is not).
    """

    def __init__(
        self, ledger: str | Path | None = None, clock: Clock = time.perf_counter, cpu_clock: Clock = time.process_time
    ):
        self.clock = clock
        self.cpu_clock = cpu_clock
        self._start = clock()
        self.ledger: Path | None = None
        self.stages_s: dict[str, float] = {}
        self.stages_cpu_s: dict[str, float] = {}
        self.session_stages_s: dict[str, float] = {}
        self.parts_s: dict[str, float] = {}
        self.sessions_s: list[float] = [0.0]
        if ledger is not None:
            self.attach(ledger)

    def attach(self, ledger: str | Path) -> None:
        """Continue the sessions recorded in ``ledger`` (when it exists): their stage and part times are added
        to this session's, and this session is appended to theirs. From now on every flush rewrites it."""
        self.ledger = Path(ledger)
        prev = self._read()
        for key, mine in (("stages_s", self.stages_s), ("stages_cpu_s", self.stages_cpu_s), ("parts_s", self.parts_s)):
            old = prev.get(key)
            for k, v in (old.items() if isinstance(old, dict) else ()):
                mine[str(k)] = mine.get(str(k), 0.0) + _seconds(v)
        old_sessions = prev.get("sessions_s")
        self.sessions_s = [_seconds(v) for v in (old_sessions if isinstance(old_sessions, list) else [])]
        self.sessions_s.append(0.0)
        self.flush()

    def _read(self) -> dict[str, Any]:
        if self.ledger is None or not self.ledger.is_file():
            return {}
        try:
            d = json.loads(self.ledger.read_text())
        except (OSError, ValueError):
            return {}  # a damaged ledger only costs the earlier sessions' figures
        return d if isinstance(d, dict) else {}

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Time the block as stage ``name`` (a stage run twice, or in two sessions, adds up)."""
        t0, c0 = self.clock(), self.cpu_clock()
        try:
            yield
        finally:
            dt = max(self.clock() - t0, 0.0)
            self.stages_cpu_s[name] = self.stages_cpu_s.get(name, 0.0) + max(self.cpu_clock() - c0, 0.0)
            self.stages_s[name] = self.stages_s.get(name, 0.0) + dt
            self.session_stages_s[name] = self.session_stages_s.get(name, 0.0) + dt
            self.flush()

    def add_part(self, name: str, seconds: float) -> None:
        """Record ``seconds`` for a part inside a stage (``tree.layer1``, ``tree.node2``): shown, not added to
        the total (its stage already holds it)."""
        self.parts_s[name] = self.parts_s.get(name, 0.0) + float(seconds)

    def flush(self) -> None:
        """Bring this session's wall time up to now and rewrite the ledger."""
        self.sessions_s[-1] = max(self.clock() - self._start, 0.0)
        if self.ledger is not None:
            self.ledger.parent.mkdir(parents=True, exist_ok=True)
            atomic_write_json(self.ledger, self.record())

    @property
    def total_s(self) -> float:
        """Wall seconds of every session so far (this one up to the last :meth:`flush`)."""
        return float(sum(self.sessions_s))

    def record(self) -> dict[str, Any]:
        """``stages_s`` (all sessions), ``stages_s_this_session``, ``stages_cpu_s`` (all sessions), ``parts_s``,
        ``sessions_s``, ``total_s``."""
        return {
            "stages_s": dict(self.stages_s),
            "stages_cpu_s": dict(self.stages_cpu_s),
            "stages_s_this_session": dict(self.session_stages_s),
            "parts_s": dict(self.parts_s),
            "sessions_s": list(self.sessions_s),
            "total_s": self.total_s,
        }
