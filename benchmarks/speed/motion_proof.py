"""Motion discovery before/after on generated scenes: mask IoU, dynamic-track life and Base's gain over static.

    python -m benchmarks.speed.motion_proof [--out DIR] [--size 320x180] [--steps 40] [--preset quick]
                                      [--methods base,worldtree]
                                      [--scenes demo,hard] [--seed 0] [--device auto] [--no-runs]
                                      [--track-tol 3] [--set KEY=VALUE ...] [--no-before]

Scenes (generated, built and given exact priors as ``benchmarks.base_proof`` does): ``demo`` is the
slow-then-fast capture of ``wtbench demo`` / ``base_proof``; ``hard`` moves its textured objects at constant
(fast) speed through the whole capture, with another seed. In both, consecutive training frames come from
different rig cameras (the NVIDIA ping-pong order), so every flow and track step crosses a camera change.

For each scene it prints, against the exact masks and tracks of ``nvls gt-priors``:

- **before**: the plain EPI masks and Lucas-Kanade dynamic tracks (``priors.motion.enabled=false``), Base
  without mask refinement, without Gaussian migration, with held track ends (no trajectory completion) and the
  prior's depth on moving objects (no trajectory depth);
- **after (priors)**: the epipolar + depth-consistency cues fused, dynamic tracks chained through flow;
- **after (Base)**: the masks refined with the static warm-up's residual inside the Base run (read from its
  ``checkpoints/motion.npz``), with migration, trajectory completion and trajectory depth on;
- **fitted model**: the tracks read off the fitted Base model (:mod:`worldtree.diagnostics.model_tracks`: each
  dynamic Gaussian carried by the scaffold and projected, where it is in view and not hidden), over every frame
  and only within 2 temporal standard deviations of its own frame (how far the model's motion is right);
- with ``--methods base,worldtree``: the WorldTree method before and after as well (its root is the Base
  stages, so its masks and tracks are Base's; only its mPSNR is added);

mask IoU / precision / recall over all frames, the median visible frames of the dynamic tracks against the
median number of frames an object is visible, the fraction of dynamic tracks whose error to the exact motion
stays below ``--track-tol`` px (:func:`track_errors`), how many are linked from pieces
(:mod:`worldtree.priors.track_linking`) and that fraction among them, and the mPSNR of static and of both Base runs (gain over
static), with its means over the first and second half of the test frames (the demo's slow and fast halves).
Finished runs are reused, so an interrupted script resumes. Figures are printed, never asserted.

``--set KEY=VALUE`` (repeatable, the ``wtbench run --set`` syntax) is added to the "after" runs only, whose tag
then ends with the settings' digest, so that their results sit beside the plain "after" runs of the same
folder; ``priors.*`` keys also change the "after (priors)" row. ``--no-before`` skips the Base "before" runs
(for a comparison of "after" settings in a folder that already holds them or does not need them).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

BEFORE_SETS = [
    "priors.motion.enabled=false", "photometric.migrate_every=0",
    "scaffold.complete_radius_units=0", "scaffold.trajectory_depth=false",
]  # fmt: skip
AFTER_SETS = [
    "priors.motion.enabled=true", "refine_masks=true", "photometric.migrate_every=100",
    "scaffold.complete_radius_units=12", "scaffold.trajectory_depth=true",
]  # fmt: skip
"""The defaults of the quick preset, written out so the 'after' rows do not depend on a default changing."""


def prepare(out: Path, name: str, size: tuple[int, int], steps: int, log=print) -> tuple[Path, Path]:
    """Generate, build and write exact priors for scene ``name`` (``demo`` or ``hard``) under ``out``."""
    from benchmarks.speed.base_proof import prepare_scene

    motion, seed = ("slow_fast", 0) if name == "demo" else ("constant", 1)
    return prepare_scene(out, size, steps, log, name=name, motion=motion, seed=seed)


def _resize_masks(masks: np.ndarray, H: int, W: int) -> np.ndarray:
    import cv2

    if masks.shape[1:] == (H, W):
        return masks
    return np.stack(
        [cv2.resize(m.astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST) > 0 for m in masks]
    )


def mask_scores(pred: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """IoU, precision and recall of ``pred`` against ``gt`` ([T, H, W] bool), pooled over all frames."""
    inter = float((pred & gt).sum())
    return {
        "iou": inter / max(float((pred | gt).sum()), 1.0),
        "precision": inter / max(float(pred.sum()), 1.0),
        "recall": inter / max(float(gt.sum()), 1.0),
    }


def track_life(visible: np.ndarray, dynamic: np.ndarray) -> tuple[int, float]:
    """``(number, median visible frames)`` of the dynamic tracks (``visible`` [T, N], ``dynamic`` [N])."""
    life = visible[:, dynamic].sum(0)
    return int(dynamic.sum()), float(np.median(life)) if life.size else 0.0


def exact_tracks(gt: Path, W: int, H: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The exact dynamic tracks of ``nvls gt-priors`` at the working size ``W`` x ``H``: ``(xy [T, M, 2] px,
    visible [T, M], object id [M])`` (pixel centres at integers at both sizes)."""
    z = np.load(gt / "tracks.npz")
    dyn = z["object_id"] > 0
    s = np.array([W, H], np.float64) / np.asarray(z["image_size"], np.float64)
    xy = ((z["tracks"][:, dyn] + 0.5) * s - 0.5).astype(np.float32)
    return xy, z["visibility"][:, dyn], z["object_id"][dyn]


