"""Torch's CPU thread count follows the cores that other processes leave free.

Rule: once :func:`enable` is called (the ``wtbench`` and ``nvls`` entry points do), every :func:`tick` (each
step of a training loop) checks, at most once per ``interval`` seconds, how busy this process's CPUs were since
the last check (``/proc/stat``, the CPUs of its affinity mask) against this process's own CPU time, and sets
torch's thread count to the cores the others left free: ``floor(cores - others + 1 - keep)`` clamped to
``[1, ceiling]``, ``ceiling`` being the count the process had when the governor started (a sweep's job, a
Slurm allocation or ``OMP_NUM_THREADS``; a count someone else sets later becomes the new ceiling, so code that
sets a count for a while uses :func:`threads_for_block`, which restores :func:`intended_threads`, not torch's
count, which may be one the governor lowered). With the
default ``keep`` of 0.6 a 2-core machine keeps both threads while others use under 0.4 of a core.

Why: OpenMP threads that sleep between parallel loops (``OMP_WAIT_POLICY=PASSIVE``) are safe on a shared
machine but can halve the speed of an idle one, where waking a sleeping core costs about a millisecond per
loop (a Firecracker VM: Base's photometric fit at 11.2 it/s against 22-26 spinning and 19.4 on one thread,
docs/running.md); threads that spin are fast alone but, sharing cores with another process, wait for a
descheduled partner (the same fit at 2.5-3.1 it/s). So the entry points let threads spin briefly
(:mod:`worldtree.infra.openmp_policy`) and this module takes the team down to one thread, which has no
partner to wait for, while anything else runs. Training results do not depend on the thread count (the
compiled kernels and PyTorch's deterministic mode are thread-count independent; tests check it), so a run
scores the same whatever the load was.

Off outside Linux (no ``/proc/stat``) and with ``WORLDTREE_THREAD_GOVERNOR=0``.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

from worldtree.infra.cores import available_cores

__all__ = [
    "ENV_SWITCH", "ThreadGovernor", "busy_ticks", "enable", "enabled", "intended_threads", "record", "threads_for",
    "threads_for_block", "tick",
]  # fmt: skip

ENV_SWITCH = "WORLDTREE_THREAD_GOVERNOR"
_TICKS_PER_S = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def threads_for(free_cores: float, ceiling: int, keep: float = 0.6) -> int:
    """Threads to run with when ``free_cores`` (cores minus the others' busy cores, may be negative or
    fractional) are left: ``floor(free_cores + 1 - keep)`` within ``[1, ceiling]``; a non-finite input gives
    ``ceiling``'s lower bound 1 (never more threads than measured room for)."""
    if not math.isfinite(free_cores):
        return 1
    return max(1, min(int(ceiling), math.floor(free_cores + 1.0 - keep)))


def busy_ticks(stat_text: str, cpus: set[int] | None) -> int | None:
    """Busy clock ticks (user, nice, system, irq, softirq; not idle, iowait or steal) summed over the
    ``cpuN`` lines of ``/proc/stat`` text whose N is in ``cpus`` (None: the aggregate ``cpu`` line); None when
    none of them is there. ``guest`` time is already inside ``user``."""
    total, seen = 0, False
    for line in stat_text.splitlines():
        if not line.startswith("cpu"):
            continue
        name, *fields = line.split()
        if cpus is None:
            if name != "cpu":
                continue
        elif name == "cpu" or int(name[3:]) not in cpus:
            continue
        v = [int(x) for x in fields[:8]] + [0] * max(0, 8 - len(fields))
        user, nice, system, _idle, _iowait, irq, softirq, _steal = v[:8]
        total += user + nice + system + irq + softirq
        seen = True
    return total if seen else None


def _read_stat() -> str | None:
    try:
        with open("/proc/stat") as f:
            return f.read()
    except OSError:
        return None


def _affinity() -> set[int] | None:
    try:
        return set(os.sched_getaffinity(0))
    except AttributeError:
        return None


