"""Leave-one-out scoring pieces: the held-out frame leaves the scene and its priors; the scores are PSNRs of
`benchmarks.evaluation.metrics`; what is rendered comes from the `Method` protocol (render_between, node_at,
render_mode with the training frame), implemented by each method."""

from __future__ import annotations

import numpy as np
import torch
from skimage.metrics import peak_signal_noise_ratio

from benchmarks.evaluation.leave_one_out import drop_frame, score, subset_priors
from benchmarks.fixtures.planar_scene import PlanarScene, PlanarSceneConfig


def test_drop_frame_reindexes():
    sc = PlanarScene(PlanarSceneConfig(width=32, height=24, num_frames=5, supersample=1)).to_scene()
    sub = drop_frame(sc, 2)
    assert sub.num_frames == 4 and sub.times.tolist() == [0, 1, 2, 3]
    torch.testing.assert_close(sub.images[2], sc.images[3])
    torch.testing.assert_close(sub.w2cs[1], sc.w2cs[1])
    assert sub.test_images.shape[0] == 0


def test_subset_priors_drops_and_renames(tmp_path):
    (tmp_path / "flow").mkdir()
    (tmp_path / "disp").mkdir()
    for i, j in [(0, 1), (1, 0), (1, 2), (2, 1), (2, 3), (3, 2), (1, 3)]:
        np.save(tmp_path / "flow" / f"{i}_{j}.npy", np.full((2, 2, 2), 10 * i + j, np.float32))
    for t in range(4):
        np.save(tmp_path / "disp" / f"{t:03d}.npy", np.full((2, 2), t, np.float32))
    out = subset_priors({"flow": tmp_path / "flow", "depth": tmp_path / "disp"}, 2, 4, tmp_path / "sub")
    names = sorted(p.name for p in out["flow"].iterdir())
    # Pairs touching frame 2 are gone; frame 3 becomes 2.
    assert names == ["00000_00001.npy", "00001_00000.npy", "00001_00002.npy"]
    assert np.load(out["flow"] / "00001_00002.npy")[0, 0, 0] == 13  # the old (1, 3) pair
    assert [float(np.load(p)[0, 0]) for p in sorted(out["depth"].iterdir())] == [0.0, 1.0, 3.0]


def test_scores_against_scikit_image_and_the_old_uint8_formula():
    rng = np.random.default_rng(1)
    a = rng.integers(0, 256, (20, 30, 3), dtype=np.uint8)
    b = np.clip(a.astype(int) + rng.integers(-20, 21, a.shape), 0, 255).astype(np.uint8)
    np.testing.assert_allclose(score(a, b), peak_signal_noise_ratio(a, b, data_range=255), rtol=1e-9)
    # The formula the harness had before it scored with evaluation.metrics: the same float64 MSE.
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    np.testing.assert_allclose(score(a, b), 10.0 * np.log10(255.0**2 / mse), rtol=1e-12)
    m = np.zeros((20, 30), bool)
    m[5:10, 3:20] = True
    np.testing.assert_allclose(score(a, b, m), peak_signal_noise_ratio(a[m], b[m], data_range=255))
    assert score(a, b, np.zeros_like(m)) is None
    assert score(a, a) == float("inf")


def test_training_frame_render_uses_the_camera_the_model_trained_with():
    from methods.registry import render_training_frame

    sc = PlanarScene(PlanarSceneConfig(width=16, height=12, num_frames=4, supersample=1)).to_scene()
    seen = []

    class Fitted:  # a method that refines its cameras: render_mode places training frame `frame` itself
        def render_mode(self, K, w2c, W, H, t, mode="rgb", test_view=False, frame=None):
            seen.append(("mode", t, mode, test_view, frame))
            return torch.zeros(H, W, 3)

    img = render_training_frame(Fitted(), sc.Ks[2], sc.w2cs[2], 16, 12, 2)
    assert img.shape == (12, 16, 3) and seen[-1] == ("mode", 2, "rgb", False, 2)

    class Plain:  # no render_mode: the given camera through render
        def render(self, K, w2c, W, H, t, test_view=False):
            seen.append(("given", w2c.clone(), t))
            return torch.zeros(H, W, 3)

    render_training_frame(Plain(), sc.Ks[1], sc.w2cs[1], 16, 12, 1)
    assert seen[-1][0] == "given" and torch.equal(seen[-1][1], sc.w2cs[1]) and seen[-1][2] == 1


def test_a_method_without_render_between_draws_the_nearer_frame():
    from methods.registry import nearer_frame, node_at, render_between

    class Plain:
        def render(self, K, w2c, W, H, t, test_view=False):
            return torch.full((H, W, 3), float(t))

    K, w2c = torch.eye(3), torch.eye(4)
    assert [nearer_frame(t) for t in (2.0, 2.49, 2.5, 2.51)] == [2, 2, 3, 3]  # halfway: the later frame
    assert float(render_between(Plain(), K, w2c, 4, 3, 4.5)[0, 0, 0]) == 5.0
    assert node_at(Plain(), 4.5) is None


