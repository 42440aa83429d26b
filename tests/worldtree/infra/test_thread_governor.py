"""The thread governor: its rule in closed form, /proc/stat parsing, the loop on a scripted machine, and on
Linux a real busy process taking the team down to one thread."""

from __future__ import annotations

import subprocess
import sys
import time

import pytest

from tests.worldtree.infra.scripted_machine import Machine
from worldtree.infra import thread_governor as tg
from worldtree.infra.thread_governor import ThreadGovernor, busy_ticks, threads_for

STAT = """cpu  100 5 50 1000 7 3 2 40 11 0
cpu0 60 5 30 400 3 2 1 20 11 0
cpu1 40 0 20 600 4 1 1 20 0 0
intr 12345
ctxt 999
"""


def test_threads_for_keeps_a_thread_only_where_a_core_is_nearly_free():
    assert threads_for(2.0, 2) == 2  # nobody else
    assert threads_for(1.7, 2) == 2  # others use 0.3 of a core: under keep (0.6) of it
    assert threads_for(1.4, 2) == 1  # others use 0.6
    assert threads_for(1.0, 2) == 1
    assert threads_for(-3.0, 2) == 1  # never below one thread
    assert threads_for(16.0, 4) == 4  # never above the ceiling
    assert threads_for(12.5, 16) == 12
    assert threads_for(float("nan"), 8) == 1


def test_busy_ticks_counts_user_nice_system_irq_softirq_only():
    # aggregate line: 100 + 5 + 50 + 3 + 2 (idle 1000, iowait 7, steal 40 and guest 11 left out)
    assert busy_ticks(STAT, None) == 160
    assert busy_ticks(STAT, {0}) == 60 + 5 + 30 + 2 + 1
    assert busy_ticks(STAT, {0, 1}) == 98 + 62
    assert busy_ticks(STAT, {5}) is None  # none of the CPUs is listed
    assert busy_ticks("intr 1\n", None) is None


def test_the_team_drops_to_one_thread_while_others_run_and_comes_back():
    m = Machine()
    g = m.governor()
    assert g.tick() == 2 and g.ceiling == 2  # first sample: nothing measured yet
    m.others = 1.0  # another process takes a core
    m.advance(1.0)
    assert g.tick() == 1 and m.threads == 1
    m.others = 0.0  # it ends
    m.advance(0.5)
    assert g.tick() == 1  # under the interval: not checked again yet
    m.advance(0.6)
    assert g.tick() == 2 and m.threads == 2  # 1.1 s since the last check, nobody else
    rec = g.record()
    assert rec["ceiling"] == 2 and rec["changes"] == 2 and rec["seconds_at"] == {"1": 1.1, "2": 1.0}


def test_a_count_set_by_someone_else_becomes_the_ceiling():
    m = Machine(cores=4)
    g = m.governor()
    g.tick()
    m.threads = 1  # e.g. a tree's worker sets its share
    m.advance(1.0)
    assert g.tick() == 1 and g.ceiling == 1  # a free machine does not raise it above the count set


def test_a_worker_started_at_its_share_takes_the_cores_the_others_free():
    m = Machine()
    m.threads = 1  # one of two tree workers
    assert m.governor().ceiling == 1  # no ceiling given: the count it started with
    g = m.governor(ceiling=2)
    g.tick()
    m.others = 1.0  # the other worker
    m.advance(1.0)
    assert g.tick() == 1
    m.others = 0.0  # it is done
    m.advance(1.0)
    assert g.tick() == 2 and m.threads == 2


def test_no_proc_stat_changes_nothing():
    m = Machine()
    g = m.governor()
    g.read_stat = lambda: None
    m.others = 2.0
    for _ in range(3):
        m.advance(1.0)
        assert g.tick() == 2


def test_switched_off_by_the_environment():
    assert tg.enable({tg.ENV_SWITCH: "0"}) is False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the governor reads Linux's /proc/stat")
def test_a_busy_process_takes_the_team_down_to_one_thread():
    burner = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    threads = [2]
    try:
        g = ThreadGovernor(
            interval=0.3, cores=2, cpus=None, get_threads=lambda: threads[0],
            set_threads=lambda n: threads.__setitem__(0, n),
        )  # fmt: skip
        g.tick()
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and threads[0] != 1:
            time.sleep(0.05)  # this process idles: the busy core is someone else's
            g.tick()
    finally:
        burner.kill()
        burner.wait()
    assert threads[0] == 1
