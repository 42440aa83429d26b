"""Base against the static baseline on a generated scene with moving objects, with classical and exact priors.

    python -m benchmarks.speed.base_proof [--out DIR] [--size 320x180] [--steps 40] [--preset quick]
                                    [--seeds 0,1] [--no-ablations] [--device auto]

Generates a slow-then-fast capture (as ``wtbench demo``), builds it with ``nvls build``, writes its exact priors
(``nvls gt-priors``), then runs, for every seed: the static baseline; Base with classical priors; Base with the
exact priors; and, unless ``--no-ablations``, Base with exact priors and ``--ablate ba`` / ``--ablate sw``.
Finished runs are skipped, so an interrupted script resumes. Prints one row per run (test-view scores, train
wall time, peak memory, scaffold nodes) and the mPSNR gain of each Base row over the static run of the same
seed. Figures are printed, never asserted (the end-to-end test asserts a margin on a smaller scene).

The exact priors stand in for the networks the paper uses (metric depth, CoTracker, SAM); scores with them
are not comparable with classical-prior scores.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class ProofRow:
    """One run of the comparison."""

    method: str
    priors: str
    """"classical" or "exact"."""
    ablate: tuple[str, ...] = ()
    seed: int = 0


def prepare_scene(
    out: Path,
    size: tuple[int, int],
    steps: int,
    log=print,
    name: str = "SynthBalloon",
    motion: str = "slow_fast",
    seed: int = 0,
) -> tuple[Path, Path]:
    """Generate (``nvls synth`` with ``motion``, ``seed``), build and write exact priors for the capture
    ``name`` under ``out``, each step skipped when done.

    Returns ``(scene folder, exact priors folder)``.
    """
    from nvidia_ls.build import BuildConfig, build_scene
    from nvidia_ls.gt_priors import GtPriorsConfig, write_gt_priors
    from nvidia_ls.synth import SynthConfig, write_raw_scene

    raw = out / "raw" / name
    if not (raw / "gt" / "cameras.json").is_file():
        log(f"generating {raw} ({size[0]}x{size[1]}, {steps} steps, {motion}, seed {seed})")
        cfg = SynthConfig(steps=steps, width=size[0], height=size[1], motion=motion, seed=seed)
        write_raw_scene(raw, cfg, force=True)
    scene = out / "scenes" / name
    if not (scene / "manifest.json").is_file():
        log(f"nvls build {raw}")
        build_scene(raw, out / "scenes", BuildConfig(force=True), log=lambda s: None)
    gt = scene / "gt_priors"
    if not (gt / "gt_priors.json").is_file():
        log(f"nvls gt-priors {raw} {scene}")
        write_gt_priors(raw, scene, gt, GtPriorsConfig(force=True))
    return scene, gt


def plan(seeds: list[int], ablations: bool) -> list[ProofRow]:
    """The runs of the comparison, in order."""
    rows: list[ProofRow] = []
    for s in seeds:
        rows += [
            ProofRow("static", "-", seed=s),
            ProofRow("base", "classical", seed=s),
            ProofRow("base", "exact", seed=s),
        ]
        if ablations:
            rows += [ProofRow("base", "exact", ("ba",), s), ProofRow("base", "exact", ("sw",), s)]
    return rows


def run_row(row: ProofRow, scene: Path, gt: Path, runs: Path, preset: str, device: str) -> dict:
    """Run (or reuse) one row; returns its scores and costs."""
    from benchmarks.runner.runs import RunRequest, execute

    priors = {}
    if row.priors == "exact":
        priors = {
            "masks": str(gt / "masks"),
            "tracks": str(gt / "tracks.npz"),
            "depth_maps": str(gt / "depth"),
        }
    options = {"ablate": list(row.ablate)} if row.ablate else {}
    res = execute(
        RunRequest(
            scene=scene, method=row.method, runs_dir=runs, preset=preset, device=device,
            overrides={"seed": row.seed}, options=options, priors=priors, progress=False,
            command=f"python -m benchmarks.speed.base_proof ({row.method}, {row.priors}, ablate={list(row.ablate)})",
        )
    )  # fmt: skip
    timing = json.loads(res.folder.timing_json.read_text())
    stats = timing.get("method_stats", {})
    return {
        **res.mean,
        "train_s": (timing.get("train") or {}).get("wall_s_all_sessions"),
        "peak_mib": timing.get("peak_rss_mib"),
        "nodes": stats.get("scaffold_nodes_final", stats.get("scaffold_nodes")),
    }


def _fmt(v, digits: int = 2) -> str:
    return "-" if v is None else f"{v:.{digits}f}" if isinstance(v, float) else str(v)


def main(argv: list[str] | None = None) -> None:
    from nvidia_ls.build import parse_size

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("base_proof"))
    ap.add_argument("--size", default="320x180")
    ap.add_argument("--steps", type=int, default=40, help="time steps of the generated capture")
    ap.add_argument("--preset", default="quick")
    ap.add_argument("--seeds", default="0", help="comma-separated seeds")
    ap.add_argument("--no-ablations", action="store_true")
    ap.add_argument("--device", default="auto")
    a = ap.parse_args(argv)
    size = parse_size(a.size)
    if size is None:
        raise SystemExit(f"error: --size {a.size!r}: give WxH, e.g. 320x180")
    seeds = [int(s) for s in a.seeds.split(",") if s.strip()]
    scene, gt = prepare_scene(a.out, size, a.steps)
    results = []
    for row in plan(seeds, not a.no_ablations):
        print(
            f"running {row.method} priors={row.priors} ablate={','.join(row.ablate) or '-'} seed={row.seed}",
            flush=True,
        )
        results.append((row, run_row(row, scene, gt, a.out / "runs", a.preset, a.device)))
    static = {r.seed: m["mpsnr"] for r, m in results if r.method == "static"}
    print()
    print(
        "| method | priors | ablate | seed | mPSNR | mSSIM | PSNR | SSIM | gain mPSNR | train s | peak MiB | nodes |"
    )
    print("|---|---|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|")
    for r, m in results:
        gain = m["mpsnr"] - static[r.seed] if r.method != "static" and r.seed in static else None
        print(
            f"| {r.method} | {r.priors} | {','.join(r.ablate) or '-'} | {r.seed} | {_fmt(m.get('mpsnr'))} | "
            f"{_fmt(m.get('mssim'), 3)} | {_fmt(m.get('psnr'))} | {_fmt(m.get('ssim'), 3)} | {_fmt(gain)} | "
            f"{_fmt(m.get('train_s'), 0)} | {_fmt(m.get('peak_mib'), 0)} | {_fmt(m.get('nodes'))} |"
        )


if __name__ == "__main__":
    main()
