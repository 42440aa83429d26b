"""The per-frame plot of the report's scene pages (benchmarks.reporting.plots.curves_figure): with labels of
150 characters the axes keep most of the figure and the legend stays inside it."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.reporting.plots import LEGEND_CHARS, Curve, curves_figure


def _curves(n: int, label_chars: int) -> list[Curve]:
    rng = np.random.default_rng(1)
    t = np.linspace(0.0, 1.0, 12)
    out = []
    for i in range(n):
        head = f"run{i} worldtree quick "
        label = (head + "priors.depth_import.kind=disparity " * 10)[:label_chars]
        vals = {"psnr": 20 + rng.normal(0, 1, t.size), "mpsnr": 21 + rng.normal(0, 1, t.size)}
        vals["psnr"][3] = np.inf  # a frame equal to the ground truth: a gap
        out.append(Curve(label, t, vals))
    return out


@pytest.mark.parametrize("metrics", [("psnr", "mpsnr"), ("psnr",)])
@pytest.mark.parametrize("n", [1, 5, 12])
def test_axes_keep_the_figure_with_150_character_labels(metrics, n):
    curves = _curves(n, 150)
    assert all(len(c.label) >= 150 for c in curves)
    fig = curves_figure(curves, metrics)
    fig.canvas.draw()
    axes = fig.axes
    assert len(axes) == len(metrics)
    # Axes share the figure: together at least 60 % of its width, each at least half its height.
    assert sum(ax.get_position().width for ax in axes) >= 0.6
    assert all(ax.get_position().height >= 0.5 for ax in axes)
    # One legend, below the axes, inside the figure, listing every run with its label cut.
    (legend,) = fig.legends
    renderer = fig.canvas.get_renderer()
    box = legend.get_window_extent(renderer)
    fig_box = fig.bbox
    assert box.x0 >= fig_box.x0 - 1 and box.x1 <= fig_box.x1 + 1 and box.y0 >= fig_box.y0 - 1
    assert all(box.y1 <= ax.get_window_extent(renderer).y0 for ax in axes)
    texts = [t.get_text() for t in legend.get_texts()]
    assert len(texts) == n and all(len(s) <= LEGEND_CHARS for s in texts)
    assert len(set(texts)) == n  # the cut keeps the names apart here (their starts differ)


def test_short_labels_unchanged():
    curves = _curves(3, 30)
    fig = curves_figure(curves, ("psnr",))
    fig.canvas.draw()
    assert [t.get_text() for t in fig.legends[0].get_texts()] == [c.label for c in curves]
