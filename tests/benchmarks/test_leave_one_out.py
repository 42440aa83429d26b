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