def track_errors(
    xy: np.ndarray,
    vis: np.ndarray,
    gt_xy: np.ndarray,
    gt_vis: np.ndarray,
    gt_obj: np.ndarray | None = None,
    radius: float = 3.0,
    k: int = 6,
) -> np.ndarray:
    """Largest error (px) of each track ``xy`` [T, N, 2] / ``vis`` [T, N] against the exact motion: ``[N]``.

    A track starting at ``x`` in frame f should move as the exact tracks ``gt_xy`` [T, M, 2] / ``gt_vis``
    [T, M] around it (up to ``k`` of those visible at f within ``radius`` px, and with ``gt_obj`` [M] only
    those on the object of the nearest one): at frame t its reference is
    the affine map that carries those still visible at t from their frame-f to their frame-t positions
    (least squares; locally exact for a rigid object in projection, rotating included), applied to ``x``;
    with fewer than 3 of them, or collinear ones, their mean displacement. NaN where no exact track starts
    near it (off the moving objects) or none stays visible."""
    from scipy.spatial import cKDTree

    T, N = vis.shape
    out = np.full(N, np.nan)
    first = vis.argmax(0)
    for f in range(T):
        ids = np.flatnonzero((first == f) & vis[f])
        cand = np.flatnonzero(gt_vis[f])
        if not len(ids) or not len(cand):
            continue
        kk = min(k, len(cand))
        d, nn = cKDTree(gt_xy[f, cand]).query(xy[f, ids], k=kk)
        d, nn = d.reshape(len(ids), kk), nn.reshape(len(ids), kk)
        for r, n in enumerate(ids):
            g = cand[nn[r][d[r] <= radius]]
            if gt_obj is not None and len(g):
                g = g[gt_obj[g] == gt_obj[g[0]]]
            errs = []
            for t in np.flatnonzero(vis[:, n]):
                h = g[gt_vis[t, g]]
                if not len(h):
                    continue
                src, dst = gt_xy[f, h].astype(np.float64), gt_xy[t, h].astype(np.float64)
                x = xy[f, n].astype(np.float64)
                ref = x + (dst - src).mean(0)
                if len(h) >= 3:
                    c = src.mean(0)
                    A = np.concatenate([src - c, np.ones((len(h), 1))], 1)
                    if np.linalg.matrix_rank(A[:, :2], tol=0.5) == 2:
                        M = np.linalg.lstsq(A, dst, rcond=None)[0]
                        ref = np.concatenate([x - c, [1.0]]) @ M
                errs.append(float(np.linalg.norm(xy[t, n] - ref)))
            if errs:
                out[n] = max(errs)
    return out


def accuracy_row(xy, vis, dynamic, pieces, exact, tol_px: float) -> dict:
    """Fractions of the dynamic tracks (and of the linked ones, ``pieces`` >= 2) whose largest error to the
    exact motion (``exact`` = :func:`exact_tracks`) stays below ``tol_px``, over those with an exact
    reference; and how many are linked."""
    sel = np.flatnonzero(dynamic)
    err = track_errors(xy[:, sel], vis[:, sel], *exact)
    ok = ~np.isnan(err)
    linked = (pieces[sel] >= 2) if pieces is not None else np.zeros(len(sel), bool)

    def frac(m):
        return float((err[m & ok] < tol_px).mean()) if (m & ok).any() else None

    return {
        "accurate": frac(np.ones(len(sel), bool)),
        "linked": int(linked.sum()),
        "linked_accurate": frac(linked),
    }


