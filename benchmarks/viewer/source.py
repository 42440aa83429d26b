"""What the viewer asks of a run: :class:`ViewSource`, and :func:`open_run`, its implementation over the Python
API's loaded run (``benchmarks.api.load_run``), which works for every registered method."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np


@dataclass(frozen=True)
class ViewCamera:
    """A named camera of the run (a training frame or the test camera)."""

    name: str
    """Shown in the viewer (and the frustum's name)."""
    K: np.ndarray
    """``[3, 3]`` pixel intrinsics."""
    w2c: np.ndarray
    """``[4, 4]`` OpenCV world-to-camera pose in the scene's frame."""
    width: int
    """Image width, pixels."""
    height: int
    """Image height, pixels."""
    time: int | None
    """Index into :attr:`ViewSource.times` of the frame this camera took, None for the test camera (it sees
    every time)."""
    is_test: bool
    """The scene's held-out test camera (a method may render it with what it learnt about it)."""
    key: Any = None
    """What the source's :meth:`ViewSource.render` takes to render this very camera (its own object)."""


#: A camera given by its numbers: ``(K [3, 3], w2c [4, 4], width, height)``.
FreeCamera = tuple[np.ndarray, np.ndarray, int, int]


class ViewSource(Protocol):
    """A finished run as the viewer sees it. Implementations must allow :meth:`render` from one thread at a
    time (the viewer serialises its calls)."""

    title: str
    """Shown at the top of the viewer's panel (e.g. ``scene / method / tag``)."""
    cameras: Sequence[ViewCamera]
    """Training frames and the test camera."""
    times: Sequence[Any]
    """The run's times in order; the time slider picks an index into them."""
    device: str
    """Where rendering runs (``cpu``, ``cuda:0``), shown in the panel."""

    def render(self, camera: ViewCamera | FreeCamera, time: int, mode: str):
        """Render ``camera`` at time index ``time``; ``mode``: ``rgb`` (``[H, W, 3]`` in [0, 1]), ``depth``
        (``[H, W]`` world units, 0 where nothing is drawn) or ``dynamic`` (``[H, W, 3]``, the moving part
        only). Returns a torch tensor or numpy array on any device."""
        ...

    def node_label(self, time: int) -> str | None:
        """The tree node that renders time index ``time`` (e.g. ``node 3 [12, 25]``); None for methods without
        a tree."""
        ...


def find_test_camera(source: ViewSource) -> ViewCamera | None:
    """The source's test camera, or None."""
    return next((c for c in source.cameras if c.is_test), None)


class RunSource:
    """:class:`ViewSource` of a finished run loaded with ``benchmarks.api.load_run`` (any registered method)."""

    def __init__(self, run) -> None:
        self.run = run
        self.times = list(run.times)
        index = {t: i for i, t in enumerate(self.times)}
        record = getattr(run, "record", {}) or {}
        folder = Path(run.folder)
        self.title = (
            f"{folder.parent.parent.name} / {record.get('method', folder.parent.name)} / {folder.name}"
        )
        self.device = str(run.device)
        cams = []
        for c in run.cameras.values():
            is_test = c.kind == "test"
            cams.append(
                ViewCamera(
                    name=c.name,
                    K=_array(c.K),
                    w2c=_array(c.w2c),
                    width=int(c.width),
                    height=int(c.height),
                    time=None if is_test else index.get(int(c.time)),
                    is_test=is_test,
                    key=c,
                )
            )
        self.cameras = cams

    def render(self, camera: ViewCamera | FreeCamera, time: int, mode: str):
        what = camera.key if isinstance(camera, ViewCamera) else camera
        return self.run.render(what, self.times[time], mode=mode)

    def node_label(self, time: int) -> str | None:
        node = self.run.node_at(self.times[time])
        return None if node is None else str(node)


def open_run(run_dir: Path, device: str | None = None) -> RunSource:
    """Load the finished run in ``run_dir`` on ``device`` (None/"auto": CUDA when present, else the CPU) for the
    viewer; problems are :class:`~worldtree.infra.errors.UserError` lines from the loader."""
    from benchmarks.api import load_run

    return RunSource(load_run(run_dir, device=device))


def _array(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)