def test_tree_node_between_walks_up_across_a_split():
    from methods.worldtree import tree_node_between
    from worldtree.tree.tpt import TemporalPartitionTree

    tree = TemporalPartitionTree(11, min_len=11)
    tree.add_children(1, 5)  # frames 0-4 and 5-10
    left, right = tree.interval(2), tree.interval(3)
    assert (left.start, left.end, right.start, right.end) == (0, 4, 5, 10)
    assert tree_node_between(tree, 2) == 2  # frames 2 and 3: both in the left leaf
    assert tree_node_between(tree, 7) == 3
    assert tree_node_between(tree, 4) == 1  # frames 4 and 5 straddle the split: the root holds both
    assert tree_node_between(TemporalPartitionTree(11, min_len=12), 4) == 1  # root only


def test_halfway_means_and_antipodal_rotations():
    from worldtree.dynamic import halfway as _halfway

    q = torch.tensor([[0.0, 0.0, 0.0, 1.0], [1.0, 0.0, 0.0, 0.0]])
    ga = (torch.zeros(2, 3), q, torch.zeros(2, 3), torch.tensor([0.2, 1.0]), torch.ones(2, 3))
    # Same rotations written with the opposite sign: the blend must not cancel to zero.
    gb = (torch.full((2, 3), 2.0), -q, torch.ones(2, 3), torch.tensor([0.6, 0.0]), torch.zeros(2, 3))
    half = torch.tensor([0.4, 0.5])  # the caller's opacities at the half-frame time
    m, qh, ls, o, c = _halfway(ga, gb, half)
    torch.testing.assert_close(m, torch.ones(2, 3))
    torch.testing.assert_close(qh.abs(), q.abs())
    assert torch.equal(o, half)
    assert torch.equal(ls, ga[2]) and torch.equal(c, ga[4]) and torch.isfinite(qh).all()


def test_between_is_halfway_at_one_half_bit_for_bit_and_the_ends_at_zero_and_one():
    from worldtree.dynamic import between, halfway

    g = torch.Generator().manual_seed(0)
    n = 1000
    ga = (torch.randn(n, 3, generator=g) * 7, torch.randn(n, 4, generator=g), torch.randn(n, 3, generator=g),
          torch.rand(n, generator=g), torch.rand(n, 3, generator=g))  # fmt: skip
    gb = (torch.randn(n, 3, generator=g) * 7, torch.randn(n, 4, generator=g), *ga[2:])
    o = torch.rand(n, generator=g)
    # The formula the leave-one-out had before `between`: (ma + mb) / 2 and the nlerp of qa + qb.
    qb = torch.where((ga[1] * gb[1]).sum(-1, keepdim=True) < 0, -gb[1], gb[1])
    q = ga[1] + qb
    for got, want in zip(between(ga, gb, o, 0.5), (0.5 * (ga[0] + gb[0]), q / q.norm(dim=-1, keepdim=True), *ga[2:3], o, ga[4]), strict=True):  # fmt: skip
        assert torch.equal(got, want)
    assert all(torch.equal(x, y) for x, y in zip(halfway(ga, gb, o), between(ga, gb, o, 0.5), strict=True))
    m0, q0, *_ = between(ga, gb, o, 0.0)
    m1, q1, *_ = between(ga, gb, o, 1.0)
    assert torch.equal(m0, ga[0]) and torch.equal(m1, gb[0])
    torch.testing.assert_close(q0, ga[1] / ga[1].norm(dim=-1, keepdim=True))
    torch.testing.assert_close(q1, qb / qb.norm(dim=-1, keepdim=True))


def test_path_weights_are_the_polynomial_through_the_knots():
    import numpy as np

    from worldtree.dynamic import path_weights

    rng = np.random.default_rng(0)
    for knots in ((-1, 0, 1, 2), (0, 1, 2), (-1, 0, 1), (0, 1)):
        for frac in (0.0, 0.25, 0.5, 0.9):
            y = rng.normal(size=len(knots))
            w = path_weights(knots, frac)
            # numpy's own fit of the polynomial of degree len - 1 through the points, evaluated at frac
            want = np.polyval(np.polyfit(knots, y, len(knots) - 1), frac)
            assert abs(sum(wi * yi for wi, yi in zip(w, y, strict=True)) - want) < 1e-9
            assert abs(sum(w) - 1.0) < 1e-12
    assert path_weights((-1, 0, 1, 2), 0.5) == (-1 / 16, 9 / 16, 9 / 16, -1 / 16)  # the four-point midpoint rule
    import pytest

    with pytest.raises(ValueError, match="distinct"):
        path_weights((0, 0, 1), 0.5)


