"""The wide table of finished runs: one row per configuration, per-scene and mean columns per metric, and its
CSV, markdown and LaTeX renderings with the best, second and third value of each column marked.

Rules (docs/tables.md):

- a cell is the mean over the runs of its (row, scene), e.g. several seeds (NaN values left out);
- the mean column of a metric averages the per-scene cells over the scenes that EVERY row has a run for (the
  "common" scenes) and names them in its header, ``psnr:mean(Balloon1, Jumping)``; a row with no value in one
  of them gets an empty mean. Scenes missing for some row keep their own column and are noted;
- ranks are dense ranks of the values as displayed (rounded), in the metric's direction; NaN is never ranked;
  a column with fewer than two values is not marked.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from benchmarks.reporting.results import GROUP_KEYS, METRICS, higher_is_better
from worldtree.infra.errors import UserError

FORMATS = ("csv", "markdown", "latex")
#: Decimals shown in markdown/LaTeX (and used to decide ties when ranking).
DECIMALS = {
    "psnr": 2,
    "ssim": 3,
    "lpips": 3,
    "avge": 3,
    "mpsnr": 2,
    "mssim": 3,
    "mlpips": 3,
    "mavge": 3,
    "wall_time_s": 1,
    "cpu_time_s": 1,
    "peak_memory_mb": 0,
    "n_gaussians": 0,
    "n_scaffold_nodes": 0,
    "n_tree_nodes": 0,
}
#: Header names in markdown/LaTeX.
LABELS = {
    "psnr": "PSNR",
    "ssim": "SSIM",
    "lpips": "LPIPS",
    "avge": "AVGE",
    "mpsnr": "mPSNR",
    "mssim": "mSSIM",
    "mlpips": "mLPIPS",
    "mavge": "mAVGE",
    "wall_time_s": "Time (s)",
    "cpu_time_s": "CPU (s)",
    "peak_memory_mb": "Memory (MiB)",
    "n_gaussians": "Gaussians",
    "n_scaffold_nodes": "Scaffold nodes",
    "n_tree_nodes": "Tree nodes",
}
#: The paper's cell colours for the best, second and third value.
LATEX_COLORS = {"first": (255, 204, 201), "second": (255, 228, 207), "third": (255, 255, 212)}


@dataclass
class WideTable:
    """The wide table and how its columns were made."""

    frame: pd.DataFrame
    """Columns: the group keys, then per metric one column per scene (``metric:scene``) and the mean column
    (``metric:mean(scene, ...)``), unless ``mean_only``."""
    group_by: tuple[str, ...]
    metrics: tuple[str, ...]
    scenes: tuple[str, ...]
    """Every scene with a run, sorted."""
    mean_scenes: tuple[str, ...]
    """The scenes every row has a run for, which the mean columns average."""
    mean_only: bool = False
    notes: list[str] = field(default_factory=list)

    def scene_column(self, metric: str, scene: str) -> str:
        return f"{metric}:{scene}"

    def mean_column(self, metric: str) -> str:
        return f"{metric}:mean({', '.join(self.mean_scenes) if self.mean_scenes else 'none'})"

    def columns_of(self, metric: str) -> list[tuple[str, str]]:
        """(column name, sub-header) pairs of ``metric`` in order: the scenes, then the mean."""
        cols = [] if self.mean_only else [(self.scene_column(metric, s), s) for s in self.scenes]
        return cols + [(self.mean_column(metric), "mean")]


def parse_list(text: str | None, option: str, allowed: Sequence[str]) -> tuple[str, ...] | None:
    """``"a,b"`` -> ``("a", "b")`` checked against ``allowed``; None for None. UserError names ``option``."""
    if text is None:
        return None
    items = tuple(s.strip() for s in text.split(",") if s.strip())
    bad = [s for s in items if s not in allowed]
    if bad or not items:
        raise UserError(f"{option} {text!r}: give a comma-separated list of {', '.join(allowed)}")
    if len(set(items)) != len(items):
        raise UserError(f"{option} {text!r}: a name is repeated; give each once")
    return items


def _row_label(key: tuple, group_by: Sequence[str]) -> str:
    return " / ".join(f"{g}={v}" for g, v in zip(group_by, key, strict=True))


def build_wide(
    long: pd.DataFrame,
    group_by: Sequence[str] = ("method", "configuration"),
    metrics: Sequence[str] | None = None,
    mean_only: bool = False,
) -> WideTable:
    """The wide table of a long table (:func:`benchmarks.reporting.results.collect_runs`) of ONE protocol.

    ``metrics``: default every metric with at least one value (the rest are noted). Rows sorted by the group
    keys. See the module doc for the cell, mean and missing-scene rules.
    """
    group_by = tuple(group_by)
    if not group_by or any(g not in GROUP_KEYS for g in group_by) or len(set(group_by)) != len(group_by):
        raise UserError(f"--group-by {','.join(group_by)}: give distinct names from {', '.join(GROUP_KEYS)}")
    if long["protocol"].nunique() > 1:
        raise UserError("the runs use several protocols; choose one with --protocol")
    notes: list[str] = []
    if metrics is None:
        present = set(long.loc[np.isfinite(long["value"].to_numpy(float)), "metric"])
        metrics = tuple(m for m in METRICS if m in present)
        empty = [m for m in METRICS if m not in present and m in set(long["metric"])]
        if empty:
            notes.append(f"left out metrics without any value: {', '.join(empty)}")
        if not metrics:
            raise UserError("the finished runs hold no metric value; check their metrics.csv and timing.json")
    metrics = tuple(metrics)
    unknown = [m for m in metrics if m not in set(long["metric"])]
    if unknown:
        raise UserError(f"--metrics: no run has {', '.join(unknown)}; choose from {', '.join(METRICS)}")
    scenes = tuple(sorted(long["scene"].unique()))

    # Group keys as text: a missing seed must group (and print) as "", not as an unhashable-equal NaN.
    long = long.assign(**{g: long[g].map(_key_text) for g in group_by})
    # One value per (row, scene, metric): the mean over that cell's runs.
    cells = {
        tuple(k): float(v)
        for k, v in long.groupby([*group_by, "scene", "metric"], sort=True)["value"].mean().items()
    }
    runs = long.drop_duplicates(["run"])
    runs_per_cell = runs.groupby([*group_by, "scene"]).size()
    if (runs_per_cell > 1).any():
        n = int((runs_per_cell > 1).sum())
        notes.append(
            f"{n} (row, scene) cell(s) average several runs (up to {int(runs_per_cell.max())}); "
            "add seed or tag to --group-by to list them apart"
        )
    have: dict[tuple, set[str]] = {}
    for k in runs_per_cell.index.to_flat_index():
        have.setdefault(tuple(k[:-1]), set()).add(k[-1])
    rows = sorted(have)
    common = tuple(s for s in scenes if all(s in have[r] for r in rows))
    for s in scenes:
        if s not in common:
            lacking = [_row_label(r, group_by) for r in rows if s not in have[r]]
            notes.append(f"scene {s} has no run for {'; '.join(lacking)}")
    if len(common) < len(scenes):
        notes.append(
            "the mean columns average only the scenes every row has: "
            + (", ".join(common) if common else "none, so they are empty")
        )

    table = WideTable(pd.DataFrame(), group_by, metrics, scenes, common, mean_only, notes)
    records = []
    for r in rows:
        rec: dict[str, object] = dict(zip(group_by, r, strict=True))
        for m in metrics:
            per_scene = {s: cells.get((*r, s, m), math.nan) for s in scenes}
            if not mean_only:
                for s in scenes:
                    rec[table.scene_column(m, s)] = per_scene[s]
            vals = [per_scene[s] for s in common]
            # Plain mean: one missing scene makes the mean missing, so the header never overstates coverage.
            rec[table.mean_column(m)] = (
                float(np.mean(vals)) if vals and not any(map(math.isnan, vals)) else math.nan
            )
        records.append(rec)
    table.frame = pd.DataFrame(records)
    return table


# ------------------------------------------------------------------------------------------------- ranking


def rank_marks(values: Sequence[float], higher_better: bool, decimals: int | None = None) -> list[int | None]:
    """Dense rank (1, 2, 3) of each value among ``values``, None beyond 3, for NaN, or when fewer than two
    values are finite-or-infinite (not NaN). Values are compared after rounding to ``decimals`` (the displayed
    precision), so values shown equal share a rank; the next distinct value takes the next rank."""
    v = np.asarray(values, dtype=np.float64)
    if decimals is not None:
        v = np.round(v, decimals)
    valid = ~np.isnan(v)
    out: list[int | None] = [None] * len(v)
    if valid.sum() < 2:
        return out
    distinct = np.unique(v[valid])  # ascending
    if higher_better:
        distinct = distinct[::-1]
    rank = {float(x): i + 1 for i, x in enumerate(distinct[:3])}
    for i, x in enumerate(v):
        if valid[i]:
            out[i] = rank.get(float(x))
    return out


def column_marks(table: WideTable) -> dict[str, list[int | None]]:
    """Marks of every metric column of ``table`` (see :func:`rank_marks`)."""
    out = {}
    for m in table.metrics:
        for col, _ in table.columns_of(m):
            out[col] = rank_marks(table.frame[col].to_numpy(float), higher_is_better(m), DECIMALS.get(m))
    return out


# ---------------------------------------------------------------------------------------------- rendering


def format_value(v: float, metric: str) -> str:
    """A value as displayed: ``-`` for NaN, ``inf``/``-inf``, else rounded to :data:`DECIMALS`."""
    if v is None or (isinstance(v, float) and math.isnan(v)) or pd.isna(v):
        return "-"
    v = float(v)
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    return f"{v:.{DECIMALS.get(metric, 3)}f}"


def _key_text(v) -> str:
    return "" if v is None or pd.isna(v) else str(v)


def to_csv(table: WideTable) -> str:
    """The wide table as CSV at full precision, no marks (NaN as an empty cell, infinity as ``inf``)."""
    return table.frame.to_csv(index=False, na_rep="", float_format="%.10g")


def _arrow(metric: str, up: str, down: str) -> str:
    return up if higher_is_better(metric) else down


def to_markdown(table: WideTable) -> str:
    """A GitHub-flavoured markdown table; best **bold**, second <u>underlined</u>, third *italic*; a legend
    line after a blank line names the scenes of the mean columns."""
    marks = column_marks(table)
    wrap = {1: "**{}**", 2: "<u>{}</u>", 3: "*{}*"}
    header = [g for g in table.group_by]
    cols: list[tuple[str, str]] = []
    for m in table.metrics:
        for col, sub in table.columns_of(m):
            cols.append((col, m))
            header.append(f"{LABELS.get(m, m)}{_arrow(m, '↑', '↓')} {sub}")
    lines = [
        "| " + " | ".join(header) + " |",
        "|" + "|".join(["---"] * len(table.group_by) + ["--:"] * len(cols)) + "|",
    ]
    for i, row in table.frame.iterrows():
        cells = [_key_text(row[g]).replace("|", "\\|") for g in table.group_by]
        for col, m in cols:
            text = format_value(row[col], m)
            mark = marks[col][i]
            cells.append(wrap[mark].format(text) if mark else text)
        lines.append("| " + " | ".join(cells) + " |")
    mean = ", ".join(table.mean_scenes) if table.mean_scenes else "none (no scene is shared by every row)"
    lines += ["", f"mean = average over {mean}. Best **bold**, second <u>underlined</u>, third *italic*."]
    return "\n".join(lines) + "\n"


_LATEX_SPECIAL = {
    "\\": r"\textbackslash{}",
    "&": r"\&",
    "%": r"\%",
    "$": r"\$",
    "#": r"\#",
    "_": r"\_",
    "{": r"\{",
    "}": r"\}",
    "~": r"\textasciitilde{}",
    "^": r"\textasciicircum{}",
}


def latex_escape(text: str) -> str:
    """``text`` with LaTeX's special characters escaped."""
    return "".join(_LATEX_SPECIAL.get(c, c) for c in text)


