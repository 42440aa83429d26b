"""benchmarks.speed.optimizer_step times the same update both ways: fused and single-tensor Adam agree."""

from __future__ import annotations

import torch

from benchmarks.speed.optimizer_step import main, optimizers, time_steps


def test_fused_and_single_variants_make_the_same_update():
    start = optimizers([50, 7], fused=False)  # the same seed: the values both variants start from
    single, fused = optimizers([50, 7], fused=False), optimizers([50, 7], fused=True)
    assert all(not o.optimizer.param_groups[0]["fused"] for o in single)
    assert all(o.optimizer.param_groups[0]["fused"] for o in fused)
    time_steps(single, 3)
    time_steps(fused, 3)
    for a, b, s0 in zip(single, fused, start, strict=True):
        groups = zip(
            a.optimizer.param_groups, b.optimizer.param_groups, s0.optimizer.param_groups, strict=True
        )
        for ga, gb, g0 in groups:
            # Same start, same gradients (same seed), 4 steps of lr 1e-3: equal to float32 rounding.
            torch.testing.assert_close(ga["params"][0], gb["params"][0], rtol=0, atol=1e-6)
            # Every element moved (about lr a step).
            assert (ga["params"][0] - g0["params"][0]).abs().min() > 1e-4


def test_main_prints_one_line_per_thread_count_and_round(capsys):
    main("--static 20 --dynamic 5 --other 3 --steps 2 --rounds 2 --threads 1".split())
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 2 and all("single" in ln and "fused" in ln for ln in lines)
