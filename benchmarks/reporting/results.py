"""Collect finished runs into one long table: a row per (run, metric).

A run folder is ``RUNS_DIR/<scene>/<method>/<tag>/`` as written by :mod:`benchmarks.runner.runs`. Only finished runs
(``DONE`` present) are read; unfinished or damaged ones are skipped with a note. What is read:

- ``config.json``: ``method``, ``preset``, ``overrides``, ``seed`` and the method's ``config`` (for the
  configuration label, :func:`describe_configuration`);
- ``metrics.csv``: the ``mean`` row of the evaluation harness (columns of :data:`HARNESS_METRICS`);
- ``metrics.json``: ``protocol.name``;
- ``timing.json`` (and ``model/model.json`` for model sizes): the cost metrics of :data:`COST_METRICS`.

The format is documented in docs/tables.md.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from benchmarks.runner.layout import find_run_folders
from worldtree.infra.errors import UserError

#: Columns of the evaluation harness (benchmarks.evaluation.evaluate.COLUMNS without ``frame``).
HARNESS_METRICS = ("psnr", "ssim", "lpips", "avge", "mpsnr", "mssim", "mlpips", "mavge")
#: Cost of a run: wall seconds, CPU seconds (every process of the run), peak memory (MiB), model size.
COST_METRICS = (
    "wall_time_s",
    "cpu_time_s",
    "peak_memory_mb",
    "n_gaussians",
    "n_scaffold_nodes",
    "n_tree_nodes",
)
METRICS = HARNESS_METRICS + COST_METRICS
#: Long-table metric name prefix of a stage's seconds, e.g. ``stage_s:train``, ``stage_s:method.tree``.
STAGE_PREFIX = "stage_s:"
#: Metrics where a larger value is better; every other metric is better when smaller.
HIGHER_IS_BETTER = frozenset({"psnr", "ssim", "mpsnr", "mssim"})
#: Columns of the long table, in order.
LONG_COLUMNS = (
    "method",
    "configuration",
    "scene",
    "protocol",
    "metric",
    "value",
    "preset",
    "tag",
    "seed",
    "run",
)
#: Columns of the long table that may group the rows of the wide table.
GROUP_KEYS = ("method", "configuration", "preset", "tag", "seed")

#: Keys naming the model-size counts, first match wins (method stats may use any of these spellings).
_SIZE_KEYS = {
    "n_gaussians": ("num_gaussians", "n_gaussians"),
    "n_scaffold_nodes": ("num_scaffold_nodes", "n_scaffold_nodes", "scaffold_nodes"),
    "n_tree_nodes": ("num_tree_nodes", "n_tree_nodes", "tree_nodes"),
}


#: Metrics that may be +inf for a good reason: the PSNR of a render identical to its ground truth.
INFINITE_OK = ("psnr", "mpsnr")


def unusable_value(metric: str, v: float) -> bool:
    """Whether ``v`` cannot be a value of ``metric``: infinite (except +inf PSNR, :data:`INFINITE_OK`). Such a
    value is shown as missing, with one note (:func:`collect_runs`), never ranked or averaged."""
    return math.isinf(v) and not (metric in INFINITE_OK and v > 0)


def written_nonfinite(csv: Path) -> set[str]:
    """Metrics whose ``mean`` row cell in the run's ``metrics.csv`` holds text that is no value of the metric
    (``nan``, ``abc``, ``inf`` except for PSNR): written so, not merely empty (the harness leaves a metric it
    did not compute empty)."""
    try:
        raw = pd.read_csv(csv, dtype=str, keep_default_na=False)
    except (OSError, ValueError, pd.errors.ParserError):
        return set()
    if "frame" not in raw.columns:
        return set()
    out = set()
    for _, row in raw[raw["frame"] == "mean"].iterrows():
        for m in HARNESS_METRICS:
            text = str(row.get(m, "")).strip()
            v = _number(text)
            if text and (math.isnan(v) or unusable_value(m, v)):  # +inf PSNR is a value
                out.add(m)
    return out


def higher_is_better(metric: str) -> bool:
    """Direction of ``metric``: True for PSNR/SSIM (plain or masked), False for errors, time, memory, size."""
    return metric in HIGHER_IS_BETTER


# ------------------------------------------------------------------------------------- configuration label


def _lookup(record: Mapping[str, Any], key: str) -> Any:
    """``key`` from the record's top level, its ``config``, or ``config["tree"]`` (first found), else None."""
    places: list[Any] = [record]
    cfg = record.get("config")
    if isinstance(cfg, Mapping):
        places.append(cfg)
        if isinstance(cfg.get("tree"), Mapping):
            places.append(cfg["tree"])
    for place in places:
        if key in place and place[key] is not None:
            return place[key]
    return None