@dataclass
class ThreadGovernor:
    """The rule of the module docstring, with injectable readers for tests.

    ``get_threads`` / ``set_threads`` default to torch's; ``read_stat`` returns ``/proc/stat``'s text (None:
    unavailable, the governor then does nothing); ``own_cpu_s`` this process's CPU seconds, all threads;
    ``clock`` a monotonic clock in seconds."""

    interval: float = 1.0
    keep: float = 0.6
    cores: int = field(default_factory=available_cores)
    cpus: set[int] | None = field(default_factory=_affinity)
    read_stat: Callable[[], str | None] = _read_stat
    own_cpu_s: Callable[[], float] = time.process_time
    clock: Callable[[], float] = time.monotonic
    get_threads: Callable[[], int] | None = None
    set_threads: Callable[[int], None] | None = None
    ceiling: int = 0
    current: int = 0
    seconds_at: dict[int, float] = field(default_factory=dict)
    changes: int = 0
    _last: tuple[float, int, float] | None = None

    def __post_init__(self) -> None:
        if self.get_threads is None or self.set_threads is None:
            import torch

            self.get_threads = self.get_threads or torch.get_num_threads
            self.set_threads = self.set_threads or torch.set_num_threads
        self.current = int(self.get_threads())
        # A ceiling given may be above the count it starts with (a tree's worker starts at its share).
        self.ceiling = max(int(self.ceiling), self.current)

    def _sample(self) -> tuple[float, int, float] | None:
        text = self.read_stat()
        busy = busy_ticks(text, self.cpus) if text is not None else None
        return None if busy is None else (self.clock(), busy, self.own_cpu_s())

    def tick(self) -> int:
        """Check the load when ``interval`` has passed since the last check; returns the thread count now."""
        now = self.clock()
        if self._last is not None and now - self._last[0] < self.interval:
            return self.current
        seen = int(self.get_threads())
        if seen != self.current:  # someone else set the count (a tree's workers, a sweep): it is the ceiling
            self.ceiling = self.current = seen
        sample = self._sample()
        if sample is None:
            return self.current
        if self._last is not None:
            wall = sample[0] - self._last[0]
            busy_s = (sample[1] - self._last[1]) / _TICKS_PER_S
            own_s = sample[2] - self._last[2]
            others = max(0.0, busy_s - own_s) / wall if wall > 0 else 0.0
            self.seconds_at[self.current] = self.seconds_at.get(self.current, 0.0) + max(wall, 0.0)
            want = threads_for(self.cores - others, self.ceiling, self.keep)
            if want != self.current:
                self.set_threads(want)
                self.current = want
                self.changes += 1
        self._last = sample
        return self.current

    def record(self) -> dict:
        """What the run's ``timing.json`` keeps: ceiling, changes and seconds spent at each thread count."""
        return {
            "ceiling": self.ceiling,
            "changes": self.changes,
            "seconds_at": {str(k): round(v, 1) for k, v in sorted(self.seconds_at.items())},
        }


_governor: ThreadGovernor | None = None
_enabled = False
_ceiling = 0


def enable(environ: dict[str, str] | None = None, ceiling: int = 0) -> bool:
    """Govern this process's threads from its next :func:`tick` on (idempotent; torch is imported then, not
    now); ``ceiling`` > 0 lets the count rise above the one the process starts with (a tree's worker, which
    starts at its share of the cores, may use them all once the other workers are done). False when switched
    off (``WORLDTREE_THREAD_GOVERNOR=0``) or without ``/proc/stat``."""
    global _enabled, _ceiling
    env = os.environ if environ is None else environ
    if env.get(ENV_SWITCH, "1").strip().lower() in ("0", "false", "off", "no"):
        return False
    _enabled = _enabled or _read_stat() is not None
    _ceiling = max(_ceiling, int(ceiling))
    return _enabled


def enabled() -> bool:
    """Whether :func:`enable` switched the governor on in this process."""
    return _enabled


def tick() -> None:
    """One step of a loop: re-check the load when due (a no-op unless :func:`enable` was called)."""
    global _governor
    if not _enabled:
        return
    if _governor is None:
        _governor = ThreadGovernor(ceiling=_ceiling)
    _governor.tick()


def intended_threads() -> int:
    """The thread count the process is meant to run with: the governor's ceiling once it governs, else torch's
    count now. Code that changes the count for a while restores this one (restoring torch's count as it found
    it would make a count the governor had lowered under load the new ceiling)."""
    if _governor is not None:
        return _governor.ceiling
    import torch

    return int(torch.get_num_threads())


@contextlib.contextmanager
def threads_for_block(n: int) -> Iterator[None]:
    """Run the block on ``n`` torch threads, then restore :func:`intended_threads` (read before the block)."""
    import torch

    before = intended_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def record() -> dict | None:
    """The governor's :meth:`ThreadGovernor.record`, or None when it is off."""
    return None if _governor is None else _governor.record()
