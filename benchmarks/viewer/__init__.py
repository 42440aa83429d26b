"""`wtbench view`: an interactive viewer of a run in the browser (viser), rendered by this project's rasterizer.

Modules: :mod:`~benchmarks.viewer.source` (what the viewer asks of a run: :class:`ViewSource`),
:mod:`~benchmarks.viewer.camera` (viser's camera <-> the project's OpenCV poses, resolution, letterbox),
:mod:`~benchmarks.viewer.frames` (time index, render mode -> displayed image, encoding) and
:mod:`~benchmarks.viewer.server` (the viser wiring). Only the last one imports viser; the others are plain
functions with unit tests. User guide: docs/viewer.md.
"""
