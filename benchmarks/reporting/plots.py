"""Speed against error: one point per configuration (its mean over the common scenes, as the table's mean
column), the Pareto front marked, drawn with matplotlib's Agg canvas (no display needed).

Error metrics are the harness's (``mavge``, ``lpips``, ...) or two derived from PSNR, as in AVGE's first
factor: ``mse = 10^(-psnr/10)`` and ``mmse = 10^(-mpsnr/10)`` (the mean squared error on [0, 1] values). When
a default error metric has no value (LPIPS, and with it AVGE, is empty when the LPIPS weights are missing),
its fallback is plotted instead and a note says so.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from benchmarks.reporting.results import METRICS, higher_is_better
from benchmarks.reporting.tables import LABELS, build_wide
from worldtree.infra.errors import UserError

#: Metrics derived per run from PSNR: name -> source metric.
DERIVED = {"mse": "psnr", "mmse": "mpsnr"}
AXIS_METRICS = METRICS + tuple(DERIVED)
#: Error metrics plotted by default, one panel each.
DEFAULT_Y = ("mavge", "lpips")
#: What to plot instead of a metric without values.
FALLBACK = {"mavge": "mmse", "avge": "mse", "lpips": "mse", "mlpips": "mmse"}
PLOT_SUFFIXES = (".png", ".pdf", ".svg")
_LABELS = {**LABELS, "mse": "MSE = 10^(-PSNR/10)", "mmse": "masked MSE = 10^(-mPSNR/10)"}


def with_derived(long: pd.DataFrame) -> pd.DataFrame:
    """``long`` plus rows of :data:`DERIVED` metrics computed per run (``10^(-psnr/10)``; NaN stays NaN,
    PSNR = +inf gives 0)."""
    extra = []
    for name, src in DERIVED.items():
        rows = long[long["metric"] == src].copy()
        rows["metric"] = name
        rows["value"] = np.power(10.0, -rows["value"].to_numpy(np.float64) / 10.0)
        extra.append(rows)
    return pd.concat([long, *extra], ignore_index=True)


def pareto_front(
    x: Sequence[float], y: Sequence[float], x_higher: bool = False, y_higher: bool = False
) -> np.ndarray:
    """Bool [N]: True for points no other point dominates (at least as good in both, better in one).

    ``x_higher``/``y_higher``: larger is better on that axis (default smaller). NaN points are never on the
    front; identical points are either both on it or both off. O(N log N) sweep.
    """
    xs = np.asarray(x, dtype=np.float64) * (-1.0 if x_higher else 1.0)
    ys = np.asarray(y, dtype=np.float64) * (-1.0 if y_higher else 1.0)
    on = np.zeros(len(xs), dtype=bool)
    ok = np.flatnonzero(~(np.isnan(xs) | np.isnan(ys)))
    order = ok[np.lexsort((ys[ok], xs[ok]))]  # by x, then y, both ascending
    best_x, best_y = math.nan, math.inf
    for i in order:
        if ys[i] < best_y:
            on[i], best_x, best_y = True, xs[i], ys[i]
        elif ys[i] == best_y and xs[i] == best_x:
            on[i] = True  # a duplicate of the point that set the front
    return on


@dataclass
class Panel:
    """The points of one speed-vs-error panel."""

    points: pd.DataFrame
    """Group keys, ``x``, ``y``, ``pareto`` (bool), ``label``; one row per configuration with both values."""
    x: str
    y: str
    scenes: tuple[str, ...]
    """Scenes averaged into each point."""
    notes: list[str] = field(default_factory=list)


def resolve_y(long: pd.DataFrame, y: str | None, default: str) -> tuple[str, list[str]]:
    """The error metric to plot: ``y`` if given (UserError when it has no value), else ``default`` or its
    :data:`FALLBACK` chain's first metric with a value."""
    have = set(long.loc[np.isfinite(long["value"].to_numpy(np.float64)), "metric"])
    if y is not None:
        if y not in AXIS_METRICS:
            raise UserError(f"--y {y}: unknown metric; choose from {', '.join(AXIS_METRICS)}")
        if y not in have:
            fb = FALLBACK.get(y)
            hint = f" (try --y {fb})" if fb else ""
            raise UserError(f"--y {y}: no finished run has a value for it{hint}")
        return y, []
    name, notes = default, []
    while name not in have and name in FALLBACK:
        notes.append(f"{name} has no value (LPIPS weights missing?); plotting {FALLBACK[name]} instead")
        name = FALLBACK[name]
    if name not in have:
        raise UserError(
            f"no finished run has a value for {default} or its fallback {name}; choose one with --y"
        )
    return name, notes


