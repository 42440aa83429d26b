"""Build the static report site: index page (wide table, speed-vs-error plots, scenes, run states) and one page
per scene (its table, per-frame curves, the frame viewer). Layout and rules: docs/report.md.

The site is written into a temporary sibling folder and renamed over ``out`` when complete
(:func:`worldtree.infra.atomic.atomic_dir`); ``out`` may only be replaced when it is an earlier report (it holds
:data:`MARKER`).
"""

from __future__ import annotations

import hashlib
import math
import re
import shutil
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

import worldtree
from benchmarks.reporting.names import NameKey, name_key, shorten
from benchmarks.reporting.results import GROUP_KEYS, HARNESS_METRICS, collect_runs, higher_is_better, select
from benchmarks.reporting.tables import LABELS, WideTable, build_wide, column_marks, format_value, to_csv
from benchmarks.reporting.webreport.gather import (
    STATES,
    RunEntry,
    frame_times,
    gather_runs,
    sweep_failures,
    test_frame_files,
)
from worldtree.infra.errors import UserError

#: A file every report holds; an existing ``-o`` folder without it is never replaced.
MARKER = ".wtbench-report"
#: A file in the temporary folder of a report being written: who writes it (PID, host, start time), so that a
#: later `wtbench report` removes the folder once that process is gone (killed before it could clean up).
PARTIAL_MARKER = ".wtbench-report-partial"
#: Age after which a temporary report folder is removed even when its writer cannot be checked (another
#: host, or no marker: killed in the instant between creating it and marking it).
PARTIAL_MAX_AGE_S = 24 * 3600.0
#: Metrics drawn over time on the scene pages.
CURVE_METRICS = ("psnr", "mpsnr")
#: Cells of a run shown in a hover text before "and N more".
_HOVER_RUNS = 4
#: Hex digits of each checksum in a cell's hover text.
_HOVER_DIGITS = 16


@dataclass(frozen=True)
class ReportOptions:
    """How the report is made (the options of `wtbench report`)."""

    group_by: tuple[str, ...] = ("method", "configuration")
    """Row keys of the tables, from :data:`benchmarks.reporting.results.GROUP_KEYS`."""
    protocol: str | None = None
    """Only this evaluation protocol; None: every protocol found, one table each."""
    image_width: int = 320
    """Width (pixels) of the viewer's images; larger images are scaled down."""
    viewer_frames: int = 24
    """Test frames in the viewer per scene, evenly spaced; 0 for every frame."""
    title: str = "worldtree-bench results"


