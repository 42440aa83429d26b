"""Pixels whose depth a static world cannot hold (free-space violations), against a per-pixel brute force and
closed-form scenes: a wall seen by a row of cameras, a near object at one time only, a point behind a surface."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from worldtree.infra.errors import SettingError
from worldtree.priors.config import FreeSpaceConfig
from worldtree.priors.free_space import comparison_frames, free_space_violations

H, W, F = 24, 32, 30.0


def _rig(T: int, spacing: float = 0.2):
    """``T`` cameras on a row along x, looking down +z (OpenCV), and their intrinsics."""
    K = torch.tensor([[F, 0.0, (W - 1) / 2], [0.0, F, (H - 1) / 2], [0.0, 0.0, 1.0]])
    w2cs = torch.eye(4).repeat(T, 1, 1)
    w2cs[:, 0, 3] = -spacing * (torch.arange(T, dtype=torch.float32) - (T - 1) / 2)
    return K.repeat(T, 1, 1), w2cs


def _wall(T: int, z: float = 10.0):
    """Exact depth of a fronto-parallel wall at camera depth ``z`` in every frame."""
    return torch.full((T, H, W), z)


def _brute(depth, Ks, w2cs, tolerance, views, share, window, min_seen=2):
    """One pixel and one frame at a time, in float64, from the definition (the module doc)."""
    d = depth.double().numpy()
    T = d.shape[0]
    r = window // 2
    out = np.zeros(d.shape, bool)
    for t in range(T):
        Kinv = np.linalg.inv(Ks[t].double().numpy())
        R, tr = w2cs[t, :3, :3].double().numpy(), w2cs[t, :3, 3].double().numpy()
        for v in range(H):
            for u in range(W):
                if not d[t, v, u] > 0:
                    continue
                X = R.T @ (Kinv @ np.array([u, v, 1.0]) * d[t, v, u] - tr)
                seen = hits = 0
                for s in comparison_frames(t, T, views):
                    Rs, ts = w2cs[s, :3, :3].double().numpy(), w2cs[s, :3, 3].double().numpy()
                    c = Rs @ X + ts
                    if c[2] <= 1e-6:
                        continue
                    p = Ks[s].double().numpy() @ (c / c[2])
                    qu, qv = round(p[0]), round(p[1])
                    if not (0 <= qu <= W - 1 and 0 <= qv <= H - 1):
                        continue
                    patch = d[s, max(qv - r, 0) : qv + r + 1, max(qu - r, 0) : qu + r + 1]
                    ref = 0.0 if (patch <= 0).any() else patch.min()
                    if ref > 0:
                        seen += 1
                        hits += c[2] < (1 - tolerance) * ref
                out[t, v, u] = seen >= min_seen and hits >= share * seen
    return torch.from_numpy(out)


def test_a_static_wall_holds_everywhere():
    Ks, w2cs = _rig(5)
    flag = free_space_violations(_wall(5), Ks, w2cs)
    assert not bool(flag.any())


def test_a_near_object_at_one_time_is_flagged_where_it_is_and_nowhere_else():
    # Frame 2 sees an object at 0.3 of the wall's depth; at every other time that place is empty wall, so its
    # points float in front of what every other frame sees. The wall pixels around it stay.
    T = 5
    Ks, w2cs = _rig(T)
    depth = _wall(T)
    obj = torch.zeros(H, W, dtype=torch.bool)
    obj[8:16, 12:20] = True
    depth[2][obj] = 3.0
    flag = free_space_violations(depth, Ks, w2cs)
    assert bool(flag[2][obj].all())
    assert not bool(flag[2][~obj].any())
    others = [t for t in range(T) if t != 2]
    # The wall behind the object is hidden from frame 2 only: other frames' wall points are occluded there, not
    # in free space, so none of them is flagged.
    assert not bool(flag[others].any())


def test_matches_a_per_pixel_brute_force_on_a_noisy_scene():
    gen = torch.Generator().manual_seed(0)
    T = 6
    Ks, w2cs = _rig(T, spacing=0.35)
    depth = 6.0 + 4.0 * torch.rand(T, H, W, generator=gen)  # rough surfaces: many pixels near the threshold
    depth[1, 8:14, 12:18] = 3.0  # a near object in frame 1
    depth[4, 10:14, 20:30] = 0.0  # no depth here
    depth[3, 0, 0] = float("nan")
    for kw in (
        dict(tolerance=0.25, views=8, share=0.5, window=3),
        dict(tolerance=0.1, views=3, share=0.34, window=1),
    ):
        got = free_space_violations(depth, Ks, w2cs, **kw)
        want = _brute(torch.nan_to_num(depth, nan=0.0), Ks, w2cs, **kw)
        assert got.dtype == torch.bool and got.shape == (T, H, W)
        assert torch.equal(got, want)
        assert bool(got[1, 8:14, 12:18].any())
        assert not bool(got[4, 10:14, 20:30].any()) and not bool(got[3, 0, 0])


def test_a_point_behind_what_another_frame_sees_is_occluded_not_flagged():
    # Frame 0 sees farther than the wall (a hole onto a far surface) where the others see the wall: its points
    # lie behind the wall from the other cameras, which a static world allows.
    T = 4
    Ks, w2cs = _rig(T)
    depth = _wall(T)
    depth[0, 6:18, 8:24] = 25.0
    assert not bool(free_space_violations(depth, Ks, w2cs).any())


def test_tolerance_and_share_are_what_decide():
    # An object at 0.8 of the wall's depth: a violation under a 10 % margin, not under 25 %.
    T = 5
    Ks, w2cs = _rig(T)
    depth = _wall(T)
    depth[2, 8:16, 12:20] = 8.0
    assert bool(free_space_violations(depth, Ks, w2cs, tolerance=0.1)[2, 12, 16])
    assert not bool(free_space_violations(depth, Ks, w2cs, tolerance=0.25)[2, 12, 16])
    # Seen by two frames at most (views=2) and needing both: still flagged; with min_seen above 2 it is kept.
    assert bool(free_space_violations(depth, Ks, w2cs, tolerance=0.1, views=2, share=1.0)[2, 12, 16])
    assert not bool(free_space_violations(depth, Ks, w2cs, tolerance=0.1, views=2, min_seen=3)[2, 12, 16])


def test_empty_single_frame_and_behind_the_camera_inputs_are_finite_and_unflagged():
    Ks, w2cs = _rig(1)
    assert not bool(free_space_violations(_wall(1), Ks, w2cs).any())  # nothing to compare with
    Ks, w2cs = _rig(3)
    assert not bool(free_space_violations(torch.zeros(3, H, W), Ks, w2cs).any())
    # A camera turned round sees every other frame's points behind it: no frame sees them, nothing is flagged.
    w2cs[1, :3, :3] = torch.diag(torch.tensor([-1.0, 1.0, -1.0]))
    depth = _wall(3)
    depth[0, 10, 10] = 0.5
    flag = free_space_violations(depth, Ks, w2cs, views=1)
    assert flag.dtype == torch.bool and not bool(flag[1].any())


def test_comparison_frames_are_spread_distinct_and_exclude_the_frame():
    assert comparison_frames(0, 1, 8) == []
    assert comparison_frames(3, 6, 8) == [0, 1, 2, 4, 5]
    got = comparison_frames(5, 160, 8)
    assert len(got) == 8 and 5 not in got and got == sorted(set(got))
    assert got[0] == 0 and got[-1] == 159
    gaps = np.diff(got)
    assert gaps.max() - gaps.min() <= 2  # evenly spread over the video
    assert comparison_frames(2, 10, 0) == []
    # None excludes no frame: the frames a static point is looked at from (the fit's floater removal).
    assert comparison_frames(None, 40, 8) == sorted(set(torch.linspace(0, 39, 8).round().long().tolist()))
    assert comparison_frames(None, 5, 8) == [0, 1, 2, 3, 4]


@pytest.mark.parametrize(
    "kw", [dict(tolerance=0.0), dict(tolerance=1.0), dict(share=0.0), dict(window=2), dict(views=0)]
)
def test_bad_settings_name_the_field(kw):
    with pytest.raises(SettingError, match=f"FreeSpaceConfig.{next(iter(kw))}"):
        FreeSpaceConfig(**kw)


def test_the_function_rejects_bad_arguments():
    Ks, w2cs = _rig(2)
    with pytest.raises(ValueError, match="tolerance"):
        free_space_violations(_wall(2), Ks, w2cs, tolerance=1.5)
    with pytest.raises(ValueError, match="expected depth"):
        free_space_violations(_wall(2)[0], Ks, w2cs)
    assert math.isfinite(float(free_space_violations(_wall(2), Ks, w2cs).sum()))