def make_panel(
    long: pd.DataFrame, x: str, y: str, group_by: Sequence[str] = ("method", "configuration")
) -> Panel:
    """Mean ``x`` and ``y`` per configuration over the common scenes, with the Pareto front flagged.
    ``long`` must hold one protocol and include derived metrics (:func:`with_derived`) when they are used."""
    if x not in AXIS_METRICS:
        raise UserError(f"--x {x}: unknown metric; choose from {', '.join(AXIS_METRICS)}")
    table = build_wide(long, group_by, metrics=(x, y) if x != y else (x,), mean_only=True)
    frame = table.frame
    pts = frame[list(group_by)].copy()
    pts["x"] = frame[table.mean_column(x)].to_numpy(np.float64)
    pts["y"] = frame[table.mean_column(y)].to_numpy(np.float64)
    notes = list(table.notes)
    bad = ~np.isfinite(pts["x"].to_numpy()) | ~np.isfinite(pts["y"].to_numpy())
    if bad.any():
        labels = [" ".join(str(v) for v in r) for r in pts.loc[bad, list(group_by)].itertuples(index=False)]
        notes.append(f"left out (no finite {x} or {y}): {'; '.join(labels)}")
    pts = pts[~bad].reset_index(drop=True)
    if pts.empty:
        raise UserError(
            f"no configuration has finite values of both {x} and {y} over common scenes; see the notes"
        )
    pts["pareto"] = pareto_front(pts["x"], pts["y"], higher_is_better(x), higher_is_better(y))
    pts["label"] = [
        " ".join(str(v) for v in r if str(v)) for r in pts[list(group_by)].itertuples(index=False)
    ]
    return Panel(pts, x, y, table.mean_scenes, notes)


def _axis_label(metric: str) -> str:
    return f"{_LABELS.get(metric, metric)} ({'higher' if higher_is_better(metric) else 'lower'} is better)"


def short_labels(labels: Sequence[str]) -> list[str]:
    """The words (space-separated) of each label that not every label shares, in their order: what tells the
    points apart (``"worldtree quick depth=2 split=binary"`` and ``"worldtree quick depth=auto split=binary"``
    give ``"depth=2"`` and ``"depth=auto"``). A single label, or one with nothing of its own, is kept whole."""
    words = [str(lab).split() for lab in labels]
    if len(words) < 2:
        return [str(lab) for lab in labels]
    common = set(words[0]).intersection(*words[1:])
    out = [" ".join(w for w in ws if w not in common) for ws in words]
    return [o if o else str(lab) for o, lab in zip(out, labels, strict=True)]


def draw(panels: Sequence[Panel], path: str | Path, dpi: int = 150) -> None:
    """Draw ``panels`` side by side into ``path`` (.png, .pdf or .svg), atomically."""
    from worldtree.infra.atomic import atomic_write_bytes

    path = Path(path)
    if path.suffix.lower() not in PLOT_SUFFIXES:
        raise UserError(f"-o {path}: give a file name ending in {', '.join(PLOT_SUFFIXES)}")
    fig = figure(panels)
    buf = io.BytesIO()
    fig.savefig(buf, format=path.suffix.lower().lstrip("."), dpi=dpi)
    atomic_write_bytes(path, buf.getvalue())