def test_between_path_follows_a_cubic_path_and_keeps_still_points():
    from worldtree.dynamic import between, between_path

    g = torch.Generator().manual_seed(1)
    n = 200
    coef = torch.randn(4, n, 3, generator=g)  # a path of degree 3 in time per Gaussian

    def at(t: float) -> torch.Tensor:
        return coef[0] + coef[1] * t + coef[2] * t**2 + coef[3] * t**3

    q = torch.randn(n, 4, generator=g)
    rest = (torch.randn(n, 3, generator=g), torch.rand(n, generator=g), torch.rand(n, 3, generator=g))
    lists = {d: (at(float(d)), q, *rest) for d in (-1, 0, 1, 2)}
    o = torch.rand(n, generator=g)
    for frac in (0.1, 0.5, 0.8):
        m, *_ = between_path(lists, o, frac)
        torch.testing.assert_close(m, at(frac), atol=1e-4, rtol=1e-5)
        # A parabola through three frames at a video's end is exact for degree 2 (the cubic term dropped).
        coef3 = coef[3].clone()
        coef[3] = 0.0
        three = {d: (at(float(d)), q, *rest) for d in (0, 1, 2)}
        torch.testing.assert_close(between_path(three, o, frac)[0], at(frac), atol=1e-4, rtol=1e-5)
        coef[3] = coef3
    still = {d: (lists[0][0], q, *rest) for d in (-1, 0, 1, 2)}  # a Gaussian that does not move stays put
    torch.testing.assert_close(between_path(still, o, 0.5)[0], lists[0][0], atol=1e-6, rtol=0)
    two = {0: lists[0], 1: lists[1]}  # two frames: exactly the straight line
    assert all(torch.equal(x, y) for x, y in zip(between_path(two, o, 0.3), between(lists[0], lists[1], o, 0.3),
                                                 strict=True))  # fmt: skip


def _dyn(t_ref: list[float], std: list[float], logits: list[float]):
    from worldtree.dynamic import DynamicGaussians

    n = len(t_ref)
    return DynamicGaussians({
        "means": torch.zeros(n, 3), "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        "log_scales": torch.zeros(n, 3), "opacity_logits": torch.tensor(logits), "sh0": torch.zeros(n, 3),
        "t_ref": torch.tensor(t_ref), "t_logstd": torch.tensor(std).log(),
    })  # fmt: skip


def test_node_opacities_between_frames_use_each_sets_local_time():
    from types import SimpleNamespace

    from methods.worldtree import node_opacities_at

    # A node over global frames 5-10 (local = global - 5) with one ancestor over 0-10 (local = global).
    own = _dyn([1.0, 2.0], [1.0, 0.5], [0.0, 2.0])
    anc = _dyn([6.0], [2.0], [1.0])
    st = SimpleNamespace(
        static=SimpleNamespace(opacities=torch.tensor([0.3])),
        dynamic=own,
        local_time=lambda t: t - 5,
        chain=[SimpleNamespace(dynamic=anc, local_time=lambda t: t)],
    )
    got = node_opacities_at(st, 6, 0.5, None)  # halfway between global frames 6 and 7

    def expect(logit, t_ref, std, t):
        return 1.0 / (1.0 + np.exp(-logit)) * np.exp(-0.5 * ((t - t_ref) / std) ** 2)

    want = [0.3, expect(0.0, 1.0, 1.0, 1.5), expect(2.0, 2.0, 0.5, 1.5), expect(1.0, 6.0, 2.0, 6.5)]
    np.testing.assert_allclose(got.detach().numpy(), want, rtol=1e-5)
    assert node_opacities_at(st, 6, 0.5, 0).shape == (3,)  # chain_length 0: no ancestor


# ---------------------------------------------------------------------------------------------- the command


