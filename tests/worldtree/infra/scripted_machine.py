"""A scripted machine for the thread governor's tests: a clock, the others' busy cores and this process's own CPU
use, read by a :class:`ThreadGovernor` instead of ``/proc/stat`` and the real clocks."""

from __future__ import annotations

from worldtree.infra import thread_governor as tg
from worldtree.infra.thread_governor import ThreadGovernor


class Machine:
    """``others`` busy cores besides this process, which uses ``own_rate`` of a core; ``threads`` is the thread
    count the governor sets unless it drives torch's own (``governor(torch_threads=True)``)."""

    def __init__(self, cores: int = 2):
        self.t, self.busy, self.own, self.others, self.own_rate = 0.0, 0, 0.0, 0.0, 1.0
        self.cores, self.threads = cores, cores

    def advance(self, seconds: float) -> None:
        self.t += seconds
        self.own += self.own_rate * seconds
        self.busy += round((self.others + self.own_rate) * seconds * tg._TICKS_PER_S)

    def stat(self) -> str:
        return f"cpu  {self.busy} 0 0 0 0 0 0 0 0 0\n"

    def governor(self, ceiling: int = 0, torch_threads: bool = False) -> ThreadGovernor:
        def set_threads(n: int) -> None:
            self.threads = n

        own = {} if torch_threads else {"get_threads": lambda: self.threads, "set_threads": set_threads}
        return ThreadGovernor(
            interval=1.0, cores=self.cores, cpus=None, read_stat=self.stat, own_cpu_s=lambda: self.own,
            clock=lambda: self.t, ceiling=ceiling, **own,
        )  # fmt: skip
