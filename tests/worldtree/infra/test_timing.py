"""The run's clock (worldtree.infra.timing.StageClock) with a fake clock: stages, parts, sessions across an
interruption, and the wall time `wtbench table` reports from the resulting timing.json."""

from __future__ import annotations

import json

import pytest

from benchmarks.reporting.results import cost_metrics, stage_times
from worldtree.infra.timing import StageClock


class FakeClock:
    """Seconds that move only when a test says so."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


# The WorldTree run of the issue (timing.json, seconds): the trainer's own wall time (116 s) was reported
# as the train stage, while the stages took 559 s.
RECORDED = {"priors": 9, "ba": 3, "sw": 67, "scaffold": 2, "photometric": 111, "tree": 306, "test_pose": 61}


def _run_stages(clock: StageClock, fake: FakeClock, stages: dict[str, float], gap: float = 0.0) -> None:
    for name, secs in stages.items():
        fake.now += gap  # time between stages belongs to the session, not to a stage
        with clock.stage(name):
            fake.now += secs


def test_stages_add_up_and_the_session_covers_the_gaps():
    fake = FakeClock()
    clock = StageClock(clock=fake)
    _run_stages(clock, fake, RECORDED, gap=0.5)
    with clock.stage("ba"):  # a stage run twice adds up
        fake.now += 1.0
    clock.add_part("tree.layer1", 100.0)
    clock.flush()
    rec = clock.record()
    assert rec["stages_s"] == {**RECORDED, "ba": 4.0}
    assert rec["parts_s"] == {"tree.layer1": 100.0}
    assert rec["sessions_s"] == [sum(RECORDED.values()) + 1.0 + 0.5 * len(RECORDED)]
    assert rec["total_s"] == rec["sessions_s"][0]


def test_an_interrupted_run_counts_every_session(tmp_path):
    ledger = tmp_path / "checkpoints" / "timing_sessions.json"
    fake = FakeClock()
    first = StageClock(clock=fake)
    with first.stage("load"):
        fake.now += 2.0
    first.attach(ledger)  # the run folder exists from here on
    with pytest.raises(KeyboardInterrupt):
        with first.stage("photometric"):
            fake.now += 50.0
            raise KeyboardInterrupt  # Ctrl-C inside a stage: its time so far is still written
    fake.now += 7.0  # lost: after the last write, before the process ends

    # The ledger on disk is what the interrupted session left behind.
    on_disk = json.loads(ledger.read_text())
    assert on_disk["stages_s"] == {"load": 2.0, "photometric": 50.0} and on_disk["sessions_s"] == [52.0]

    second = StageClock(clock=fake)
    with second.stage("load"):
        fake.now += 2.0
    second.attach(ledger)
    _run_stages(second, fake, {"photometric": 61.0, "tree": 306.0, "eval": 5.0})
    second.flush()
    rec = second.record()
    assert rec["sessions_s"] == [52.0, 2.0 + 61.0 + 306.0 + 5.0]
    assert rec["stages_s"] == {"load": 4.0, "photometric": 111.0, "tree": 306.0, "eval": 5.0}
    assert rec["stages_s_this_session"] == {"load": 2.0, "photometric": 61.0, "tree": 306.0, "eval": 5.0}
    assert rec["total_s"] == pytest.approx(52.0 + 374.0)
    # What the tables report: every session's wall time, less the scoring.
    timing = {**rec, "train": {"wall_s_all_sessions": 111.0}}
    assert cost_metrics(timing, None)["wall_time_s"] == pytest.approx(52.0 + 374.0 - 5.0)
    assert stage_times(timing)["stage_s:photometric"] == 111.0


def test_the_recorded_run_reports_its_stages_not_the_trainer_loop():
    fake = FakeClock()
    clock = StageClock(clock=fake)
    _run_stages(clock, fake, {"load": 1.0, **RECORDED, "render": 4.0, "eval": 9.0})
    clock.flush()
    timing = {**clock.record(), "train": {"wall_s_all_sessions": 116.0}}
    assert cost_metrics(timing, None)["wall_time_s"] == pytest.approx(1.0 + sum(RECORDED.values()) + 4.0)


def test_a_damaged_ledger_only_loses_the_earlier_sessions(tmp_path):
    ledger = tmp_path / "t.json"
    ledger.write_text('{"stages_s": {"ba": "x", "sw": -3, "tree": 4}, "sessions_s": [1, NaN, "y"]}')
    fake = FakeClock()
    clock = StageClock(ledger, clock=fake)
    assert clock.stages_s == {"ba": 0.0, "sw": 0.0, "tree": 4.0} and clock.sessions_s == [1.0, 0.0, 0.0, 0.0]
    ledger.write_text("{not json")
    assert StageClock(ledger, clock=fake).sessions_s == [0.0]


def test_cpu_seconds_per_stage_add_up_across_sessions(tmp_path):
    # A stage's CPU seconds (own clock, e.g. several threads: more CPU than wall) are recorded beside its wall
    # time and carried by the ledger into the next session.
    ledger = tmp_path / "timing_sessions.json"
    wall, cpu = FakeClock(), FakeClock()
    first = StageClock(ledger, clock=wall, cpu_clock=cpu)
    with first.stage("photometric"):
        wall.now += 10.0
        cpu.now += 19.0
    with first.stage("tree"):
        wall.now += 5.0
        cpu.now += 1.0
    second = StageClock(ledger, clock=wall, cpu_clock=cpu)
    with second.stage("tree"):
        wall.now += 3.0
        cpu.now += 2.5
    rec = second.record()
    assert rec["stages_cpu_s"] == {"photometric": 19.0, "tree": 3.5}
    assert rec["stages_s"] == {"photometric": 10.0, "tree": 8.0}
    assert json.loads(ledger.read_text())["stages_cpu_s"] == {"photometric": 19.0, "tree": 3.5}


def test_the_default_cpu_clock_counts_this_process_work():
    clock = StageClock()
    with clock.stage("busy"):
        x = 0
        for i in range(300_000):
            x += i * i
    with clock.stage("idle"):
        pass
    assert clock.stages_cpu_s["busy"] > clock.stages_cpu_s["idle"] >= 0.0