def _labels(record: Mapping[str, Any]) -> tuple[list[tuple[str, str]], tuple[str, ...]] | None:
    """``(options as (field, tag), ablation order)`` of the record's method: from the record itself
    (``labels``, written by the runner from ``MethodSpec.options`` / ``MethodSpec.ablations``), else, for a
    record older than that, from the method registered here under its name; None when neither is known."""
    labels = record.get("labels")
    if isinstance(labels, Mapping):
        opts = [(str(f), str(t)) for f, t in labels.get("options") or []]
        return opts, tuple(str(a) for a in labels.get("ablations") or ())
    name = record.get("method")
    if not isinstance(name, str):
        return None
    from methods.registry import list_methods

    spec = next((s for s in list_methods() if s.name == name), None)
    return None if spec is None else ([(o.field, o.tag) for o in spec.options], spec.ablations)


def _ablations(value: Any, order: tuple[str, ...] = ()) -> list[str]:
    if isinstance(value, str):
        items = [s for s in value.replace(",", " ").split() if s]
    elif isinstance(value, Iterable):
        items = [str(s) for s in value]
    else:
        return []
    items = sorted({s.strip().lstrip("-").lower() for s in items if s.strip()})
    known = [a for a in order if a in items]
    return known + [a for a in items if a not in order]


def describe_configuration(record: Mapping[str, Any]) -> str:
    """A short label of a run's configuration from its ``config.json`` record; missing keys are left out.

    Reads, in this order: ``preset`` (e.g. ``quick``); ``overrides`` other than ``seed`` as ``key=value``
    sorted by key (runs differing only in their seed share a label, so that a table averages seeds); then
    ``ablate`` (list or comma/space separated string) as ``-ba -sw``, in the order of the method's
    ``MethodSpec.ablations`` (others alphabetically); then each option the method declares
    (``MethodSpec.options``, in its order) as ``<tag>=<value>`` (a ``bool`` option as ``<tag>`` when on), e.g.
    WorldTree's ``depth=2 chain=3 split=binary``: read from the record's ``labels`` (the runner writes them), or
    for an older record from the method registered under its name; a run of a method known neither way labels
    the options it was given (``record["options"]``) as ``key=value``. Each value is looked up at the record's top level, then
    in ``record["config"]``, then in ``record["config"]["tree"]``.
    ``{"method": "worldtree", "preset": "quick", "config": {"ablate": ["sw", "ba"], "depth": 3}}`` ->
    ``"quick -ba -sw depth=3"``.
    Then ``sets`` (``--set KEY=VALUE``, sorted) and ``imported_priors`` (``--masks`` etc.) as ``name=folder``
    (the path's last part), so runs that differ only there never share a row.
    A record with none of these keys gives ``"default"``.
    """
    parts: list[str] = []
    preset = record.get("preset")
    if preset not in (None, ""):
        parts.append(str(preset))
    overrides = record.get("overrides")
    if isinstance(overrides, Mapping):
        parts += [f"{k}={overrides[k]}" for k in sorted(overrides) if k != "seed"]
    labels = _labels(record)
    parts += [f"-{a}" for a in _ablations(_lookup(record, "ablate"), labels[1] if labels else ())]
    if labels is not None:
        named = [(f, t) for f, t in labels[0] if f != "ablate"]
    else:
        given = record.get("options")
        named = [(k, k) for k in sorted(given) if k != "ablate"] if isinstance(given, Mapping) else []
    for key, tag in named:
        v = _lookup(record, key)
        if isinstance(v, bool):
            parts += [tag] if v else []
        elif v is not None and not isinstance(v, Mapping | list):
            parts.append(f"{tag}={v}")
    sets = record.get("sets")
    if isinstance(sets, list):
        parts += sorted(str(x) for x in sets)
    priors = record.get("imported_priors")
    if isinstance(priors, Mapping):
        parts += [f"{k}={Path(str(priors[k])).name}" for k in sorted(priors)]
    return " ".join(parts) if parts else "default"


# --------------------------------------------------------------------------------------------- collection


@dataclass
class Collection:
    """Finished runs as a long table, and what was noticed while reading them."""

    long: pd.DataFrame
    """One row per (run, metric) with columns :data:`LONG_COLUMNS`; ``value`` NaN where absent."""
    notes: list[str] = field(default_factory=list)
    """One line per skipped run or oddity, for the user."""


