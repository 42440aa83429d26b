"""Leave-one-out scoring pieces: the held-out frame leaves the scene and its priors; the scores are PSNRs."""

from __future__ import annotations

import numpy as np
import torch
from skimage.metrics import peak_signal_noise_ratio

from benchmarks.evaluation.leave_one_out import drop_frame, masked_psnr_u8, psnr_u8, subset_priors
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


def test_psnr_against_scikit_image():
    rng = np.random.default_rng(1)
    a = rng.integers(0, 256, (20, 30, 3), dtype=np.uint8)
    b = np.clip(a.astype(int) + rng.integers(-20, 21, a.shape), 0, 255).astype(np.uint8)
    np.testing.assert_allclose(psnr_u8(a, b), peak_signal_noise_ratio(a, b, data_range=255), rtol=1e-9)
    m = np.zeros((20, 30), bool)
    m[5:10, 3:20] = True
    np.testing.assert_allclose(masked_psnr_u8(a, b, m), peak_signal_noise_ratio(a[m], b[m], data_range=255))
    assert masked_psnr_u8(a, b, np.zeros_like(m)) is None


def test_training_frame_render_uses_the_camera_the_model_trained_with():
    from types import SimpleNamespace

    from benchmarks.evaluation.leave_one_out import render_training_frame

    sc = PlanarScene(PlanarSceneConfig(width=16, height=12, num_frames=4, supersample=1)).to_scene()
    seen = []
    optimised = torch.eye(4).repeat(4, 1, 1) * 2.0  # distinguishable from every given pose

    def fit_render(K, w2c, W, H, t):
        seen.append(("fit", w2c.clone(), W, H, t))
        return SimpleNamespace(rgb=torch.full((H, W, 3), 2.0))  # clamped to 1 by the caller

    base_like = SimpleNamespace(
        state=SimpleNamespace(fit=SimpleNamespace(cameras=lambda: optimised, render=fit_render)),
        device=torch.device("cpu"),
    )
    img = render_training_frame(base_like, sc, 2)
    assert img.shape == (12, 16, 3) and float(img.max()) == 1.0
    assert seen[-1][0] == "fit" and torch.equal(seen[-1][1], optimised[2]) and seen[-1][4] == 2

    def method_render(K, w2c, W, H, t):
        seen.append(("given", w2c.clone(), W, H, t))
        return torch.zeros(H, W, 3)

    static_like = SimpleNamespace(render=method_render)
    render_training_frame(static_like, sc, 1)
    assert seen[-1][0] == "given" and torch.equal(seen[-1][1], sc.w2cs[1]) and seen[-1][4] == 1


def test_tree_node_between_walks_up_across_a_split():
    from benchmarks.evaluation.leave_one_out import tree_node_between
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


def _dyn(t_ref: list[float], std: list[float], logits: list[float]):
    from worldtree.dynamic import DynamicGaussians

    n = len(t_ref)
    return DynamicGaussians({
        "means": torch.zeros(n, 3), "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        "log_scales": torch.zeros(n, 3), "opacity_logits": torch.tensor(logits), "sh0": torch.zeros(n, 3),
        "t_ref": torch.tensor(t_ref), "t_logstd": torch.tensor(std).log(),
    })  # fmt: skip


def test_node_opacities_halfway_use_each_sets_local_time():
    from types import SimpleNamespace

    from benchmarks.evaluation.leave_one_out import node_opacities_halfway

    # A node over global frames 5-10 (local = global - 5) with one ancestor over 0-10 (local = global).
    own = _dyn([1.0, 2.0], [1.0, 0.5], [0.0, 2.0])
    anc = _dyn([6.0], [2.0], [1.0])
    st = SimpleNamespace(
        static=SimpleNamespace(opacities=torch.tensor([0.3])),
        dynamic=own,
        local_time=lambda t: t - 5,
        chain=[SimpleNamespace(dynamic=anc, local_time=lambda t: t)],
    )
    got = node_opacities_halfway(st, 6, None)  # halfway between global frames 6 and 7

    def expect(logit, t_ref, std, t):
        return 1.0 / (1.0 + np.exp(-logit)) * np.exp(-0.5 * ((t - t_ref) / std) ** 2)

    want = [0.3, expect(0.0, 1.0, 1.0, 1.5), expect(2.0, 2.0, 0.5, 1.5), expect(1.0, 6.0, 2.0, 6.5)]
    np.testing.assert_allclose(got.detach().numpy(), want, rtol=1e-5)
    assert node_opacities_halfway(st, 6, 0).shape == (3,)  # chain_length 0: no ancestor


# ---------------------------------------------------------------------------------------------- the command


def _tiny_scene(root):
    import importlib.util
    from pathlib import Path

    path = Path(__file__).parent.parent / "methods" / "scene_fixture.py"
    spec = importlib.util.spec_from_file_location("wt_tests_scene_fixture_loo", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.write_tiny_scene(root, width=32, height=18, frames=5)


def test_set_keys_and_ranges_are_checked_before_any_work(tmp_path):
    import pytest

    from benchmarks.evaluation import leave_one_out as loo
    from worldtree.errors import UserError

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
    ]
    for extra, match in cases:
        argv = base + extra if extra[0] != "--frames" else [str(scene), *extra, "-o", str(out)]
        with pytest.raises(UserError, match=match) as e:
            loo.main(argv)
        assert "\n" not in str(e.value)
        assert not out.exists()  # refused before anything is written


def test_finished_results_are_keyed_by_their_whole_configuration(tmp_path, monkeypatch, capsys):
    """A result is reused only for the same preset, steps, --set and priors; a changed configuration computes
    again (the old row is kept, the summary shows the current configuration's)."""
    import json

    from benchmarks.evaluation import leave_one_out as loo

    scene = _tiny_scene(tmp_path / "scene")
    out = tmp_path / "out"
    calls = []

    def fake_run_one(args, spec, cfg, scene, k, device, prior_dirs, out_):
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


def test_priors_are_part_of_the_key(tmp_path, monkeypatch):
    import numpy as np

    from benchmarks.evaluation import leave_one_out as loo

    scene = _tiny_scene(tmp_path / "scene")
    calls = []
    monkeypatch.setattr(loo, "run_one", lambda *a: calls.append(a[1].name) or {
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
    proc = subprocess.Popen(
        cmd, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    )  # fmt: skip
    try:
        for _ in range(1200):
            if out.is_dir() and list(out.glob(f"{loo.TMP_PREFIX}*")) or proc.poll() is not None:
                break
            time.sleep(0.1)
        assert proc.poll() is None, proc.stderr.read()
        assert list(out.glob(f"{loo.TMP_PREFIX}*"))
        os.kill(proc.pid, signum)
        _, err = proc.communicate(timeout=120)  # a lost signal fails here, not a timing assert
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
