"""The viewer's view of a loaded run (:class:`benchmarks.viewer.source.RunSource`) on a stand-in for
``benchmarks.api.LoadedRun`` with only the members the viewer uses, and a viewer started and stopped without a
browser on a run without test views (own video)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks.viewer.source import RunSource, find_test_camera


@dataclass(frozen=True)
class _Cam:
    name: str
    kind: str
    K: torch.Tensor
    w2c: torch.Tensor
    width: int
    height: int
    time: int


class _Run:
    """Times 10, 20, 30 (not 0..2: the slider's index must be mapped to them)."""

    def __init__(self, with_test: bool = True, tree: bool = False) -> None:
        K = torch.tensor([[40.0, 0, 15.5], [0, 40.0, 11.5], [0, 0, 1]])
        self.folder = Path("runs/SceneX/base/quick")
        self.record = {"method": "base"}
        self.device = torch.device("cpu")
        self.times = [10, 20, 30]
        self.cameras = {}
        for i, t in enumerate(self.times):
            w2c = torch.eye(4)
            w2c[0, 3] = -0.1 * i
            self.cameras[f"train_{i:03d}"] = _Cam(f"train_{i:03d}", "train", K, w2c, 32, 24, t)
        if with_test:
            self.cameras["test"] = _Cam("test", "test", K, torch.eye(4), 32, 24, 10)
        self.tree = tree
        self.calls = []

    def render(self, camera, time, mode="rgb"):
        self.calls.append((camera, time, mode))
        return torch.full((24, 32, 3), time / 100.0)

    def node_at(self, time):
        return {10: 1, 20: 2, 30: 3}[time] if self.tree else None


def test_run_source_maps_cameras_times_and_nodes():
    run = _Run(tree=True)
    src = RunSource(run)
    assert src.title == "SceneX / base / quick" and src.device == "cpu"
    assert src.times == [10, 20, 30]
    names = [c.name for c in src.cameras]
    assert names == ["train_000", "train_001", "train_002", "test"]
    train1 = src.cameras[1]
    assert train1.time == 1 and not train1.is_test  # an index into times, not the time 20
    assert train1.K.dtype == np.float64 and train1.w2c[0, 3] == pytest.approx(-0.1)
    test = find_test_camera(src)
    assert test is not None and test.is_test and test.time is None
    # A named camera is rendered as the run's own camera object (so the test camera gets its refined pose) ...
    src.render(test, 2, "depth")
    assert run.calls[-1] == (run.cameras["test"], 30, "depth")
    # ... a free camera by its numbers.
    free = (np.eye(3), np.eye(4), 16, 12)
    src.render(free, 0, "rgb")
    assert run.calls[-1] == (free, 10, "rgb")
    assert [src.node_label(i) for i in range(3)] == ["1", "2", "3"]
    assert RunSource(_Run(tree=False)).node_label(0) is None


def test_viewer_of_a_run_without_test_views_starts_and_stops():
    from benchmarks.viewer.server import Viewer

    src = RunSource(_Run(with_test=False))
    assert find_test_camera(src) is None
    viewer = Viewer(src, port=0, max_size=None)
    try:
        assert viewer.initial_camera is not None and viewer.initial_camera.name == "train_000"
        assert viewer.max_size == 32  # the run's image size
        assert viewer.url.startswith("http://127.0.0.1:") and viewer.port > 0
        assert viewer.mode_menu.options == ("colour", "depth", "dynamic part")  # no tree: no tree-node mode
        viewer.time_slider.value = 2
        assert viewer.time_index() == 2
    finally:
        viewer.stop()