def read_json(path: Path) -> dict[str, Any] | None:
    """The JSON object in ``path``, or None when it is missing, unreadable or not an object."""
    try:
        obj = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError):
        return None
    return obj if isinstance(obj, dict) else None


def _number(v: Any) -> float:
    """A JSON/CSV value as float; NaN when absent or not a number."""
    if v is None or isinstance(v, bool):
        return math.nan
    try:
        return float(v)
    except (TypeError, ValueError):
        return math.nan


def read_metrics_table(csv: Path) -> pd.DataFrame | None:
    """A run's ``metrics.csv`` as written by the harness: one row per frame plus the ``mean`` row, the
    ``frame`` column as text, empty cells NaN. None when unreadable or without a ``frame`` column."""
    try:
        table = pd.read_csv(csv, dtype={"frame": str}, keep_default_na=False, na_values=[""])
    except (OSError, ValueError, pd.errors.ParserError):
        return None
    return table if "frame" in table.columns else None


def _mean_row(csv: Path) -> dict[str, float] | None:
    table = read_metrics_table(csv)
    if table is None:
        return None
    rows = table[table["frame"] == "mean"]
    if len(rows) != 1:
        return None
    row = rows.iloc[0]
    return {m: _number(row[m]) if m in table.columns else math.nan for m in HARNESS_METRICS}


def _first(places: Sequence[Mapping[str, Any] | None], keys: Sequence[str]) -> float:
    for place in places:
        if not isinstance(place, Mapping):
            continue
        for k in keys:
            v = _number(place.get(k))
            if not math.isnan(v):
                return v
    return math.nan


def cost_metrics(timing: Mapping[str, Any] | None, model_info: Mapping[str, Any] | None) -> dict[str, float]:
    """The :data:`COST_METRICS` of one run from its ``timing.json`` and ``model/model.json`` (NaN if absent).

    ``wall_time_s``: the run's wall time over all its sessions (``total_s``: an interrupted and resumed run
    counts every session, and every stage of the method, the tree included) less ``eval`` and ``kernel_build``
    (scoring and the C++ rasterizer's one-time compile are not the method's cost). Run folders written
    before sessions were recorded (no ``sessions_s``) keep the older estimate: the sum of ``stages_s`` except
    those two, with ``train`` replaced by ``train.wall_s_all_sessions``; ``total_s`` when ``stages_s`` is
    missing. ``peak_memory_mb``: ``cuda_peak_allocated_mib`` when the run was on CUDA, else ``peak_rss_mib``
    (MiB). ``cpu_time_s``: CPU seconds (user + system, every thread) of the run's process over all its
    sessions (``stages_cpu_s`` less ``eval`` and ``kernel_build``) plus those of the tree's worker processes
    (``method_stats.tree.layers[].nodes_cpu_s`` of the layers run in ``parallel`` mode: a ``sequential`` or
    ``in-process`` layer ran in the run's process and is counted there); unlike wall time it hardly changes when other jobs share the
    machine, so fronts measured on a busy machine compare. A run grown on another run's root (``--root-from``)
    adds to both the seconds those stages took there (``root_from``), so it costs what it would have alone. NaN for run folders without ``stages_cpu_s``.
    Sizes: the first of ``num_*``/``n_*`` keys found in timing.json, its ``method_stats``, then
    model.json.
    """
    timing = timing or {}
    stages = timing.get("stages_s")
    wall = math.nan
    if isinstance(timing.get("sessions_s"), list):
        wall = _number(timing.get("total_s"))
        for k in ("eval", "kernel_build"):
            v = _number(stages.get(k)) if isinstance(stages, Mapping) else math.nan
            wall -= v if math.isfinite(v) else 0.0
    elif isinstance(stages, Mapping) and stages:
        vals = {str(k): _number(v) for k, v in stages.items() if k not in ("eval", "kernel_build")}
        train = timing.get("train")
        all_sessions = _number(train.get("wall_s_all_sessions")) if isinstance(train, Mapping) else math.nan
        if "train" in vals and not math.isnan(all_sessions):
            vals["train"] = all_sessions
        finite = [v for v in vals.values() if math.isfinite(v)]
        wall = float(sum(finite)) if finite else math.nan
    if math.isnan(wall):
        wall = _number(timing.get("total_s"))
    wall += _lent_seconds(timing, "stages_s")
    mem = _number(timing.get("cuda_peak_allocated_mib"))
    if math.isnan(mem):
        mem = _number(timing.get("peak_rss_mib"))
    stats = timing.get("method_stats")
    places = [timing, stats if isinstance(stats, Mapping) else None, model_info]
    out = {"wall_time_s": wall, "cpu_time_s": _cpu_seconds(timing), "peak_memory_mb": mem}
    for metric, keys in _SIZE_KEYS.items():
        out[metric] = _first(places, keys)
    return out