def reference_floor(exact, tol_px: float, every: int = 4) -> float | None:
    """What :func:`track_errors` gives perfect tracks: the fraction of every ``every``-th exact track, held out
    and scored against the others, that stays below ``tol_px`` (the reference's own error bounds the
    accuracy column)."""
    gt_xy, gt_vis, gt_obj = exact
    held = np.arange(gt_xy.shape[1]) % every == 0
    err = track_errors(gt_xy[:, held], gt_vis[:, held], gt_xy[:, ~held], gt_vis[:, ~held], gt_obj[~held])
    ok = ~np.isnan(err)
    return float((err[ok] < tol_px).mean()) if ok.any() else None


def object_frames(gt: Path) -> float:
    """Median over the moving objects of the number of training frames in which each is visible."""
    z = np.load(gt / "tracks.npz")
    vis, obj = z["visibility"], z["object_id"]
    counts = [int(vis[:, obj == o].any(1).sum()) for o in np.unique(obj) if o > 0] or [
        int(vis[:, obj == o].any(1).sum()) for o in np.unique(obj)
    ]
    return float(np.median(counts))


def priors_rows(
    scene_dir: Path, gt: Path, downscale: int, tol_px: float = 3.0, sets: list[str] | None = None
) -> dict[str, dict]:
    """Mask and track figures of the priors before (plain EPI, LK) and after (fused cues, chained tracks);
    ``sets``: ``priors.*`` assignments applied to the "after" priors."""
    import dataclasses

    from methods.config_overrides import apply_overrides
    from worldtree.imageio import read_mask
    from worldtree.priors import PriorsConfig, compute_priors
    from worldtree.priors.config import MotionConfig
    from worldtree.scene import load_scene

    scene = load_scene(scene_dir, downscale=downscale)
    cache = scene_dir / "priors" / f"x{downscale}"
    T, H, W = scene.images.shape[:3]
    truth = _resize_masks(np.stack([read_mask(p) for p in sorted((gt / "masks").iterdir())]), H, W)
    exact = exact_tracks(gt, W, H)
    out = {}
    for name, cfg in (
        ("before", dataclasses.replace(PriorsConfig(), motion=MotionConfig(enabled=False))),
        (
            "after (priors)",
            apply_overrides(
                dataclasses.replace(PriorsConfig(), motion=MotionConfig(enabled=True)),
                [s.removeprefix("priors.") for s in sets or [] if s.startswith("priors.")],
            ),
        ),
    ):
        pri = compute_priors(scene, cfg, cache)
        n, life = track_life(pri.track_vis, pri.track_dynamic)
        acc = accuracy_row(pri.tracks, pri.track_vis, pri.track_dynamic, pri.track_pieces, exact, tol_px)
        out[name] = {**mask_scores(pri.epi_mask, truth), "tracks": n, "life": life, **acc}
    return out, truth, exact


def model_rows(
    model_dir: Path, scene_dir: Path, downscale: int, exact, tol_px: float, max_tracks: int = 2000
):
    """Track figures of the tracks read off a fitted Base model (:mod:`worldtree.diagnostics.model_tracks`):
    every frame where a Gaussian is in view and unhidden, and only the frames within 2 temporal standard
    deviations of its own frame (where its temporal opacity still draws it)."""
    import torch

    from worldtree.diagnostics.model_tracks import model_tracks, pick_gaussians
    from worldtree.dynamic import DynamicGaussians
    from worldtree.gaussians import GaussianSet
    from worldtree.motion.scaffold import Scaffold
    from worldtree.scene import load_scene

    scene = load_scene(scene_dir, downscale=downscale, load_masks=False)
    T, H, W = scene.images.shape[:3]
    static = GaussianSet.load(model_dir / "static_gaussians.pt")
    dynamic = DynamicGaussians.load(model_dir / "dynamic_gaussians.pt")
    sc = torch.load(model_dir / "scaffold_cameras.pt", map_location="cpu", weights_only=False)
    scaffold = Scaffold.from_state(sc["scaffold"])
    idx = pick_gaussians(dynamic, max_tracks)
    out = {}
    for name, window in (("fitted model, all frames", None), ("fitted model, own time +-2 std", 2.0)):
        tr = model_tracks(static, dynamic, scaffold, scene.Ks, sc["w2cs"], W, H, idx, window=window)
        xy, vis = tr.xy.cpu().numpy(), tr.visible.cpu().numpy()
        dyn = vis.any(0)
        n, life = track_life(vis, dyn)
        out[name] = {"iou": None, "precision": None, "recall": None, "tracks": n, "life": life,
                     **accuracy_row(xy, vis, dyn, None, exact, tol_px)}  # fmt: skip
    return out


