"""Static warm-up: masked loss, exact zero influence of dynamic pixels, and a decreasing loss on a tiny scene."""

from __future__ import annotations

import numpy as np
import torch
from scipy import ndimage

from worldtree.render import rasterize
from worldtree.stages.static_warmup import (
    StaticWarmup,
    StaticWarmupConfig,
    quick_static_warmup_config,
    ssim_weights,
    static_weights,
)
from worldtree.strategy import DensifyStrategy
from worldtree.trainer import Trainer, TrainerConfig

W, H, T = 48, 32, 4


def tiny_video(seed: int = 0):
    """Frames of a Gaussian 'wall' 4 units away from 4 cameras on a line, plus a 'dynamic' square painted
    with random colours (not explained by any static model) and its mask."""
    g = torch.Generator().manual_seed(seed)
    n = 400
    xy = (torch.rand(n, 2, generator=g) - 0.5) * torch.tensor([4.5, 3.2])
    means = torch.cat([xy, torch.full((n, 1), 4.0)], 1)
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1)
    ls = torch.full((n, 3), float(np.log(0.1)))
    op = torch.full((n,), 0.9)
    col = torch.rand(n, 3, generator=g)
    K = torch.tensor([[40.0, 0, (W - 1) / 2], [0, 40.0, (H - 1) / 2], [0, 0, 1]])
    Ks = K[None].repeat(T, 1, 1)
    w2cs = torch.eye(4)[None].repeat(T, 1, 1)
    w2cs[:, 0, 3] = torch.linspace(-0.2, 0.2, T)
    imgs, depth = [], []
    with torch.no_grad():
        for t in range(T):
            out = rasterize(means, quats, ls, op, col, K, w2cs[t], W, H)
            imgs.append(out.rgb.clamp(0, 1))
            depth.append(torch.full((H, W), 4.0))
    imgs = torch.stack(imgs)
    dynamic = torch.zeros(T, H, W, dtype=torch.bool)
    for t in range(T):
        dynamic[t, 10:20, 8 + 4 * t : 20 + 4 * t] = True
    imgs[dynamic] = torch.rand(int(dynamic.sum()), 3, generator=g)
    return imgs, dynamic, torch.stack(depth), Ks, w2cs


def test_static_weights_match_scipy_dilation_and_erosion():
    rng = np.random.default_rng(0)
    dyn = rng.random((3, 20, 30)) > 0.97
    w = static_weights(torch.from_numpy(dyn), 2).numpy()
    ref = ~np.stack([ndimage.binary_dilation(d, np.ones((5, 5), bool)) for d in dyn])
    np.testing.assert_array_equal(w > 0.5, ref)
    sw = ssim_weights(torch.from_numpy(ref.astype(np.float32))).numpy()
    # 1 exactly where the 11x11 window around the (valid-region) pixel holds no dynamic pixel.
    er = np.stack([ndimage.binary_erosion(r, np.ones((11, 11), bool), border_value=1) for r in ref])
    np.testing.assert_array_equal(sw > 0.5, er[:, 5:-5, 5:-5])


def make_warmup(cfg: StaticWarmupConfig, video):
    imgs, dyn, depth, Ks, w2cs = video
    torch.manual_seed(0)
    return StaticWarmup(cfg, imgs, dyn, depth, Ks, w2cs, extent=1.0, seed=0)


def test_dynamic_pixels_do_not_contribute():
    video = tiny_video()
    cfg = StaticWarmupConfig(steps=10, dilate_px=2, init_stride_px=3)
    sw = make_warmup(cfg, video)
    imgs = video[0]
    # Change the targets on the dilated dynamic region only.
    grown = static_weights(video[1], cfg.dilate_px) < 0.5
    other = imgs.clone()
    other[grown] = 1.0 - other[grown]

    def loss_and_grads(targets):
        sw.images = targets
        for p in sw.gaussians.params.values():
            p.grad = None
        out = sw.render(1)
        loss, _ = sw.frame_loss(1, out)
        loss.backward()
        return float(loss.detach()), {k: v.grad.clone() for k, v in sw.gaussians.params.items()}

    la, ga = loss_and_grads(imgs)
    lb, gb = loss_and_grads(other)
    assert la == lb
    for k in ga:
        torch.testing.assert_close(ga[k], gb[k], rtol=0, atol=0)
    # ...while a change on a static pixel does change the loss (the check above can fail).
    third = imgs.clone()
    third[1, 28:31, 40:44] = 0.0
    lc, _ = loss_and_grads(third)
    assert lc != la


def test_warmup_decreases_the_masked_loss():
    video = tiny_video(1)
    cfg = StaticWarmupConfig(
        steps=120,
        init_stride_px=3,
        lambda_depth=0.05,
        strategy=DensifyStrategy(refine_start=40, refine_stop=100, refine_every=40, reset_every=0),
    )
    sw = make_warmup(cfg, video)

    @torch.no_grad()
    def mean_loss():
        return float(np.mean([float(sw.frame_loss(i, sw.render(i))[0]) for i in range(T)]))

    before = mean_loss()
    summary = Trainer(TrainerConfig(steps=cfg.steps, checkpoint_every=0), sw, progress=False).fit()
    after = mean_loss()
    assert summary.end_step == 120
    assert after < 0.6 * before, (before, after)
    assert len(sw.gaussians) > 0 and torch.isfinite(sw.gaussians.means).all()


def test_quick_preset_is_smaller_than_paper():
    q, p = quick_static_warmup_config(), StaticWarmupConfig()
    assert q.steps < p.steps == 6000


def test_initial_points_grow_with_the_training_image():
    """The bound on initial points is ``init_max_points``, raised to ``init_points_per_pixel`` per pixel of a
    training image: the quick preset's 4,000 stay at 160x90 and 240x135 and become 15,552 at 480x270; a warm-up
    starts with exactly that many of its candidates (static grid pixels of every frame) when it has more."""
    from worldtree.stages.static_warmup import initial_points

    q = quick_static_warmup_config()
    assert initial_points(q, 90, 160) == initial_points(q, 135, 240) == 4000
    assert initial_points(q, 270, 480) == 15_552
    assert initial_points(StaticWarmupConfig(), 270, 480) == 20_000  # paper: no per-pixel rule
    video = tiny_video(2)
    static_grid = int(static_weights(video[1], 3)[:, ::1, ::1].gt(0.5).sum())  # stride 1: every static pixel
    for per_px, expected in ((0.0, 50), (0.25, W * H // 4)):
        cfg = StaticWarmupConfig(steps=1, init_stride_px=1, init_max_points=50, init_points_per_pixel=per_px)
        assert expected < static_grid
        assert len(make_warmup(cfg, video).gaussians) == expected