def _lent_seconds(timing: Mapping[str, Any], key: str) -> float:
    """Seconds (``key``: ``stages_s`` or ``stages_cpu_s``) that the stages lent by ``--root-from`` took in the
    lending run (``timing.json``'s ``root_from``; 0 for a run that trained its own root)."""
    lent = timing.get("root_from")
    vals = lent.get(key) if isinstance(lent, Mapping) else None
    if not isinstance(vals, Mapping):
        return 0.0
    return float(sum(v for v in map(_number, vals.values()) if math.isfinite(v)))


def _cpu_seconds(timing: Mapping[str, Any]) -> float:
    """``cpu_time_s`` of :func:`cost_metrics` (NaN when the run recorded no CPU seconds)."""
    cpu = timing.get("stages_cpu_s")
    if not isinstance(cpu, Mapping) or not cpu:
        return math.nan
    vals = [_number(v) for k, v in cpu.items() if k not in ("eval", "kernel_build")]
    total = float(sum(v for v in vals if math.isfinite(v)))
    stats = timing.get("method_stats")
    tree = stats.get("tree") if isinstance(stats, Mapping) else None
    layers = tree.get("layers") if isinstance(tree, Mapping) else None
    for layer in layers if isinstance(layers, list) else ():
        if not isinstance(layer, Mapping) or layer.get("mode", "parallel") != "parallel":
            continue  # a layer run in the main process (sequential, or one node in-process) is in its stages
        nodes = layer.get("nodes_cpu_s")
        if isinstance(nodes, Mapping):
            total += sum(v for v in map(_number, nodes.values()) if math.isfinite(v))
    return total + _lent_seconds(timing, "stages_cpu_s")


def stage_times(timing: Mapping[str, Any] | None) -> dict[str, float]:
    """``{STAGE_PREFIX + name: seconds}`` for every stage of ``timing.json``: the run's (``stages_s``, all
    sessions; ``train`` is the method's whole ``fit``), then the method's own (``method_stats.stages_s``:
    priors, ba, sw, scaffold, photometric, tree, test_pose ... as ``method.<name>``); the long table carries them."""
    timing = timing or {}
    out: dict[str, float] = {}
    stages = timing.get("stages_s")
    if isinstance(stages, Mapping):
        out.update({f"{STAGE_PREFIX}{k}": _number(v) for k, v in stages.items()})
    stats = timing.get("method_stats")
    inner = stats.get("stages_s") if isinstance(stats, Mapping) else None
    if isinstance(inner, Mapping):
        out.update({f"{STAGE_PREFIX}method.{k}": _number(v) for k, v in inner.items()})
    return out


