"""Which raw time steps are kept, and which rig camera supplies each training frame."""

from __future__ import annotations

import numpy as np

from worldtree.infra.errors import UserError


def sample_times(times: list[int], frames: int) -> list[int]:
    """Keep all of ``times`` when there are at most ``frames``, else ``frames`` uniformly spaced ones.

    The first and last time steps are always kept; indices are ``round(linspace(0, n - 1, frames))``, which are
    distinct whenever ``frames <= n``.
    """
    if frames < 1:
        raise UserError(f"--frames {frames}: must be at least 1")
    n = len(times)
    if n <= frames:
        return list(times)
    idx = np.round(np.linspace(0, n - 1, frames)).astype(np.int64)
    return [times[i] for i in idx]


def training_cameras(cameras: list[int], test_camera: int) -> list[int]:
    """The rig cameras used for training: all but the test camera, in id order."""
    if test_camera not in cameras:
        raise UserError(
            f"--test-camera {test_camera}: the rig has cameras {cameras[0]}..{cameras[-1]}; pick one of them"
        )
    train = [c for c in cameras if c != test_camera]
    if not train:
        raise UserError("the rig has only the test camera; at least 2 cameras are needed")
    return train


def pingpong(train: list[int], num_frames: int) -> list[int]:
    """Camera of each training frame: ``train[0], train[1], ..., train[-1], train[-2], ..., train[1], train[0], ...``.

    With 11 training cameras (2..12) the period is 20: 2, 3, ..., 12, 11, ..., 3, then 2 again.
    """
    m = len(train)
    if m == 1:
        return [train[0]] * num_frames
    period = 2 * (m - 1)
    out = []
    for t in range(num_frames):
        k = t % period
        out.append(train[k if k < m else period - k])
    return out