def to_latex(table: WideTable) -> str:
    """A ``tabular`` in the paper's style: best ``\\cellcolor{first}\\textbf{}``, second
    ``\\cellcolor{second}``, third ``\\cellcolor{third}``; needs ``\\usepackage[table]{xcolor}``. The colour
    definitions come first; the first row names the scenes of the mean columns."""
    marks = column_marks(table)
    groups = [(m, table.columns_of(m)) for m in table.metrics]
    n_keys = len(table.group_by)
    n_cols = n_keys + sum(len(c) for _, c in groups)
    spec = "l" * n_keys + "".join("|" + "c" * len(c) for _, c in groups)
    out = ["% wtbench table; needs \\usepackage[table]{xcolor}"]
    out += [f"\\definecolor{{{k}}}{{RGB}}{{{r}, {g}, {b}}}" for k, (r, g, b) in LATEX_COLORS.items()]
    out += [f"\\begin{{tabular}}{{{spec}}}", "\\hline"]
    mean = ", ".join(table.mean_scenes) if table.mean_scenes else "none"
    out.append(f"\\multicolumn{{{n_cols}}}{{c}}{{\\textit{{mean over {latex_escape(mean)}}}}} \\\\ \\hline")
    keys = [latex_escape(g.capitalize()) for g in table.group_by]
    up, down = "$\\uparrow$", "$\\downarrow$"
    titles = [latex_escape(LABELS.get(m, m)) + _arrow(m, up, down) for m, _ in groups]
    if all(len(c) == 1 for _, c in groups):
        out.append(" & ".join(keys + titles) + " \\\\ \\hline")
    else:
        top = list(keys)
        clines = []
        start = n_keys + 1
        for k, ((_, c), title) in enumerate(zip(groups, titles, strict=True)):
            align = "c|" if k < len(groups) - 1 else "c"
            top.append(f"\\multicolumn{{{len(c)}}}{{{align}}}{{{title}}}")
            clines.append(f"\\cline{{{start}-{start + len(c) - 1}}}")
            start += len(c)
        out.append(" & ".join(top) + " \\\\ " + " ".join(clines))
        sub = [""] * n_keys + [latex_escape(s) for _, c in groups for _, s in c]
        out.append(" & ".join(sub) + " \\\\ \\hline")
    cell = {
        1: "\\cellcolor{{first}}\\textbf{{{}}}",
        2: "\\cellcolor{{second}}{}",
        3: "\\cellcolor{{third}}{}",
    }
    for i, row in table.frame.iterrows():
        cells = [latex_escape(_key_text(row[g])) for g in table.group_by]
        for m, c in groups:
            for col, _ in c:
                text = latex_escape(format_value(row[col], m))
                mark = marks[col][i]
                cells.append(cell[mark].format(text) if mark else text)
        out.append(" & ".join(cells) + " \\\\")
    out += ["\\hline", "\\end{tabular}"]
    return "\n".join(out) + "\n"


def render(table: WideTable, fmt: str) -> str:
    """``table`` as ``fmt`` (one of :data:`FORMATS`)."""
    if fmt == "csv":
        return to_csv(table)
    if fmt == "markdown":
        return to_markdown(table)
    if fmt == "latex":
        return to_latex(table)
    raise UserError(f"--format {fmt}: choose one of {', '.join(FORMATS)}")


def format_for(path, fmt: str | None) -> str:
    """``fmt``, or from the suffix of ``path`` when None: .md -> markdown, .tex -> latex, else csv."""
    if fmt is not None:
        if fmt not in FORMATS:
            raise UserError(f"--format {fmt}: choose one of {', '.join(FORMATS)}")
        return fmt
    suffix = "" if path is None else str(path).lower().rsplit(".", 1)[-1]
    return {"md": "markdown", "markdown": "markdown", "tex": "latex"}.get(suffix, "csv")
