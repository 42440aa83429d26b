"""Does the tree beat its root? One markdown row per scene from the run folders of `wtbench sweep --grid tree`
(the root alone, depths 1 and 2, ``--depth auto``): mPSNR, PSNR, CPU seconds and Gaussians of each (as
`wtbench table` counts them, :func:`benchmarks.reporting.results.cost_metrics`), the gains
over the root and auto's share of depth 2's CPU time, what auto grew and why (its root's decision from
``timing.json``'s ``method_stats.tree.auto``: kept as a leaf with the reason, or split into N nodes), then the
means over scenes.

Usage::

    python -m benchmarks.speed.tree_vs_root RUNS_DIR [RUNS_DIR ...] [--noise DB]

A run folder counts as ``depth D`` from its recorded options (``config.json``); several runs of one scene and
depth (e.g. seeds) are averaged. A depth a scene was not run at (e.g. only the root and depth 2) reads ``-``, as
does every figure made from it; the best fixed depth is the best of those run, and each mean is over the scenes
that have its figure. ``--noise`` marks a gain below minus that many dB as a loss beyond noise.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from benchmarks.reporting.results import cost_metrics

DEPTHS = ("0", "1", "2", "auto")


def collect(roots: list[Path]) -> dict[str, dict[str, list[dict]]]:
    """``{scene: {depth: [run, ...]}}`` with each run's mean scores, CPU seconds and Gaussian count."""
    out: dict[str, dict[str, list[dict]]] = defaultdict(lambda: defaultdict(list))
    for root in roots:
        for cfg_path in sorted(root.glob("*/worldtree/*/config.json")):
            run = cfg_path.parent
            if not (run / "DONE").exists():
                continue
            cfg = json.loads(cfg_path.read_text())
            depth = str(cfg["config"].get("depth"))
            if "tpt" in cfg["config"].get("ablate", []):
                depth = "0"
            if depth not in DEPTHS:
                continue
            mean = json.loads((run / "metrics.json").read_text())["mean"]
            timing = json.loads((run / "timing.json").read_text())
            model = run / "model" / "model.json"
            cost = cost_metrics(timing, json.loads(model.read_text()) if model.exists() else None)
            out[run.parent.parent.name][depth].append({
                "mpsnr": float(mean["mpsnr"]), "psnr": float(mean["psnr"]), "cpu_s": cost["cpu_time_s"],
                "gaussians": cost["n_gaussians"], "grown": grown(timing),
            })  # fmt: skip
    return out


def grown(timing: dict) -> str:
    """What a tree run grew, from its ``timing.json``: ``"leaf: REASON"`` when the root was kept alone by
    ``--depth auto`` (the reason up to its first colon, e.g. ``depth unmeasured``), ``"N nodes"`` otherwise,
    ``""`` for a run that recorded no tree."""
    tree = (timing.get("method_stats") or {}).get("tree") or {}
    nodes = tree.get("nodes") or []
    root = (tree.get("auto") or {}).get("1") or {}
    if len(nodes) <= 1 and root and not root.get("split", False):
        return "leaf: " + str(root.get("reason", "")).split(":")[0]
    return f"{len(nodes)} node{'s' if len(nodes) != 1 else ''}" if nodes else ""


def _avg(runs: list[dict], key: str) -> float:
    return float(np.mean([r[key] for r in runs])) if runs else float("nan")


def _fmt(v: float, spec: str) -> str:
    """``v`` formatted by ``spec``, or ``-`` where it is missing (NaN: a depth not run)."""
    return "-" if v != v else format(v, spec)


def table(data: dict[str, dict[str, list[dict]]], noise: float = 0.0) -> str:
    """The markdown table (see the module docstring)."""
    head = ("| scene | root mPSNR | d1 | d2 | auto | d1 - root | d2 - root | auto - best fixed | PSNR root / d2 | "
            "CPU s root / d1 / d2 / auto | auto CPU / d2 | Gaussians root / d2 / auto | auto grew |")  # fmt: skip
    rows = [head, "|" + "|".join([" --- "] * 13) + "|"]
    gains: dict[str, list[float]] = defaultdict(list)
    for scene in sorted(data):
        d = data[scene]
        m = {k: _avg(d.get(k, []), "mpsnr") for k in DEPTHS}
        p = {k: _avg(d.get(k, []), "psnr") for k in DEPTHS}
        c = {k: _avg(d.get(k, []), "cpu_s") for k in DEPTHS}
        g = {k: _avg(d.get(k, []), "gaussians") for k in DEPTHS}
        fixed = [m[k] for k in ("0", "1", "2") if m[k] == m[k]]
        best = max(fixed) if fixed else float("nan")
        g1, g2, ga = m["1"] - m["0"], m["2"] - m["0"], m["auto"] - best
        share = c["auto"] / c["2"] if c["2"] > 0 else float("nan")
        for k, v in (("d1", g1), ("d2", g2), ("auto_best", ga), ("auto_cpu", share)):
            if v == v:
                gains[k].append(v)
        flag = " (below)" if g2 < -noise else ""
        rows.append(
            f"| {scene} | {_fmt(m['0'], '.2f')} | {_fmt(m['1'], '.2f')} | {_fmt(m['2'], '.2f')} | "
            f"{_fmt(m['auto'], '.2f')} | {_fmt(g1, '+.2f')} | {_fmt(g2, '+.2f')}{flag} | {_fmt(ga, '+.2f')} | "
            f"{_fmt(p['0'], '.2f')} / {_fmt(p['2'], '.2f')} | {' / '.join(_fmt(c[k], '.0f') for k in DEPTHS)} | "
            f"{_fmt(share, '.0%')} | {' / '.join(_fmt(g[k], '.0f') for k in ('0', '2', 'auto'))} | "
            f"{' / '.join(sorted({r['grown'] for r in d.get('auto', [])}))} |"
        )
    if data:

        def mean(k: str, spec: str) -> str:
            return _fmt(float(np.mean(gains[k])) if gains[k] else float("nan"), spec)

        rows.append(
            f"| **mean of {len(data)}** | | | | | {mean('d1', '+.2f')} | {mean('d2', '+.2f')} | "
            f"{mean('auto_best', '+.2f')} | | | {mean('auto_cpu', '.0%')} | | |"
        )
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--noise", type=float, default=0.0, help="dB: a depth-2 loss beyond this is flagged")
    a = ap.parse_args(argv)
    print(table(collect(a.runs), a.noise))


if __name__ == "__main__":
    main()