def figure(panels: Sequence[Panel]):
    """The matplotlib ``Figure`` of :func:`draw`: one axes per panel, points labelled by what differs between
    them (:func:`short_labels`; the full labels are in the legend's method colours and the command's listing).
    Labels are left out of the layout, so long ones run past the axes instead of shrinking them."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4 * len(panels), 5.0), layout="constrained")
    FigureCanvasAgg(fig)
    for k, p in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), k + 1)
        key = p.points[p.points.columns[0]].astype(str)  # the first group key, normally the method
        methods = sorted(key.unique())
        colours = {m: f"C{i % 10}" for i, m in enumerate(methods)}
        for m in methods:
            sel = p.points[key == m]
            ax.scatter(sel["x"], sel["y"], s=36, color=colours[m], label=m, zorder=3)
        front = p.points[p.points["pareto"]].sort_values(["x", "y"])
        # The boundary of the region the front dominates: along x at each front point's y until the next one.
        ax.plot(front["x"], front["y"], color="crimson", ls="--", lw=1.2, drawstyle="steps-post", zorder=2)
        ax.scatter(
            front["x"],
            front["y"],
            s=130,
            facecolors="none",
            edgecolors="crimson",
            lw=1.6,
            zorder=4,
            label="Pareto front",
        )
        for (_, r), text in zip(p.points.iterrows(), short_labels(list(p.points["label"])), strict=True):
            note = ax.annotate(text, (r["x"], r["y"]), xytext=(4, 4), textcoords="offset points", fontsize=7)
            note.set_in_layout(False)
        xs = p.points["x"].to_numpy()
        if (xs > 0).all() and xs.max() / xs.min() > 30:
            ax.set_xscale("log")
        ax.margins(x=0.15, y=0.08)  # room for the rightmost point's label inside the figure
        ax.set_xlabel(_axis_label(p.x))
        ax.set_ylabel(_axis_label(p.y))
        ax.set_title(f"mean over {', '.join(p.scenes)}", fontsize=9)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    return fig


# ---------------------------------------------------------------------------------------------- over time

#: Characters of a legend entry of :func:`curves_figure`; longer labels are cut (the page's key has them whole).
LEGEND_CHARS = 60


@dataclass
class Curve:
    """One run's per-frame scores for :func:`curves_figure`."""

    label: str
    t: np.ndarray
    """Time of each test frame."""
    values: dict[str, np.ndarray]
    """Metric -> score of each frame (NaN or infinite: a gap)."""


def curves_figure(curves: Sequence[Curve], metrics: Sequence[str]):
    """Per-frame scores over time: one axes per metric side by side, one line per curve, and one legend for
    all axes below them (outside the axes, so that long labels never shrink the plots; labels cut to
    :data:`LEGEND_CHARS`, as many columns as the figure's width holds)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from benchmarks.reporting.names import cut

    fontsize = 7
    width = 6.0 * len(metrics)
    labels = [cut(c.label, LEGEND_CHARS) for c in curves]
    # About 0.6 em per character plus the line sample and the gap between columns.
    entry_in = (max((len(s) for s in labels), default=1) * 0.6 * fontsize + 40) / 72
    ncols = max(1, min(len(curves), int(width * 0.95 // entry_in)))
    rows = -(-len(curves) // ncols)
    fig = Figure(figsize=(width, 3.6 + rows * fontsize * 1.6 / 72), layout="constrained")
    FigureCanvasAgg(fig)
    handles = []
    for k, m in enumerate(metrics):
        ax = fig.add_subplot(1, len(metrics), k + 1)
        for i, c in enumerate(curves):
            y = np.asarray(c.values.get(m, np.full(len(c.t), np.nan)), dtype=np.float64)
            # Infinite PSNR (a frame equal to the ground truth) cannot be drawn; it is left as a gap.
            y = np.where(np.isfinite(y), y, np.nan)
            (line,) = ax.plot(c.t, y, marker=".", ms=4, lw=1.2, color=f"C{i % 10}")
            if k == 0:
                handles.append(line)
        ax.set_xlabel("test frame time")
        ax.set_ylabel(f"{_LABELS.get(m, m)} (dB, higher is better)")
        ax.grid(True, alpha=0.3)
    if handles:
        fig.legend(handles, labels, loc="outside lower center", ncols=ncols, fontsize=fontsize, frameon=False)
    return fig
