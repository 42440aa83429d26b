"""The whole-run profiler's bookkeeping: per-stage profiles and per-kind inclusive times."""

from __future__ import annotations

import pstats

import torch

from benchmarks.speed.e2e import StageProfiles, _qualnames, kind_times


def _outer_work():
    return sum(i * i for i in range(2000))


def _inner_work():
    return sorted(range(3000), key=lambda v: -v)[0]


def _names(prof) -> set[str]:
    return {key[2] for key in pstats.Stats(prof).stats}


def test_nested_stages_collect_apart():
    """The innermost running stage collects; the outer one resumes after it (like tree inside test_pose)."""
    p = StageProfiles()
    with p.stage("outer"):
        _outer_work()
        with p.stage("inner"):
            _inner_work()
        _outer_work()
    assert "_outer_work" in _names(p.profiles["outer"]) and "_inner_work" not in _names(p.profiles["outer"])
    assert "_inner_work" in _names(p.profiles["inner"]) and "_outer_work" not in _names(p.profiles["inner"])
    assert pstats.Stats(p.profiles["outer"]).stats[
        next(k for k in pstats.Stats(p.profiles["outer"]).stats if k[2] == "_outer_work")
    ][1] == 2  # both calls, before and after the inner stage
    assert 0 < p.wall["inner"] <= p.wall["outer"]


def test_kind_times_count_a_kind_once():
    """losses.ssim calls losses.ssim_map which calls losses._blur: the losses kind is ssim's inclusive time."""
    from worldtree.losses import ssim

    a, b = torch.rand(40, 40, 3), torch.rand(40, 40, 3)
    p = StageProfiles()
    with p.stage("s"):
        for _ in range(3):
            ssim(a, b)
    st = pstats.Stats(p.profiles["s"])
    kt = kind_times(st, _qualnames())
    ssim_key = next(k for k in st.stats if k[2] == "ssim" and k[0].endswith("worldtree/losses.py"))
    assert kt["losses"] == st.stats[ssim_key][3]  # inclusive time of the entry point, nothing added twice
    assert kt["losses"] <= p.wall["s"]