def half_means(metrics_csv: Path) -> tuple[float, float]:
    """Mean per-frame mPSNR over the first and the second half of the test frames (the demo's slow and fast
    halves), from a run's ``metrics.csv``."""
    import csv

    with open(metrics_csv, newline="") as f:
        vals = [float(r["mpsnr"]) for r in csv.DictReader(f) if r.get("mpsnr")]
    n = len(vals) // 2
    if n == 0:
        return float("nan"), float("nan")
    return float(np.mean(vals[:n])), float(np.mean(vals[n:]))


def run(scene: Path, runs: Path, method: str, sets: list[str], preset: str, device: str, seed: int, tag: str):
    from benchmarks.runner.runs import RunRequest, execute

    res = execute(
        RunRequest(
            scene=scene, method=method, runs_dir=runs, preset=preset, device=device, overrides={"seed": seed},
            sets=list(sets), progress=False, tag=tag,
            command=f"python -m benchmarks.speed.motion_proof ({method}, {tag})",
        )
    )  # fmt: skip
    timing = json.loads(res.folder.timing_json.read_text())
    return res, timing.get("method_stats", {})


def main(argv: list[str] | None = None) -> None:
    from nvidia_ls.build import parse_size

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("motion_proof"))
    ap.add_argument("--size", default="320x180")
    ap.add_argument("--steps", type=int, default=40, help="time steps of the generated captures")
    ap.add_argument("--preset", default="quick")
    ap.add_argument("--scenes", default="demo,hard")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--no-runs", action="store_true", help="mask and track figures of the priors only")
    ap.add_argument("--methods", default="base", help="base, or base,worldtree (WorldTree before/after too)")
    ap.add_argument(
        "--track-tol",
        type=float,
        default=3.0,
        help="a track is accurate while its error to the exact motion stays below this (px, working size)",
    )
    ap.add_argument(
        "--set",
        dest="sets",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="added to the 'after' runs (tag suffixed with the settings' digest); priors.* also to the priors",
    )
    ap.add_argument("--no-before", action="store_true", help="skip the Base (and WorldTree) 'before' runs")
    a = ap.parse_args(argv)
    from methods.config_overrides import sets_digest

    after_sets = AFTER_SETS + list(a.sets)
    after_tag = f"{a.preset}-after-s{a.seed}" + (f"-{sets_digest(a.sets)}" if a.sets else "")
    size = parse_size(a.size)
    if size is None:
        raise SystemExit(f"error: --size {a.size!r}: give WxH, e.g. 320x180")
    from methods.registry import get_method

    downscale = get_method("base").presets[a.preset]().downscale
    methods = [m.strip() for m in a.methods.split(",") if m.strip()]
    if not set(methods) <= {"base", "worldtree"} or "base" not in methods:
        raise SystemExit(f"error: --methods {a.methods!r}: give base or base,worldtree")
    table, floors = [], {}
    for name in [s.strip() for s in a.scenes.split(",") if s.strip()]:
        if name not in ("demo", "hard"):
            raise SystemExit(f"error: --scenes {name!r}: choose among demo, hard")
        scene, gt = prepare(a.out, name, size, a.steps)
        rows, truth, exact = priors_rows(scene, gt, downscale, a.track_tol, a.sets)
        floors[name] = reference_floor(exact, a.track_tol)
        visible = object_frames(gt)
        psnr, halves = {}, {}
        if not a.no_runs:
            runs = a.out / "runs"
            print(f"[{name}] static", flush=True)
            res, _ = run(scene, runs, "static", [], a.preset, a.device, a.seed, f"{a.preset}-s{a.seed}")
            psnr["static"] = res.mean.get("mpsnr")
            halves["static"] = half_means(res.folder.metrics_csv)
            if not a.no_before:
                print(f"[{name}] base before", flush=True)
                tag = f"{a.preset}-before-s{a.seed}"
                res, _ = run(scene, runs, "base", BEFORE_SETS, a.preset, a.device, a.seed, tag)
                psnr["before"] = res.mean.get("mpsnr")
                halves["before"] = half_means(res.folder.metrics_csv)
            print(f"[{name}] base after", flush=True)
            res, st = run(scene, runs, "base", after_sets, a.preset, a.device, a.seed, after_tag)
            psnr["after (Base)"] = res.mean.get("mpsnr")
            halves["after (Base)"] = half_means(res.folder.metrics_csv)
            mot = res.folder.checkpoints / "motion.npz"
            if mot.is_file():
                z = np.load(mot)
                n, life = track_life(z["visible"], z["dynamic"])
                pieces = z["pieces"] if "pieces" in z.files else None
                acc = accuracy_row(z["tracks"], z["visible"], z["dynamic"], pieces, exact, a.track_tol)
                rows["after (Base)"] = {**mask_scores(z["mask"], truth), "tracks": n, "life": life, **acc,
                                        "migration": st.get("migration", {}),
                                        "object_flow": {k.removeprefix("object_flow_"): v for k, v in
                                                        st.get("motion_refine", {}).get("chained_track_links",
                                                                                        {}).items()
                                                        if k.startswith("object_flow_")}}  # fmt: skip
            if (res.folder.model / "dynamic_gaussians.pt").is_file():
                rows.update(model_rows(res.folder.model, scene, downscale, exact, a.track_tol))
            if "worldtree" in methods:
                for k, sets, src, tag in (
                    ("before", BEFORE_SETS, "before", f"{a.preset}-before-s{a.seed}"),
                    ("after", after_sets, "after (Base)", after_tag),
                ):
                    if k == "before" and a.no_before:
                        continue
                    print(f"[{name}] worldtree {k}", flush=True)
                    res, _ = run(scene, runs, "worldtree", sets, a.preset, a.device, a.seed, tag)
                    psnr[f"{k} (WorldTree)"] = res.mean.get("mpsnr")
                    halves[f"{k} (WorldTree)"] = half_means(res.folder.metrics_csv)
                    if src in rows:  # the tree's root is the Base stages: same masks and tracks
                        rows[f"{k} (WorldTree)"] = {
                            x: v for x, v in rows[src].items() if x not in ("migration", "object_flow")
                        }
        for k, r in rows.items():
            p = psnr.get(k) if k != "after (priors)" else None
            gain = p - psnr["static"] if p is not None and psnr.get("static") is not None else None
            table.append((name, k, r, visible, psnr.get("static"), p, gain, halves.get(k)))
    print()
    tol = f"{a.track_tol:g} px"
    print(f"| scene | masks / tracks | mask IoU | P | R | dyn. tracks | median life | object frames | "
          f"tracks < {tol} | linked (< {tol}) | static mPSNR | method mPSNR | gain | 1st / 2nd half |")  # fmt: skip
    print("|---|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|")

    def f(v, d=2):
        return "-" if v is None else f"{v:.{d}f}"

    for name, floor in floors.items():
        print(f"[{name}] exact tracks held out and scored like the others: {f(floor)} below {tol}")
    for name, k, r, vis, st, p, g, hv in table:
        hs = "-" if hv is None else f"{f(hv[0])} / {f(hv[1])}"
        acc = f"{r['linked']} ({f(r['linked_accurate'])})" if r.get("linked") else "0"
        print(
            f"| {name} | {k} | {f(r['iou'])} | {f(r['precision'])} | {f(r['recall'])} | {r['tracks']} | "
            f"{f(r['life'], 1)} | {f(vis, 0)} | {f(r.get('accurate'))} | {acc} | {f(st)} | {f(p)} | "
            f"{'-' if g is None else f'{g:+.2f}'} | {hs} |"
        )
        if "migration" in r:
            m = r["migration"]
            print(f"|   | migration: {m.get('static_to_dynamic', 0)} static->dynamic, "
                  f"{m.get('dynamic_to_static', 0)} dynamic->static | | | | | | | | | | | |")  # fmt: skip
        if r.get("object_flow"):
            m = r["object_flow"]
            print(f"|   | object flow: {m.get('matched', 0)} of {m.get('components', 0)} component matches "
                  f"accepted (refused: {m.get('refused_flat', 0)} flat, {m.get('refused_window', 0)} window, "
                  f"{m.get('refused_mask', 0)} off-mask, {m.get('refused_score', 0)} score) "
                  "| | | | | | | | | | | |")  # fmt: skip


if __name__ == "__main__":
    main()
