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


def _brute_view_count(p, Ks, w2cs, width, height):
    """How many cameras have point ``p`` in front and inside the image, one camera at a time in float64."""
    n = 0
    for K, w2c in zip(Ks.double(), w2cs.double(), strict=True):
        c = w2c[:3, :3] @ p.double() + w2c[:3, 3]
        if c[2] <= 1e-6:
            continue
        u, v = (K[0, 0] * c[0] / c[2] + K[0, 2]).item(), (K[1, 1] * c[1] / c[2] + K[1, 2]).item()
        n += int(-0.5 <= u < width - 0.5 and -0.5 <= v < height - 0.5)
    return n


def test_view_counts_match_a_camera_by_camera_count():
    """Random points (some behind every camera, some outside every image) against a per-point, per-camera
    count; a point behind a camera is never counted, whatever it projects to."""
    from worldtree.stages.static_warmup import view_counts

    g = torch.Generator().manual_seed(3)
    _, _, _, Ks, w2cs = tiny_video(0)
    pts = (torch.rand(300, 3, generator=g) - 0.5) * torch.tensor([12.0, 8.0, 16.0]) + torch.tensor([0, 0, 2.0])
    got = view_counts(pts, Ks, w2cs, W, H)
    want = torch.tensor([_brute_view_count(p, Ks, w2cs, W, H) for p in pts])
    assert torch.equal(got, want)
    assert (want == 0).any() and (want == T).any() and ((want > 0) & (want < T)).any()  # every case occurs
    behind = torch.tensor([[0.1, 0.0, -4.0]])  # mirrors a visible point through the camera centre
    assert int(view_counts(behind, Ks, w2cs, W, H)[0]) == 0


def test_view_counts_scale_a_camera_subset_back_to_all_frames(monkeypatch):
    """With more frames than the counted subset, a point every camera sees counts T and an unseen one 0."""
    import worldtree.stages.static_warmup as sw

    monkeypatch.setattr(sw, "VIEW_COUNT_CAMERAS", 3)
    _, _, _, Ks, w2cs = tiny_video(0)
    Ks, w2cs = Ks.repeat(5, 1, 1), w2cs.repeat(5, 1, 1)  # 20 frames
    pts = torch.tensor([[0.0, 0.0, 4.0], [0.0, 0.0, -4.0]])
    assert sw.view_counts(pts, Ks, w2cs, W, H).tolist() == [20, 0]


def test_balanced_initial_points_fill_what_one_camera_sees():
    """A wall seen by a row of cameras, each sliding further right: the strip that only the first camera sees
    gets 1 / T of the uniform draw's candidates but, drawn with weight 1 / views, about the density of the
    rest of the wall (points per unit area within a factor 2), where the uniform draw leaves it several times
    sparser."""
    from worldtree.stages.static_warmup import lift_pixels, view_counts

    T_, Hh, Ww = 8, 40, 60
    K = torch.tensor([[50.0, 0, (Ww - 1) / 2], [0, 50.0, (Hh - 1) / 2], [0, 0, 1]])
    Ks = K[None].repeat(T_, 1, 1)
    w2cs = torch.eye(4)[None].repeat(T_, 1, 1)
    w2cs[:, 0, 3] = -torch.arange(T_, dtype=torch.float32) * 0.5  # camera t centred at x = 0.5 t
    depth = torch.full((T_, Hh, Ww), 5.0)
    images = torch.rand(T_, Hh, Ww, 3, generator=torch.Generator().manual_seed(0))
    mask = torch.ones(T_, Hh, Ww)
    half_width = 5.0 * (Ww / 2) / 50.0  # the wall's half extent one camera sees at depth 5
    strip = (-half_width, -half_width + 0.5)  # seen by camera 0 alone
    densities = {}
    for balance in (False, True):
        P, _, _ = lift_pixels(images, depth, mask, Ks, w2cs, 1, 3000, torch.Generator().manual_seed(1), balance)
        counts = view_counts(P, Ks, w2cs, Ww, Hh)
        in_strip = (P[:, 0] >= strip[0]) & (P[:, 0] < strip[1])
        assert (counts[in_strip] == 1).all()
        middle = (P[:, 0] >= 1.0) & (P[:, 0] < 2.0)  # 1 unit wide, seen by many cameras
        assert (counts[middle] > 2).all()
        densities[balance] = (in_strip.sum().item() / 0.5, middle.sum().item() / 1.0)
    uniform, balanced = densities[False], densities[True]
    assert uniform[0] * 3 < uniform[1]  # the uniform draw: the edge several times sparser
    assert 0.5 < balanced[0] / balanced[1] < 2.0  # balanced: about even
