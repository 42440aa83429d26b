"""Static <-> dynamic migration during the photometric fit: a missed moving region is recovered."""

from __future__ import annotations

import sys
from pathlib import Path

import torch

from worldtree.dynamic import DynamicGaussians
from worldtree.optim import GroupedAdam, gaussian_schedules
from worldtree.stages import set_migration as mig
from worldtree.stages.photometric import PhotometricConfig, PhotometricFit

sys.path.insert(0, str(Path(__file__).parent))
from test_stages_photometric import scene  # the tiny scene with a moving object


def test_accumulator_means_match_brute_force():
    g = torch.Generator().manual_seed(0)
    res = [torch.rand(6, 8, generator=g) for _ in range(3)]
    pts = torch.tensor([[1.2, 2.4], [7.0, 5.0], [-3.0, 1.0], [4.6, 0.4]])
    radii = torch.tensor([2, 1, 3, 0])
    acc = mig.ResidualAccumulator(4, torch.device("cpu"))
    for t, r in enumerate(res):
        acc.add(r, pts, radii, t)
    # Point 0 at pixel (x=1, y=2), point 1 at (7, 5); point 2 outside, point 3 culled.
    torch.testing.assert_close(acc.mean()[0], torch.stack([r[2, 1] for r in res]).mean())
    torch.testing.assert_close(acc.mean()[1], torch.stack([r[5, 7] for r in res]).mean())
    assert acc.count.tolist() == [3.0, 3.0, 0.0, 0.0]
    assert int(acc.frame[0]) == int(torch.stack([r[2, 1] for r in res]).argmax())


def test_moves_keep_parameters_and_optimizer_rows():
    _, _, _, _, static, dyn, scf = scene()
    n_s, n_d = len(static), len(dyn)
    s_opt = GroupedAdam(
        dict(static.params.items()), gaussian_schedules(1e-3, 1e-5, 10, 1e-3, 1e-3, 1e-2, 1e-3)
    )
    move = torch.zeros(n_s, dtype=torch.bool)
    move[:7] = True
    moved_means = static.means[:7].detach().clone()
    t_ref = torch.full((n_s,), 3, dtype=torch.long)
    k = mig.static_to_dynamic(static, s_opt, {}, dyn, None, {}, move, t_ref)
    assert k == 7 and len(static) == n_s - 7 and len(dyn) == n_d + 7
    torch.testing.assert_close(dyn.means[-7:], moved_means)
    assert (dyn.t_ref[-7:] == 3).all() and (dyn.skin_correction[-7:] == 0).all()
    assert s_opt.group("means")["params"][0] is static.params["means"]
    back = torch.zeros(len(dyn), dtype=torch.bool)
    back[-7:] = True
    assert mig.dynamic_to_static(static, s_opt, {}, dyn, None, {}, back) == 7
    assert len(static) == n_s and len(dyn) == n_d
    torch.testing.assert_close(static.means[-7:], moved_means)


def test_missed_object_gaussians_become_dynamic():
    imgs, depth, Ks, w2cs, static, dyn, scf = scene()
    # Half of the object was missed by the masks: its Gaussians are in the static set, at the frame-2 position
    # with the object's colour (what a static fit converges to at that frame).
    n_d = len(dyn)
    half = n_d // 2
    missed = dyn.means[half:].detach().clone()
    rows = {
        "means": missed,
        "quats": dyn.quats[half:].detach(),
        "log_scales": dyn.log_scales[half:].detach(),
        "opacity_logits": dyn.params["opacity_logits"][half:].detach(),
        "sh0": dyn.params["sh0"][half:].detach(),
    }
    n_bg = len(static)
    mig.append(static, None, {}, rows)
    keep = torch.zeros(n_d, dtype=torch.bool)
    keep[:half] = True
    dyn = DynamicGaussians({k: v.detach()[keep] for k, v in dyn.params.items()})
    cfg = PhotometricConfig(steps=10, migrate_every=1, migrate_start=0, migrate_stop=10, migrate_frames=5)
    fit = PhotometricFit(cfg, imgs, depth, Ks, w2cs, static, dyn, scf, None, None, extent=5.0)
    fit._migrate(0)
    moved = fit.migration["static_to_dynamic"]
    # The missed Gaussians are the static set's last rows: find where they went by position.
    d = (missed[:, None] - fit.dynamic.means.detach()[None]).norm(dim=-1).min(1).values
    assert float((d < 1e-6).float().mean()) >= 0.8  # most of the missed object is dynamic now
    assert moved - int((d < 1e-6).sum()) <= 0.05 * n_bg  # and hardly any background Gaussian
    assert len(fit.static) + len(fit.dynamic) == n_bg + n_d
    assert fit.migration["events"] == [[0, moved, fit.migration["dynamic_to_static"]]]