def slug(text: str) -> str:
    """``text`` as a safe file name part (letters, digits, ``._-``; anything else ``_``). Not one-to-one
    (``A b`` and ``A_b`` give the same): file names of several texts come from :func:`unique_slugs`."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", text) or "_"


#: Longest slug kept before its hash suffix (a scene name may be up to 255 bytes; the page adds ``.html``).
_SLUG_MAX = 120


def unique_slugs(texts: Iterable[str]) -> dict[str, str]:
    """Text -> file name part, different for different texts, also on a case-insensitive file system.

    A text that is already a safe name (letters, digits, ``._-``, not too long) keeps it when no other text
    took it first (safe names are served first, in sorted order); any other text gets its :func:`slug` plus
    ``-`` and 10 hex digits of its sha256, so ``A b`` and ``A_b`` get two pages, and the same text gets the
    same name in every report.
    """
    out: dict[str, str] = {}
    taken: set[str] = set()
    for text in sorted(set(texts), key=lambda t: (slug(t) != t or len(t) > _SLUG_MAX, t)):
        base = slug(text)[:_SLUG_MAX]
        name = base
        if name != text or name.lower() in taken:
            name = f"{base}-{hashlib.sha256(text.encode('utf-8', 'surrogateescape')).hexdigest()[:10]}"
        n = 2
        while name.lower() in taken:  # a safe name that happens to look like another's hashed one
            name = f"{base}-{hashlib.sha256(text.encode('utf-8', 'surrogateescape')).hexdigest()[:10]}-{n}"
            n += 1
        taken.add(name.lower())
        out[text] = name
    return out


def _key_text(v: Any) -> str:
    return "" if v is None or pd.isna(v) else str(v)


def _data_value(v: float) -> str:
    """A number for the sorter's ``data-v`` (JavaScript's parseFloat spelling); empty for NaN."""
    if v is None or math.isnan(v):
        return ""
    if math.isinf(v):
        return "Infinity" if v > 0 else "-Infinity"
    return repr(float(v))


# ---------------------------------------------------------------------------------------------- the table


def _table_model(
    table: WideTable,
    long: pd.DataFrame,
    entries: dict[str, RunEntry],
    scenes: Sequence[str] | None = None,
    links: dict[str, str] | None = None,
    codes: NameKey | None = None,
) -> dict[str, Any]:
    """What the table template needs: header groups, sortable sub-headers, rows of cells (text, value, rank
    mark, hover text) and each row's runs. ``scenes``: only these scenes' columns (no mean), for a scene page.
    ``links``: run folder -> scene page, for the runs listed in each row's details. ``codes``: the site's name
    key; when it shortens, each row carries its code and each key cell a short text (the full one to hover)."""
    keys = list(table.group_by)
    key_texts = [[_key_text(rec[g]) for g in keys] for _, rec in table.frame.iterrows()]
    # Each key column shortened on its own (a long configuration leaves the method column as it is).
    short_cols = [shorten([t[j] for t in key_texts]) if key_texts else [] for j in range(len(keys))]
    marks = column_marks(table)
    long = long.assign(**{g: long[g].map(_key_text) for g in keys})
    runs_of: dict[tuple, list[str]] = {}
    for k, grp in long.drop_duplicates("run").groupby([*keys, "scene"], sort=False):
        runs_of[tuple(k)] = sorted(grp["run"])
    columns: list[tuple[str, str, str]] = []  # (column, metric, scene or "" for the mean)
    groups = []
    for m in table.metrics:
        cols = [
            (col, m, "" if sub == "mean" and col == table.mean_column(m) else sub)
            for col, sub in table.columns_of(m)
        ]
        if scenes is not None:
            cols = [c for c in cols if c[2] in scenes]
        if cols:
            arrow = "↑" if higher_is_better(m) else "↓"
            groups.append({"label": f"{LABELS.get(m, m)}{arrow}", "span": len(cols), "metric": m})
            columns += cols
    subs = [{"label": g, "col": i, "type": "text", "best": "asc", "metric": "", "scene": ""} for i, g in
            enumerate(keys)]  # fmt: skip
    for j, (_, m, scene) in enumerate(columns):
        subs.append(
            {
                "label": scene or "mean",
                "col": len(keys) + j,
                "type": "num",
                "best": "desc" if higher_is_better(m) else "asc",
                "metric": m,
                "scene": scene,
                "title": (
                    f"{LABELS.get(m, m)} on {scene}"
                    if scene
                    else f"{LABELS.get(m, m)}: mean over {', '.join(table.mean_scenes) or 'no common scene'}"
                ),
            }
        )
    rows = []
    for n, (i, rec) in enumerate(table.frame.iterrows()):
        key = tuple(key_texts[n])
        name = " ".join(k for k in key if k)
        code = codes.code(name) if codes is not None and codes.shortened and name in codes.names else ""
        cells = []
        for col, m, scene in columns:
            v = float(rec[col])
            in_cell = [
                r for s in ([scene] if scene else table.mean_scenes) for r in runs_of.get((*key, s), [])
            ]
            hover = [f"{LABELS.get(m, m)} {scene or 'mean over ' + ', '.join(table.mean_scenes)}: "
                     f"{format_value(v, m)} ({len(in_cell)} run(s))"]  # fmt: skip
            for r in in_cell[:_HOVER_RUNS]:
                e = entries.get(r)
                # Cut checksums keep the hover text (one per cell) small; the row's runs list holds them whole.
                hover.append(e.provenance(digits=_HOVER_DIGITS) if e else r)
            if len(in_cell) > _HOVER_RUNS:
                hover.append(f"... and {len(in_cell) - _HOVER_RUNS} more")
            cells.append(
                {
                    "text": format_value(v, m),
                    "v": _data_value(v),
                    "rank": marks[col][i],
                    "metric": m,
                    "scene": scene,
                    "title": "\n".join(hover),
                }
            )
        row_runs = [
            r for s in (scenes if scenes is not None else table.scenes) for r in runs_of.get((*key, s), [])
        ]
        runs = []
        for r in row_runs:
            e = entries.get(r)
            if e is not None:
                runs.append({"entry": e, "link": (links or {}).get(r)})
        if scenes is not None and not row_runs:
            continue  # a configuration without a run on this scene has no row on its page
        key_cells = [
            {"text": short_cols[j][n], "full": k, "shortened": short_cols[j][n] != k}
            for j, k in enumerate(key)
        ]
        rows.append({"keys": key_cells, "code": code, "name": name, "cells": cells, "runs": runs})
    return {
        "groups": groups,
        "subs": subs,
        "n_keys": len(keys),
        "rows": rows,
        "mean_scenes": list(table.mean_scenes),
    }


# ---------------------------------------------------------------------------------------------- plots


def _speed_plots(long: pd.DataFrame, keys: Sequence[str], folder: Path, stem: str) -> tuple[list, list]:
    """One speed-vs-error PNG per harness metric with values (x: wall time), Pareto front marked
    (:mod:`benchmarks.reporting.plots`). Returns (plots as dicts of file and metric, notes)."""
    from benchmarks.reporting.plots import draw, make_panel

    have = set(long.loc[np.isfinite(long["value"].to_numpy(np.float64)), "metric"])
    plots, notes = [], []
    if "wall_time_s" not in have:
        return [], ["no run has a wall time (timing.json), so there is no speed-vs-error plot"]
    for m in HARNESS_METRICS:
        if m not in have:
            continue
        try:
            panel = make_panel(long, "wall_time_s", m, keys)
        except UserError as e:
            notes.append(f"no {m} plot: {e}")
            continue
        name = f"plots/{stem}_{m}.png"
        draw([panel], folder / name, dpi=90)
        front = panel.points[panel.points["pareto"]]["label"].tolist()
        plots.append({"file": name, "metric": LABELS.get(m, m), "front": front})
    return plots, notes


def _curves(runs: Sequence[RunEntry], labels: dict[str, str], path: Path) -> bool:
    """Per-frame PSNR and masked PSNR over time, one line per run (:func:`benchmarks.reporting.plots.curves_figure`),
    into ``path`` (PNG). False when no run has per-frame scores."""
    from benchmarks.reporting.plots import Curve, curves_figure

    metrics = [
        m
        for m in CURVE_METRICS
        if any(r.frames is not None and m in r.frames and r.frames[m].notna().any() for r in runs)
    ]
    if not metrics:
        return False
    curves = [
        Curve(
            labels[str(r.folder)],
            np.asarray(frame_times(r.scene_dir, list(r.frames.index)), dtype=np.float64),
            {m: r.frames[m].to_numpy(np.float64) for m in metrics if m in r.frames},
        )
        for r in runs
        if r.frames is not None
    ]
    curves_figure(curves, metrics).savefig(path, format="png", dpi=90)
    return True


# ---------------------------------------------------------------------------------------------- viewer


def _pick(n: int, k: int) -> list[int]:
    """``k`` indices of ``range(n)`` evenly spaced, first and last included (all when ``k`` is 0 or >= n)."""
    if k <= 0 or k >= n:
        return list(range(n))
    return sorted({round(x) for x in np.linspace(0, n - 1, k)})


def _viewer(
    scene: str,
    runs: Sequence[RunEntry],
    labels: dict[str, str],
    root: Path,
    opts: ReportOptions,
    scene_slug: str | None = None,
) -> tuple[list[dict[str, Any]], list[str]]:
    """Write the viewer's images of ``scene`` under ``root/img/<scene_slug>/`` (default: its :func:`slug`)
    and return (frames, notes); a frame holds its name, ground truth, mask and one row per run (render,
    error map, scores)."""
    from benchmarks.reporting.webreport.images import error_map, fit_width, mask_view, write_jpeg
    from worldtree.imageio import read_image, read_mask

    notes: list[str] = []
    scene_dir = next((r.scene_dir for r in runs if r.scene_dir is not None), None)
    gt_files = test_frame_files(scene_dir) if scene_dir is not None else {}
    if scene_dir is None:
        notes.append("the scene folder named by the runs' config.json is not here: no ground truth shown")
    names: list[str] = list(gt_files)
    if not names:
        for r in runs:
            if r.frames is not None:
                names += [n for n in r.frames.index if n not in names]
    names = [n for n in names if gt_files or any((r.folder / "renders" / f"{n}.png").is_file() for r in runs)]
    if not names:
        return [], notes + ["no test frame with a render or a ground-truth image: no viewer"]
    chosen = [names[i] for i in _pick(len(names), opts.viewer_frames)]
    if len(chosen) < len(names):
        notes.append(f"the viewer shows {len(chosen)} of {len(names)} test frames (--viewer-frames)")
    folder = f"img/{scene_slug or slug(scene)}"
    stems = unique_slugs(chosen)  # frames "a b" and "a_b" keep their own images
    frames = []
    for name in chosen:
        gt = mask = None
        frame: dict[str, Any] = {"name": name, "gt": None, "mask": None, "rows": []}
        if name in gt_files:
            gt_path, mask_path = gt_files[name]
            try:
                gt = read_image(gt_path)
                mask = read_mask(mask_path) if mask_path is not None else None
            except UserError as e:
                notes.append(str(e))
                gt = mask = None
            if gt is not None:
                frame["gt"] = f"{folder}/{stems[name]}_gt.jpg"
                write_jpeg(root / frame["gt"], fit_width(gt, opts.image_width))
            if gt is not None and mask is not None and mask.shape == gt.shape[:2]:
                frame["mask"] = f"{folder}/{stems[name]}_mask.jpg"
                write_jpeg(root / frame["mask"], fit_width(mask_view(gt, mask), opts.image_width))
        for i, r in enumerate(runs):
            row: dict[str, Any] = {
                "label": labels[str(r.folder)],
                "render": None,
                "error": None,
                "scores": [],
            }
            render_path = r.folder / "renders" / f"{name}.png"
            if render_path.is_file():
                try:
                    pred = read_image(render_path)
                except UserError as e:
                    notes.append(str(e))
                    pred = None
                if pred is not None:
                    row["render"] = f"{folder}/{stems[name]}_r{i}.jpg"
                    write_jpeg(root / row["render"], fit_width(pred, opts.image_width))
                    if gt is not None and gt.shape == pred.shape:
                        row["error"] = f"{folder}/{stems[name]}_e{i}.jpg"
                        write_jpeg(root / row["error"], error_map(pred, gt, width=opts.image_width))
            if r.frames is not None and name in r.frames.index:
                for m in CURVE_METRICS:
                    if m in r.frames:
                        row["scores"].append(f"{LABELS[m]} {format_value(float(r.frames.loc[name, m]), m)}")
            frame["rows"].append(row)
        frames.append(frame)
    return frames, notes


def _video(e: RunEntry, label: str, root: Path, stem: str, notes: list[str]) -> dict[str, str]:
    """The run's ``test_view.mp4`` as WebM under ``root/<stem>.webm`` (browsers do not play OpenCV's mp4v);
    the mp4 copied as it is, with a note, where OpenCV cannot re-encode it."""
    from benchmarks.reporting.video import to_webm

    (root / "videos").mkdir(exist_ok=True)
    if to_webm(e.video, root / f"{stem}.webm"):
        return {"label": label, "file": f"{stem}.webm", "type": "video/webm"}
    notes.append(f"{e.video}: could not be re-encoded as WebM; copied as mp4 (some browsers cannot play it)")
    shutil.copyfile(e.video, root / f"{stem}.mp4")
    return {"label": label, "file": f"{stem}.mp4", "type": "video/mp4"}


# ---------------------------------------------------------------------------------------------- the site


def _environment():
    import jinja2

    return jinja2.Environment(
        loader=jinja2.PackageLoader("benchmarks.reporting.webreport", "templates"),
        autoescape=jinja2.select_autoescape(["html"]),
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )


def _check_out(out: Path) -> None:
    from worldtree.infra.output_paths import check_output_folder

    if out.exists() and not out.is_dir():
        raise UserError(f"-o {out}: is a file; give a folder for the report")
    if out.is_dir() and any(out.iterdir()) and not (out / MARKER).is_file():
        raise UserError(
            f"-o {out}: the folder exists and is not a wtbench report; give a new or empty folder"
        )
    check_output_folder(out, "-o")  # -o FILE/sub, an unwritable parent


def _row_text(e: RunEntry, keys: Sequence[str]) -> str:
    """The run's table row as one text: its group keys' values joined by spaces (the name the key codes)."""
    fields = {"method": e.method, "configuration": e.configuration, "tag": e.tag,
              "seed": "" if e.seed is None else str(e.seed), "preset": ""}  # fmt: skip
    return " ".join(fields[k] for k in keys if fields.get(k))


def _name_key(long: pd.DataFrame | None, opts: ReportOptions, entries: Sequence[RunEntry]) -> NameKey:
    """Codes of the site's row names (:mod:`benchmarks.reporting.names`), the same on every page: the table
    rows in their order (sorted by the group keys), then the rows of runs not in a table (unfinished)."""
    rows: list[str] = []
    if long is not None:
        keys = list(opts.group_by)
        texts = long[keys].map(_key_text).drop_duplicates()
        rows = [" ".join(k for k in row if k) for row in sorted(texts.itertuples(index=False, name=None))]
    return name_key(rows + [_row_text(e, opts.group_by) for e in entries])


def _run_label(e: RunEntry, keys: Sequence[str], key: NameKey) -> str:
    """A run's label in the viewer, the curves and the videos: its row's :meth:`NameKey.label` and its tag."""
    return f"{key.label(_row_text(e, keys))} [{e.tag}]"


def build_report(
    runs_dirs: Sequence[str | Path],
    out: str | Path,
    opts: ReportOptions | None = None,
    log: Callable[[str], None] = print,
) -> list[str]:
    """Write the report of the runs under ``runs_dirs`` to the folder ``out`` (replacing an earlier report).

    Returns the notes (skipped runs, missing scenes, left-out plots) that the pages also show.
    Raises :class:`UserError` for a missing RUNS_DIR, a folder without any run, or an ``out`` that is not an
    earlier report.
    """
    from worldtree.infra.atomic import atomic_dir, atomic_write_text

    opts = opts or ReportOptions()
    if not opts.group_by or any(g not in GROUP_KEYS for g in opts.group_by):
        raise UserError(f"--group-by {','.join(opts.group_by)}: give names from {', '.join(GROUP_KEYS)}")
    if opts.image_width < 16:
        raise UserError(f"--image-width {opts.image_width}: give at least 16 pixels")
    if opts.viewer_frames < 0:
        raise UserError(f"--viewer-frames {opts.viewer_frames}: give 0 (every frame) or a positive count")
    out = Path(out)
    for d in map(Path, runs_dirs):
        if not d.is_dir():
            raise UserError(
                f"RUNS_DIR {d}: no such folder; give the -o folder of `wtbench run`/`wtbench sweep`"
            )
    _check_out(out)
    try:
        found = collect_runs(runs_dirs)
        long, notes = found.long, list(found.notes)
    except UserError:
        long, notes = None, ["no finished run yet: the tables and plots are empty"]
    entries = gather_runs(runs_dirs, set(long["run"]) if long is not None else set())
    failures = sweep_failures(runs_dirs)
    if not entries and not failures:
        where = ", ".join(str(d) for d in runs_dirs)
        raise UserError(
            f"RUNS_DIR {where}: no run folder (RUNS_DIR/<scene>/<method>/<tag>/config.json) found"
        )
    by_run = {str(e.folder): e for e in entries}
    scenes = sorted({e.scene for e in entries})
    scene_slug = unique_slugs(scenes)  # scenes "A b" and "A_b" get a page each
    scene_page = {s: f"scenes/{scene_slug[s]}.html" for s in scenes}
    links = {str(e.folder): scene_page[e.scene] for e in entries}
    key = _name_key(long, opts, entries)
    labels = {str(e.folder): _run_label(e, opts.group_by, key) for e in entries}
    env = _environment()
    now = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
    common = {"title": opts.title, "generated": now, "version": worldtree.__version__, "labels": LABELS}

    for stale in remove_stale_report_partials(out):
        log(f"removed {stale}: the temporary folder of a report that was killed")
    with atomic_dir(out, force=True) as tmp:
        _mark_partial(tmp)
        (tmp / "plots").mkdir()
        (tmp / "scenes").mkdir()
        (tmp / "data").mkdir()
        for name in ("report.css", "report.js"):
            shutil.copyfile(Path(__file__).parent / "templates" / name, tmp / name)
        sections, tables = [], {}
        protocols = [] if long is None else sorted(long["protocol"].unique())
        if opts.protocol is not None:
            if opts.protocol not in protocols:
                raise UserError(
                    f"--protocol {opts.protocol}: no finished run uses it; the runs use {', '.join(protocols)}"
                )
            protocols = [opts.protocol]
        proto_slug = unique_slugs(protocols)
        for proto in protocols:
            plong = select(long, proto)
            table = build_wide(plong, opts.group_by)
            tables[proto] = (table, plong)
            notes += [f"{proto}: {n}" for n in table.notes]
            stem = proto_slug[proto]
            atomic_write_text(tmp / "data" / f"{stem}_wide.csv", to_csv(table))
            atomic_write_text(
                tmp / "data" / f"{stem}_long.csv", plong.to_csv(index=False, na_rep="", float_format="%.10g")
            )
            log(f"protocol {proto}: {len(table.frame)} configuration(s), drawing speed-vs-error plots")
            from benchmarks.reporting.plots import with_derived

            plots, why = _speed_plots(with_derived(plong), opts.group_by, tmp, stem)
            notes += [f"{proto}: {n}" for n in why]
            sections.append(
                {
                    "protocol": proto,
                    "id": f"results-{stem}",
                    "table": _table_model(table, plong, by_run, links=links, codes=key),
                    "plots": plots,
                    "csv": f"data/{stem}_wide.csv",
                    "long_csv": f"data/{stem}_long.csv",
                    "metrics": list(table.metrics),
                }
            )

        scene_cards = []
        for k, s in enumerate(scenes):
            runs = [e for e in entries if e.scene == s]
            done = [e for e in runs if e.state == "done"]
            log(f"scene {k + 1}/{len(scenes)} {s}: {len(done)} finished run(s) of {len(runs)}")
            frames, scene_notes = _viewer(s, done, labels, tmp, opts, scene_slug[s]) if done else ([], [])
            curves = f"plots/curves_{scene_slug[s]}.png"
            has_curves = bool(done) and _curves(done, labels, tmp / curves)
            scene_tables = [
                {
                    "protocol": proto,
                    "id": f"scene-{proto_slug[proto]}",
                    "table": _table_model(table, plong, by_run, scenes=[s], codes=key),
                    "metrics": list(table.metrics),
                }
                for proto, (table, plong) in tables.items()
                if s in table.scenes
            ]
            videos = []
            for i, e in enumerate(done):
                if e.video is not None:
                    videos.append(
                        _video(e, labels[str(e.folder)], tmp, f"videos/{scene_slug[s]}_{i}", scene_notes)
                    )
            page = env.get_template("scene.html").render(
                **common,
                root="../",
                scene=s,
                tables=scene_tables,
                curves=curves if has_curves else None,
                frames=frames,
                videos=videos,
                runs=runs,
                name_key=key.entries(_row_text(e, opts.group_by) for e in runs) if key.shortened else [],
                run_codes={str(e.folder): key.code(_row_text(e, opts.group_by)) for e in runs},
                notes=scene_notes,
                error_vmax=_error_vmax(),
            )
            atomic_write_text(tmp / scene_page[s], page)
            thumb = next((f["gt"] or next((r["render"] for r in f["rows"] if r["render"]), None)
                          for f in frames), None)  # fmt: skip
            counts = {st: sum(e.state == st for e in runs) for st in STATES}
            scene_cards.append({"name": s, "page": scene_page[s], "thumb": thumb, "counts": counts})
        from benchmarks.reporting.webreport.images import write_colorbar

        write_colorbar(tmp / "plots" / "error_colorbar.png")

        state_counts = {st: sum(e.state == st for e in entries) for st in STATES}
        index = env.get_template("index.html").render(
            **common,
            root="",
            runs_dirs=[str(d) for d in runs_dirs],
            sections=sections,
            scenes=scene_cards,
            runs=entries,
            links=links,
            name_key=key.entries() if key.shortened else [],
            failures=failures,
            notes=notes,
            state_counts=state_counts,
        )
        atomic_write_text(tmp / "index.html", index)
        (tmp / MARKER).write_text(f"wtbench report {worldtree.__version__} {now}\n")
        (tmp / PARTIAL_MARKER).unlink()
    return notes


def _mark_partial(tmp: Path) -> None:
    import json
    import os
    import socket

    doc = {"pid": os.getpid(), "host": socket.gethostname(), "since": time.time()}
    (tmp / PARTIAL_MARKER).write_text(json.dumps(doc))


def _writer_gone(folder: Path, now: float) -> bool:
    """Whether the report writer that made the temporary ``folder`` is gone: its marker names a process of
    this host that no longer runs, or the folder is older than :data:`PARTIAL_MAX_AGE_S`."""
    import json
    import os
    import socket

    try:
        age = now - folder.stat().st_mtime
    except OSError:
        return False
    try:
        doc = json.loads((folder / PARTIAL_MARKER).read_text())
        pid, host = int(doc["pid"]), str(doc["host"])
    except (OSError, ValueError, KeyError, TypeError):
        return age > PARTIAL_MAX_AGE_S
    if host != socket.gethostname():
        return age > PARTIAL_MAX_AGE_S
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False
    return False


def remove_stale_report_partials(out: Path) -> list[Path]:
    """Remove the temporary folders ``.OUT.XXXXXXXX.partial`` beside ``out`` (the name
    :func:`worldtree.infra.atomic.atomic_dir` gives them) whose writer is gone (:func:`_writer_gone`): a report
    killed while being written (SIGKILL, a lost node) leaves one. A folder of a live writer, or one not
    named like ours, is kept. Returns the folders removed."""
    out = Path(out)
    if not out.parent.is_dir():
        return []
    pattern = re.compile(rf"\.{re.escape(out.name)}\.[a-z0-9_]{{8}}\.partial")
    now = time.time()
    removed = []
    for p in sorted(out.parent.iterdir()):
        if pattern.fullmatch(p.name) and p.is_dir() and not p.is_symlink() and _writer_gone(p, now):
            shutil.rmtree(p, ignore_errors=True)
            removed.append(p)
    return removed


def _error_vmax() -> float:
    from benchmarks.reporting.webreport.images import ERROR_VMAX

    return ERROR_VMAX
