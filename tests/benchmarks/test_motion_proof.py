"""The motion proof's track figures on synthetic tracks with a known answer (benchmarks.speed.motion_proof)."""

import numpy as np
import pytest

from benchmarks.speed.motion_proof import accuracy_row, track_errors, track_life

T = 8


def _exact_grid() -> tuple[np.ndarray, np.ndarray]:
    """Exact tracks on a 2 px grid, all translating by (1.5, -0.5) px per frame; one hidden at frames 2-4."""
    gx, gy = np.meshgrid(np.arange(10.0, 30.0, 2.0), np.arange(20.0, 40.0, 2.0))
    start = np.stack([gx.ravel(), gy.ravel()], -1)
    t = np.arange(T, dtype=np.float64)[:, None, None]
    xy = (start[None] + t * np.array([1.5, -0.5])).astype(np.float32)
    vis = np.ones(xy.shape[:2], bool)
    vis[2:5, 0] = False
    return xy, vis


def test_track_life_is_the_median_visible_frames_of_the_dynamic_tracks():
    vis = np.zeros((10, 3), bool)
    vis[:2, 0] = True
    vis[3:8, 1] = True
    vis[:, 2] = True
    assert track_life(vis, np.array([True, True, False])) == (2, 3.5)
    assert track_life(vis, np.array([False, False, False]))[0] == 0


def test_track_errors_against_the_exact_motion():
    gt_xy, gt_vis = _exact_grid()
    t = np.arange(T, dtype=np.float64)
    xy = np.zeros((T, 4, 2), np.float32)
    vis = np.zeros((T, 4), bool)
    # 0: follows the motion from between grid points; 1: drifts 0.4 px/frame in x on top of it, from frame 2;
    # 2: starts far from every exact track; 3: follows the motion with a 3-frame hole.
    xy[:, 0] = np.stack([15.0 + 1.5 * t, 25.0 - 0.5 * t], -1)
    vis[:, 0] = True
    xy[2:, 1] = np.stack([20.0 + 1.5 * (t[2:] - 2) + 0.4 * (t[2:] - 2), 30.0 - 0.5 * (t[2:] - 2)], -1)
    vis[2:, 1] = True
    xy[:, 2] = [[80.0, 80.0]]
    vis[:, 2] = True
    xy[:, 3] = np.stack([12.0 + 1.5 * t, 22.0 - 0.5 * t], -1)
    vis[:, 3] = True
    vis[3:6, 3] = False
    err = track_errors(xy, vis, gt_xy, gt_vis)
    assert err[0] == pytest.approx(0.0, abs=1e-4)
    assert err[1] == pytest.approx(0.4 * (T - 1 - 2), abs=1e-4)
    assert np.isnan(err[2])
    assert err[3] == pytest.approx(0.0, abs=1e-4)
    acc = accuracy_row(
        xy, vis, np.array([True, True, True, False]), np.array([1, 2, 1, 3]), (gt_xy, gt_vis, None), 1.0
    )
    # Dynamic tracks with a reference: 0 (accurate) and 1 (2 px off); the only linked one among them is 1.
    assert acc == {"accurate": 0.5, "linked": 1, "linked_accurate": 0.0}


def test_track_errors_follow_a_rotating_object():
    # Exact tracks on a disc turning 0.2 rad per frame about (40, 40): neighbours 2 px apart move differently,
    # so the reference must map them affinely; a point between them that turns with the disc has no error,
    # one that translates with the mean of its neighbours' motion has.
    gx, gy = np.meshgrid(np.arange(30.0, 52.0, 2.0), np.arange(30.0, 52.0, 2.0))
    p0 = np.stack([gx.ravel(), gy.ravel()], -1) - 40.0
    ang = 0.2 * np.arange(T)

    def turn(p):
        c, s = np.cos(ang)[:, None], np.sin(ang)[:, None]
        return 40.0 + np.stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1]], -1)

    gt_xy = turn(p0).astype(np.float32)
    gt_vis = np.ones(gt_xy.shape[:2], bool)
    start = np.array([[9.0, 5.0]])  # (49, 45): between grid points, 10 px from the centre
    xy = turn(start).astype(np.float32)
    vis = np.ones((T, 1), bool)
    assert track_errors(xy, vis, gt_xy, gt_vis)[0] == pytest.approx(0.0, abs=1e-3)
    moved = xy[0] + (xy - xy[0]) * 0.8  # lags behind the turn
    lag = float(np.linalg.norm(xy[-1, 0] - moved[-1, 0]))
    assert track_errors(moved, vis, gt_xy, gt_vis)[0] == pytest.approx(lag, rel=1e-3)