def _tiny_scene(root, width=32, height=18):
    import importlib.util
    from pathlib import Path

    path = Path(__file__).parent.parent / "methods" / "scene_fixture.py"
    spec = importlib.util.spec_from_file_location("wt_tests_scene_fixture_loo", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.write_tiny_scene(root, width=width, height=height, frames=5)


def test_set_keys_and_ranges_are_checked_before_any_work(tmp_path, monkeypatch):
    import pytest

    from benchmarks.evaluation import leave_one_out as loo
    from worldtree.infra.errors import UserError

    scene = _tiny_scene(tmp_path / "scene")
    out = tmp_path / "out"
    base = [str(scene), "--frames", "2", "--methods", "static,base", "-o", str(out)]
    cases = [
        (["--set", "nope=1"], "no method of --methods static,base has it"),
        (["--set", "lambda_dsim=0.1"], "did you mean 'lambda_dssim'"),
        (["--set", "photometric.lambda_depth=-1"], "must be at least 0"),
        (["--set", "seed=1", "--seed", "2"], "also given by --seed"),
        (["--steps", "0"], "--steps 0"),
        (["--seed", "1" * 20], "--seed"),
        (["--frames", "4"], "needs a frame on each side"),
        (["--set", "worldtree:min_len=3"], "'worldtree' is not among --methods static,base"),
        (["--set", "static:nope=1"], "(method static)"),
        (["--static-steps", "0"], "--static-steps 0: must be at least 1"),
        (["--set", "base:steps=0"], "--set base:steps=0: must be at least 1"),
        (["--set", "static:steps=5", "--static-steps", "6"], "given more than once"),
        (["--set", "base:priors.flow_source=x", "--flow", str(tmp_path)], "also given by --flow"),
        # checked against the priors this run imports: a setting for a fitted import needs --depth-fit
        (["--set", "scaffold.trajectory_depth_imported=true", "--depth-maps", str(tmp_path)],
         "fitted to the classical one only"),
    ]
    for extra, match in cases:
        argv = base + extra if extra[0] != "--frames" else [str(scene), *extra, "-o", str(out)]
        with pytest.raises(UserError, match=match) as e:
            loo.main(argv)
        assert "\n" not in str(e.value)
        assert not out.exists()  # refused before anything is written
    # ... and accepted with it (the import options are in the config the --set items are checked against)
    seen = []
    monkeypatch.setattr(loo, "_run_all", lambda args, plans, *rest: seen.extend(plans))
    loo.main(
        base + ["--depth-maps", str(tmp_path), "--depth-kind", "disparity", "--depth-fit"]
        + ["--set", "scaffold.trajectory_depth_imported=true", "--set", "priors.depth_import.merge=fill"]
    )
    (_, static, _), (_, b, _) = seen
    assert b.scaffold.trajectory_depth_imported and b.priors.depth_source == str(tmp_path)
    assert b.priors.depth_import.fit_scale_shift and b.priors.depth_import.kind == "disparity"
    assert not hasattr(static, "priors")


def test_finished_results_are_keyed_by_their_whole_configuration(tmp_path, monkeypatch, capsys):
    """A result is reused only for the same preset, steps, --set and priors; a changed configuration computes
    again (the old row is kept, the summary shows the current configuration's)."""
    import json

    from benchmarks.evaluation import leave_one_out as loo

    scene = _tiny_scene(tmp_path / "scene")
    out = tmp_path / "out"
    calls = []

    def fake_run_one(args, spec, cfg, scene, k, device, prior_dirs, out_, score_scene=None, **_):
        calls.append((spec.name, k, cfg.steps, cfg.lambda_dssim))
        return {"k": k, "method": spec.name, "psnr": 20.0 + len(calls), "train_s": 0.0,
                "psnr_train_neighbours": {"prev": 1.0, "next": 1.0}}  # fmt: skip

    monkeypatch.setattr(loo, "run_one", fake_run_one)
    argv = [str(scene), "--frames", "1,2", "--methods", "static", "-o", str(out), "--steps", "5"]
    loo.main(argv)
    assert len(calls) == 2
    loo.main(argv)  # the same configuration: both results reused
    assert len(calls) == 2
    loo.main(argv[:-1] + ["6"])  # other steps
    assert calls[-1][2] == 6 and len(calls) == 4
    loo.main(argv + ["--set", "lambda_dssim=0.5"])  # another setting
    assert calls[-1][3] == 0.5 and len(calls) == 6
    loo.main(argv + ["--set", "lambda_dssim=0.5"])
    assert len(calls) == 6
    rows = json.loads((out / "loo.json").read_text())["runs"]
    assert len(rows) == 6 and len({r["config_key"] for r in rows}) == 3
    # The summary of the last command is over its own configuration's rows (PSNR 25 and 26), not all six.
    assert "mean PSNR 25.50" in capsys.readouterr().out.strip().splitlines()[-1]
    # A killed run's temporary folder is removed by the next run (it holds OUT's lock, so it is stale).
    (out / f"{loo.TMP_PREFIX}abc123").mkdir()
    loo.main(argv)
    assert not list(out.glob(f"{loo.TMP_PREFIX}*"))


def _configs_seen(monkeypatch, loo) -> dict:
    """``{method: config}`` of the last held-out run of each method; the runs themselves are faked."""
    seen = {}

    def fake_run_one(args, spec, cfg, scene, k, device, prior_dirs, out_, score_scene=None, **_):
        seen[spec.name] = cfg
        return {"k": k, "method": spec.name, "psnr": 1.0, "train_s": 0.0,
                "psnr_train_neighbours": {"prev": 1.0, "next": 1.0}}  # fmt: skip

    monkeypatch.setattr(loo, "run_one", fake_run_one)
    return seen


def test_one_methods_settings(tmp_path, monkeypatch):
    """``--set NAME:KEY=VALUE`` and ``--NAME-steps N`` (what ``--static-steps`` was) change one method's config,
    over the common options; an unscoped ``--set`` changes every method that has the key."""
    from benchmarks.evaluation import leave_one_out as loo

    scene = _tiny_scene(tmp_path / "scene")
    seen = _configs_seen(monkeypatch, loo)
    argv = [str(scene), "--frames", "2", "--methods", "static,base", "--preset", "quick", "--steps", "5"]
    loo.main([*argv, "-o", str(tmp_path / "a"), "--static-steps", "7", "--set", "base:dynamic_max_init=99"])
    assert (seen["static"].steps, seen["base"].steps, seen["base"].dynamic_max_init) == (7, 5, 99)
    loo.main([*argv, "-o", str(tmp_path / "b"), "--set", "base:steps=9", "--set", "seed=3"])
    assert (seen["static"].steps, seen["base"].steps, seen["static"].seed, seen["base"].seed) == (5, 9, 3, 3)


def test_given_steps_are_exact_on_a_long_video(tmp_path, monkeypatch):
    """As in ``wtbench run``: ``--steps N`` / ``--NAME-steps N`` ask for exactly N photometric steps, where the
    quick preset would raise them to 15 a frame on a long video; a ``--set`` of ``steps_per_frame`` still wins."""
    from benchmarks.evaluation import leave_one_out as loo

    scene = _tiny_scene(tmp_path / "scene")
    seen = _configs_seen(monkeypatch, loo)
    argv = [str(scene), "--frames", "2", "--methods", "base", "--preset", "quick"]
    loo.main([*argv, "-o", str(tmp_path / "a")])
    assert seen["base"].photometric_steps(160) == 2400  # the preset's 15 a frame
    loo.main([*argv, "-o", str(tmp_path / "b"), "--steps", "100"])
    assert seen["base"].photometric_steps(160) == 100
    loo.main([*argv, "-o", str(tmp_path / "c"), "--base-steps", "90"])
    assert seen["base"].photometric_steps(160) == 90
    loo.main([*argv, "-o", str(tmp_path / "d"), "--steps", "100", "--set", "base:steps_per_frame=2"])
    assert seen["base"].photometric_steps(160) == 320


def test_priors_are_part_of_the_key(tmp_path, monkeypatch):
    import numpy as np

    from benchmarks.evaluation import leave_one_out as loo

    scene = _tiny_scene(tmp_path / "scene")
    calls = []
    monkeypatch.setattr(loo, "run_one", lambda *a, **_: calls.append(a[1].name) or {
        "k": a[4], "method": a[1].name, "psnr": 1.0, "train_s": 0.0,
        "psnr_train_neighbours": {"prev": 1.0, "next": 1.0}})  # fmt: skip
    disp = tmp_path / "disp"
    disp.mkdir()
    for t in range(5):
        np.save(disp / f"{t:03d}.npy", np.ones((18, 32), np.float32))
    argv = [
        str(scene),
        "--frames",
        "2",
        "--methods",
        "base",
        "-o",
        str(tmp_path / "out"),
        "--preset",
        "smoke",
    ]
    loo.main(argv)
    loo.main(argv + ["--depth-maps", str(disp)])
    loo.main(argv + ["--depth-maps", str(disp)])
    np.save(disp / "004.npy", np.full((18, 32), 2.0, np.float32))  # another prior: computed again
    loo.main(argv + ["--depth-maps", str(disp)])
    assert len(calls) == 3


def _stop_with(signum, tmp_path):
    """Start a leave-one-out training that would run for minutes, with SIGINT ignored as a shell's background
    job inherits it, send ``signum`` once its temporary folder exists; return (exit code, stderr, OUT)."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from benchmarks.evaluation import leave_one_out as loo

    scene = _tiny_scene(tmp_path / "scene")
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "benchmarks.evaluation.leave_one_out", str(scene), "--frames", "2",
           "--methods", "static", "--steps", "1000000", "--device", "cpu", "-o", str(out)]  # fmt: skip
    # PYTHONFAULTHANDLER: a child that outlives the signal is sent SIGABRT and prints every thread's stack,
    # so a hang (seen once on CI, not reproduced here) fails with where it was stuck.
    proc = subprocess.Popen(
        cmd, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
        env={**os.environ, "PYTHONFAULTHANDLER": "1"},
    )  # fmt: skip
    try:
        for _ in range(1200):
            if out.is_dir() and list(out.glob(f"{loo.TMP_PREFIX}*")) or proc.poll() is not None:
                break
            time.sleep(0.1)
        assert proc.poll() is None, proc.stderr.read()
        assert list(out.glob(f"{loo.TMP_PREFIX}*"))
        os.kill(proc.pid, signum)
        try:
            _, err = proc.communicate(timeout=120)  # a lost signal fails here, not a timing assert
        except subprocess.TimeoutExpired:
            os.kill(proc.pid, signal.SIGABRT)
            _, err = proc.communicate(timeout=60)
            raise AssertionError(f"still running 120 s after signal {signum}; its stacks:\n{err[-6000:]}") from None
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, err, out


def test_sigint_stops_at_once_and_leaves_no_temporary_folder(tmp_path):
    import signal

    rc, err, out = _stop_with(signal.SIGINT, tmp_path)
    assert rc == 130, err
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith("interrupted:")
    assert sorted(p.name for p in out.iterdir()) == []


def test_sigterm_leaves_no_temporary_folder(tmp_path):
    import signal

    rc, err, out = _stop_with(signal.SIGTERM, tmp_path)
    assert rc == 143, err
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith("terminated:")
    assert sorted(p.name for p in out.iterdir()) == []


# ------------------------------------------------------------------------ the methods' render_between, trained


def _opacities_between(fit, ga, time):
    """``[N]`` opacities of frame ``a``'s render list ``ga`` with the dynamic ones taken at ``time``."""
    o = ga[3]
    n_s, n_d = len(fit.static), len(fit.dynamic)
    if o.shape[0] == n_s + n_d:
        o = torch.cat([o[:n_s], fit.dynamic.opacities_at(time)])
    return o


def _old_formula_base(method, K, w2c, W, H, a):
    """What the harness computed before the protocol (Base family), reaching into the fitted state: every
    Gaussian halfway between frames a and a + 1, dynamic opacities at a + 0.5, the camera placed at a + 0.5."""
    from worldtree.dynamic import halfway
    from worldtree.render import rasterize

    fit = method.state.fit
    ga = fit.gaussians_at(a)
    m, q, ls, o, c = halfway(ga, fit.gaussians_at(a + 1), _opacities_between(fit, ga, a + 0.5))
    pose = method.state.placement.place(w2c.to(torch.float32), a + 0.5)
    return rasterize(m, q, ls, o, c, K.to(torch.float32), pose, W, H, backend=fit.cfg.backend).rgb.clamp(0, 1)


def _fitted(name, scene_dir, **sets):
    import dataclasses

    from methods.registry import get_method
    from worldtree.scene import load_scene
    from worldtree.trainer import TrainContext

    cfg = dataclasses.replace(get_method(name).config("smoke"), priors_cache=False, **sets)
    torch.manual_seed(0)
    method = get_method(name).build(cfg, load_scene(scene_dir), torch.device("cpu"))
    method.fit(TrainContext(checkpoint_dir=None, progress=False))
    return method


def _off_rig(w2c):
    """``w2c`` moved 2 cm up: a camera no training frame has (a training frame's own pose is drawn from that
    frame's fitted pose, not through the placement these formulas use)."""
    out = w2c.clone()
    out[1, 3] += 0.02
    return out


def test_base_render_between_is_the_old_halfway_and_its_frames_at_integer_times(tmp_path):
    from methods.base import BaseConfig

    assert BaseConfig().between_frames == 4  # the default; the straight line (2) is checked first
    method = _fitted("base", _tiny_scene(tmp_path / "scene"), between_frames=2)  # the straight line first
    sc = method.state.scene
    K, w2c, W, H = sc.Ks[0], _off_rig(sc.w2cs[0]), sc.width, sc.height
    for a in (0, 2):
        got = method.render_between(K, w2c, W, H, a + 0.5)
        assert torch.equal(got, _old_formula_base(method, K, w2c, W, H, a))
        assert torch.equal(method.render_between(K, w2c, W, H, float(a)), method.render(K, w2c, W, H, a))
    # Just after a frame it draws (nearly) that frame: the interpolation starts where the frame is.
    torch.testing.assert_close(method.render_between(K, w2c, W, H, 1 + 1e-6), method.render(K, w2c, W, H, 1),
                               atol=1e-3, rtol=0)  # fmt: skip
    assert method.node_at(1.5) is None
    # between_frames 4: the cubic through frames a - 1 .. a + 2 (a parabola through three at the video's ends),
    # recomputed here from the fitted lists and numpy's polynomial fit.
    import dataclasses

    import numpy as np
    import pytest

    from worldtree.dynamic import between
    from worldtree.infra.errors import SettingError
    from worldtree.render import rasterize

    method.cfg = dataclasses.replace(method.cfg, between_frames=4)
    fit, T = method.state.fit, sc.num_frames
    for a, frac in ((1, 0.5), (0, 0.25), (T - 2, 0.5)):
        knots = [d for d in (-1, 0, 1, 2) if 0 <= a + d < T]
        pos = np.stack([fit.gaussians_at(a + d)[0].detach().numpy().astype(np.float64) for d in knots])  # [k, N, 3]
        flat = pos.reshape(len(knots), -1)
        want_m = np.stack([np.polyval(np.polyfit(knots, flat[:, i], len(knots) - 1), frac)
                           for i in range(flat.shape[1])]).reshape(pos.shape[1:])  # fmt: skip
        ga, gb = (tuple(x.detach() for x in fit.gaussians_at(t)) for t in (a, a + 1))
        _, q, ls, o, c = between(ga, gb, _opacities_between(fit, ga, a + frac), frac)
        pose = method.state.placement.place(w2c.to(torch.float32), a + frac)
        want = rasterize(torch.from_numpy(want_m).float(), q, ls, o, c, K.to(torch.float32), pose, W, H,
                         backend=fit.cfg.backend).rgb.clamp(0, 1)  # fmt: skip
        torch.testing.assert_close(method.render_between(K, w2c, W, H, a + frac), want, atol=2e-4, rtol=0)
    with pytest.raises(SettingError, match="between_frames"):
        dataclasses.replace(method.cfg, between_frames=3)


def test_worldtree_render_between_uses_the_node_holding_both_frames(tmp_path):
    from methods.worldtree import node_opacities_at, tree_node_between
    from worldtree.dynamic import halfway
    from worldtree.render import rasterize

    method = _fitted("worldtree", _tiny_scene(tmp_path / "scene"), min_len=2, sequential=True, between_frames=2)
    s = method.state
    assert s.tree is not None and len(s.states) > 1
    sc = s.scene
    K, w2c, W, H = sc.Ks[1], _off_rig(sc.w2cs[1]), sc.width, sc.height
    for a in range(sc.num_frames - 1):
        j = tree_node_between(s.tree, a)
        assert method.node_at(a + 0.5) == j
        st = s.states[j]
        cache = st.dynamic.attach(st.scaffold)
        ga = st.gaussians_at(a, s.cfg.chain_length, cache)
        gb = st.gaussians_at(a + 1, s.cfg.chain_length, cache)
        m, q, ls, o, c = halfway(ga, gb, node_opacities_at(st, a, 0.5, s.cfg.chain_length))
        pose = s.placement.place(w2c, a + 0.5)
        want = rasterize(m, q, ls, o, c, K, pose, W, H, backend=s.cfg.photometric.backend).rgb.clamp(0, 1)
        assert torch.equal(method.render_between(K, w2c, W, H, a + 0.5), want)
    assert method.node_at(2) == method.node_at(2.0)
    # between_frames 4: the path through the frames around a and a + 1 that the drawing node holds, no others.
    import dataclasses

    from worldtree.dynamic import between_path

    s.cfg = dataclasses.replace(s.cfg, between_frames=4)
    method.cfg = s.cfg
    for a in range(sc.num_frames - 1):
        st = s.states[tree_node_between(s.tree, a)]
        cache = st.dynamic.attach(st.scaffold)
        lists = {d: st.gaussians_at(a + d, s.cfg.chain_length, cache) for d in (-1, 0, 1, 2)
                 if st.interval.start <= a + d <= st.interval.end}  # fmt: skip
        m, q, ls, o, c = between_path(lists, node_opacities_at(st, a, 0.5, s.cfg.chain_length), 0.5)
        want = rasterize(m, q, ls, o, c, K, s.placement.place(w2c, a + 0.5), W, H,
                         backend=s.cfg.photometric.backend).rgb.clamp(0, 1)  # fmt: skip
        assert torch.equal(method.render_between(K, w2c, W, H, a + 0.5), want)


def test_score_size_full_renders_and_scores_at_the_scenes_own_size(tmp_path):
    """``--score-size full``: a model trained at half size draws frame k at the scene's size and is scored
    there (the NVIDIA protocol scores 480x270 whatever the training size); the PSNR is the one of the written
    full-size image against the scene's frame, computed here with scikit-image; the key differs from the
    training-size result's, so neither is reused for the other."""
    import json

    from skimage.metrics import peak_signal_noise_ratio

    from benchmarks.evaluation import leave_one_out as loo
    from worldtree.imageio import read_image

    scene = _tiny_scene(tmp_path / "scene", width=48, height=24)  # half size still above the SSIM window
    out = tmp_path / "out"
    argv = [str(scene), "--frames", "2", "--methods", "static", "-o", str(out), "--steps", "5",
            "--downscale", "2"]  # fmt: skip
    loo.main(argv)
    loo.main(argv + ["--score-size", "full"])
    rows = json.loads((out / "loo.json").read_text())["runs"]
    assert [r["scored_size"] for r in rows] == [[24, 12], [48, 24]]
    assert rows[0]["config_key"] != rows[1]["config_key"]
    pred = read_image(out / "k02_static.png")
    assert pred.shape[:2] == (24, 48)
    gt = read_image(sorted((scene / "images").iterdir())[2])
    assert abs(rows[1]["psnr"] - peak_signal_noise_ratio(gt, pred, data_range=255)) < 1e-3


def test_the_quick_preset_trains_a_short_video_at_full_size(tmp_path, monkeypatch):
    """Without --downscale the quick preset trains at full size when the video without frame k holds at most
    ``full_size_pixels`` pixels (a 5-frame 32x18 scene: 4 x 32 x 18 = 2304), at half size above it; a given
    --downscale wins."""
    from benchmarks.evaluation import leave_one_out as loo

    scene = _tiny_scene(tmp_path / "scene")
    seen = []
    monkeypatch.setattr(loo, "run_one", lambda *a, **_: seen.append(a[2].downscale) or {
        "k": a[4], "method": a[1].name, "psnr": 1.0, "train_s": 0.0,
        "psnr_train_neighbours": {"prev": 1.0, "next": 1.0}})  # fmt: skip
    base = [str(scene), "--frames", "2", "--methods", "static", "--preset", "quick"]
    loo.main(base + ["-o", str(tmp_path / "a"), "--set", "full_size_pixels=2304"])
    loo.main(base + ["-o", str(tmp_path / "b"), "--set", "full_size_pixels=2303"])
    loo.main(base + ["-o", str(tmp_path / "c"), "--set", "full_size_pixels=2304", "--downscale", "2"])
    assert seen == [1, 2, 2]


def test_each_held_out_run_trains_with_deterministic_kernels(tmp_path, monkeypatch):
    """A leave-one-out run trains as `wtbench run` does: torch's deterministic kernels on for the CPU, so
    the per-frame differences between methods are not thread-order noise (two runs of one seed ended 0.70 dB
    apart without them, docs/worldtree_method.md)."""
    import torch

    from benchmarks.evaluation import leave_one_out as loo
    from methods.static3dgs import StaticGaussians

    seen = []
    fit = StaticGaussians.fit

    def spy(self, ctx):
        seen.append(torch.are_deterministic_algorithms_enabled())
        return fit(self, ctx)

    monkeypatch.setattr(StaticGaussians, "fit", spy)
    assert not torch.are_deterministic_algorithms_enabled()  # conftest starts every test with them off
    scene = _tiny_scene(tmp_path / "scene", width=48, height=24)
    loo.main([str(scene), "--frames", "2", "--methods", "static", "-o", str(tmp_path / "out"), "--steps", "3"])
    assert seen == [True]


def test_worldtree_takes_the_held_out_frames_root_from_base(tmp_path):
    """By default WorldTree's run without frame k grows its tree on Base's root of the same frame (linked, not
    trained again: its row names the lender, and its time includes the lent stages'); its scores are those of
    the run that trains its own root (`--no-share-root`), to the last digit."""
    import json

    from benchmarks.evaluation import leave_one_out as loo

    scene = _tiny_scene(tmp_path / "scene", width=48, height=24)
    argv = [str(scene), "--frames", "2", "--methods", "base,worldtree", "--preset", "smoke", "--device", "cpu",
            "--set", "worldtree:min_len=2"]  # fmt: skip
    loo.main([*argv, "-o", str(tmp_path / "shared")])
    loo.main([*argv, "-o", str(tmp_path / "alone"), "--no-share-root"])
    shared, alone = ({r["method"]: r for r in json.loads((tmp_path / d / "loo.json").read_text())["runs"]}
                     for d in ("shared", "alone"))  # fmt: skip
    lent = shared["worldtree"]["root_from"]
    assert lent["method"] == "base" and "photometric" in lent["items"] and lent["stages_s"]["photometric"] > 0
    assert shared["worldtree"]["train_s"] >= lent["stages_s"]["photometric"]
    assert "root_from" not in shared["base"] and "root_from" not in alone["worldtree"]
    for m in ("base", "worldtree"):
        assert shared[m]["psnr"] == alone[m]["psnr"], m
        assert shared[m]["psnr_train_neighbours"] == alone[m]["psnr_train_neighbours"], m
    assert shared["worldtree"]["tree"]["tree_nodes"] == alone["worldtree"]["tree"]["tree_nodes"]
    assert not list((tmp_path / "shared").glob(f"{loo.TMP_PREFIX}*"))  # the frame's roots are removed