def collect_runs(runs_dirs: Sequence[str | Path]) -> Collection:
    """Read every finished run under ``runs_dirs`` into a long table (see the module doc).

    Raises :class:`UserError` when a folder does not exist or no finished run is found.
    """
    rows: list[dict[str, Any]] = []
    notes: list[str] = []
    unfinished: list[str] = []
    skipped_bad: list[str] = []
    nonfinite: list[str] = []
    no_ground_truth: list[str] = []
    seen: set[Path] = set()
    for d in runs_dirs:
        d = Path(d)
        if not d.is_dir():
            raise UserError(
                f"RUNS_DIR {d}: no such folder; give the -o folder of `wtbench run`/`wtbench sweep`"
            )
        for run in find_run_folders(d):
            if run.resolve() in seen:
                continue  # the same run reached through two RUNS_DIR arguments counts once
            seen.add(run.resolve())
            rel = str(run.relative_to(d))
            if not (run / "DONE").is_file():
                unfinished.append(rel)
                continue
            config = read_json(run / "config.json")
            record = read_json(run / "metrics.json") or {}
            no_gt = record.get("ground_truth") is False  # a scene without test views: nothing was scored
            if no_gt:
                no_ground_truth.append(rel)
            mean = {m: math.nan for m in HARNESS_METRICS} if no_gt else _mean_row(run / "metrics.csv")
            timing_path = run / "timing.json"
            timing = read_json(timing_path)
            unreadable = [
                what
                for what, bad in (
                    ("config.json", config is None),
                    ("metrics.csv (no single 'mean' row)", mean is None),
                    # A missing timing.json only leaves the cost columns empty; a damaged one is said.
                    ("timing.json", timing is None and timing_path.exists()),
                )
                if bad
            ]
            if unreadable:
                skipped_bad.append(f"{run} ({', '.join(unreadable)})")
                notes.append(
                    f"skipped {run}: unreadable {', '.join(unreadable)}; re-run it with `wtbench run ... --force`"
                )
                continue
            proto = record.get("protocol")
            protocol = (
                str(proto.get("name")) if isinstance(proto, Mapping) and proto.get("name") else "unknown"
            )
            if protocol == "unknown":
                notes.append(f"{run}: metrics.json names no protocol; listed as protocol 'unknown'")
            values = {
                **mean,
                **cost_metrics(timing, read_json(run / "model" / "model.json")),
            }
            # Values no metric can take (NaN or inf written into metrics.csv, an infinite time or size): shown
            # as missing, never ranked or averaged, and said once for all runs below.
            bad = sorted({m for m, v in values.items() if unusable_value(m, v)} | written_nonfinite(run / "metrics.csv"),
                         key=list(values).index)  # fmt: skip
            for m in bad:
                values[m] = math.nan
            if bad:
                nonfinite.append(f"{rel} ({', '.join(bad)})")
            inf = [m for m, v in values.items() if math.isinf(v)]
            if inf:
                notes.append(f"{run}: infinite {', '.join(inf)} (renders identical to the ground truth?)")
            seed = config.get("seed")
            base = {
                "method": str(config.get("method") or run.parent.name),
                "configuration": describe_configuration(config),
                "scene": run.parent.parent.name,
                "protocol": protocol,
                "preset": str(config.get("preset") or ""),
                "tag": run.name,
                "seed": int(seed) if isinstance(seed, int) and not isinstance(seed, bool) else None,
                "run": str(run),
            }
            rows += [{**base, "metric": m, "value": values[m]} for m in METRICS]
            rows += [{**base, "metric": m, "value": v} for m, v in stage_times(timing).items()]
    if nonfinite:
        shown = "; ".join(nonfinite[:5]) + (f" and {len(nonfinite) - 5} more" if len(nonfinite) > 5 else "")
        notes.append(
            f"{len(nonfinite)} run(s) hold NaN or infinite values, shown as missing: {shown}; "
            "re-score them (`wtbench eval`) or re-run them"
        )
    if no_ground_truth:
        shown = ", ".join(no_ground_truth[:5]) + (
            f" and {len(no_ground_truth) - 5} more" if len(no_ground_truth) > 5 else ""
        )
        notes.append(
            f"no ground truth for {len(no_ground_truth)} run(s) (scenes without test views, e.g. your own video): "
            f"{shown}; listed without scores"
        )
    if unfinished:
        shown = ", ".join(unfinished[:5]) + (
            f" and {len(unfinished) - 5} more" if len(unfinished) > 5 else ""
        )
        notes.append(f"skipped {len(unfinished)} unfinished run(s) (no DONE): {shown}")
    if not rows:
        where = ", ".join(str(d) for d in runs_dirs)
        if skipped_bad:
            raise UserError(
                f"RUNS_DIR {where}: no readable finished run; skipped {'; '.join(skipped_bad)}; re-run those "
                "with `wtbench run ... --force`"
            )
        raise UserError(
            f"RUNS_DIR {where}: no finished run (RUNS_DIR/<scene>/<method>/<tag>/DONE) found; "
            "run `wtbench run --method M --scene S -o RUNS_DIR` first"
        )
    long = pd.DataFrame(rows)
    long["seed"] = long["seed"].astype("Int64")
    long["value"] = long["value"].astype(np.float64)
    return Collection(long[list(LONG_COLUMNS)], notes)


def select(
    long: pd.DataFrame, protocol: str | None = None, metrics: Sequence[str] | None = None
) -> pd.DataFrame:
    """Rows of one protocol (``protocol`` or the only one present) and of ``metrics`` (default: all).

    Raises :class:`UserError` when several protocols are present and none is chosen, or a name is unknown.
    """
    protocols = sorted(long["protocol"].unique())
    if protocol is None:
        if len(protocols) > 1:
            raise UserError(
                f"runs were scored under several protocols ({', '.join(protocols)}); choose one with --protocol"
            )
    elif protocol not in protocols:
        raise UserError(f"--protocol {protocol}: no run uses it; the runs use {', '.join(protocols)}")
    else:
        long = long[long["protocol"] == protocol]
    if metrics is not None:
        bad = [m for m in metrics if m not in METRICS]
        if bad:
            raise UserError(f"--metrics: unknown {', '.join(bad)}; choose from {', '.join(METRICS)}")
        long = long[long["metric"].isin(list(metrics))]
    return long
