"""benchmarks.speed.priors_threads: runs on a small built scene and finds the runs identical."""

from __future__ import annotations

import pytest

from benchmarks.speed import priors_threads

synth = pytest.importorskip("nvidia_ls.synth")
build = pytest.importorskip("nvidia_ls.build")


def test_prints_times_and_identity(tmp_path, capsys):
    cfg = synth.SynthConfig(cameras=12, steps=8, width=96, height=54, supersample=1)
    raw = synth.write_raw_scene(tmp_path / "raw" / "S", cfg)
    scene = build.build_scene(
        raw, tmp_path / "scenes", build.BuildConfig(poses=raw / "gt" / "poses_bounds.npy")
    )
    assert priors_threads.main([str(scene), "--threads", "1,3"]) == 0
    out = capsys.readouterr().out
    lines = [ln for ln in out.splitlines() if ln.startswith("threads ")]
    assert len(lines) == 2
    assert all(ln.endswith("same as the first run: True") for ln in lines)


def test_bad_thread_list_is_one_line(capsys):
    assert priors_threads.main(["unused", "--threads", "one"]) == 2
    assert "--threads" in capsys.readouterr().err
