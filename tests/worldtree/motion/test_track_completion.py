"""Trajectory completion from the neighbours' motion: two separate bodies translating differently, each tracked
only by short staggered tracks; the completed trajectories are compared with the known motion."""

from __future__ import annotations

import torch

from worldtree.motion.lift import fill_gaps
from worldtree.motion.track_completion import complete_trajectories

T = 20


def _bodies():
    """Two clusters about 17 apart (radius 0.5 each), A moving (+0.3, 0, 0) per frame, B (0, -0.2, +0.1); each
    point measured in a 5-frame window, windows staggered so every step is measured by some points of each."""
    g = torch.Generator().manual_seed(0)
    n = 24
    start = torch.cat([torch.randn(n, 3, generator=g) * 0.2, torch.randn(n, 3, generator=g) * 0.2 + 10.0])
    vel = torch.cat([torch.tensor([0.3, 0.0, 0.0]).expand(n, 3), torch.tensor([0.0, -0.2, 0.1]).expand(n, 3)])
    t = torch.arange(T, dtype=torch.float32)[:, None, None]
    truth = start[None] + t * vel[None]  # [T, 2n, 3]
    valid = torch.zeros(T, 2 * n, dtype=torch.bool)
    for j in range(2 * n):
        a = (j * 3) % (T - 4)
        valid[a : a + 5, j] = True
    return truth, valid


def test_short_tracks_follow_their_body_through_every_frame():
    truth, valid = _bodies()
    assert valid.any(1).all() and not valid.all(0).any()  # every frame measured, no track measured throughout
    pts = torch.where(valid[..., None], truth, torch.zeros_like(truth))
    done, observed = complete_trajectories(pts, valid, radius=2.0, k=8)
    assert torch.equal(observed, valid)
    assert torch.equal(done[valid], truth[valid])  # measured frames untouched
    # Pure translations: every donor of a body moves by the body's step, so the completion is exact.
    torch.testing.assert_close(done, truth, atol=1e-4, rtol=0)
    held, _ = fill_gaps(pts, valid)
    assert (held - truth).norm(dim=-1).max() > 2.0  # holding the ends misses the motion by metres


def test_no_donor_in_reach_holds_the_ends_like_fill_gaps():
    truth, valid = _bodies()
    pts = torch.where(valid[..., None], truth, torch.zeros_like(truth))
    held, _ = fill_gaps(pts, valid)
    # A radius smaller than any distance between two points: nobody lends a displacement.
    tiny, _ = complete_trajectories(pts, valid, radius=1e-6, k=8)
    torch.testing.assert_close(tiny, held, atol=0, rtol=0)
    off, _ = complete_trajectories(pts, valid, radius=0.0)
    torch.testing.assert_close(off, held, atol=0, rtol=0)


def test_bodies_do_not_borrow_each_others_motion():
    truth, valid = _bodies()
    n = truth.shape[1] // 2
    # Body B is measured only in frames 0..4: afterwards its points have no donor of their own body.
    valid[5:, n:] = False
    pts = torch.where(valid[..., None], truth, torch.zeros_like(truth))
    b = n + torch.nonzero(valid[:, n:].any(0)).flatten()  # B's tracks with a measured frame
    assert b.numel() >= 4
    done, _ = complete_trajectories(pts, valid, radius=2.0, k=8)
    # Followed while B is measured (to frame 4), then held: A's points are far beyond the radius.
    torch.testing.assert_close(done[:5, b], truth[:5, b], atol=1e-4, rtol=0)
    torch.testing.assert_close(done[5:, b], truth[4, b][None].expand(T - 5, -1, -1), atol=1e-4, rtol=0)
    # A radius reaching across (B is 17 away) lends A's motion to B: what the radius is there to stop.
    wide, _ = complete_trajectories(pts, valid, radius=100.0, k=8)
    assert (wide[5:, b] - truth[4, b][None]).norm(dim=-1).max() > 1.0
