"""A network-like relative disparity for a generated scene, and how well its per-frame fit places a moving object.

Issue #28 asks whether monocular depth, used as relative depth, puts a moving object at the right depth. A
generated scene has no network prior, so ``write`` makes one from its exact depth (``SCENE/gt_priors/depth``,
written by ``nvls gt-priors``) with the errors a network's has: per frame an unknown scale and shift of the
inverse depth, a smooth multiplicative field (``--field``, relative amplitude), pixel noise (``--noise``) and a
per-object relative bias (``--object-error``: each connected region of the exact dynamic mask is drawn nearer
or farther by up to this fraction). Import it as any disparity (``--depth-maps OUT --set
priors.depth_import.kind=disparity --set priors.depth_import.fit_scale_shift=true --set
priors.depth_import.merge=fill``).

``fit`` reads the scene's cached classical depth (``SCENE/priors/x<downscale>/depth-*``) and reports, per frame,
the median ratio of fitted to true depth over the smallest moving region (the twin's ball) for the ways of
fitting the disparity to the classical depth: all pixels (what ``merge=fill`` did before the refit), without
the exact dynamic mask, without a run's own motion masks (``--run RUN``: its ``checkpoints/motion.npz``, the
priors' masks and the masks refined after the static warm-up), and the same with balanced weights
(``priors.depth_import.fit_balance_bins``).

    python -m benchmarks.speed.twin_mono_prior write SCENE OUT [--seed 0] [--object-error 0.1]
    python -m benchmarks.speed.twin_mono_prior fit SCENE DISP [--run RUN] [--downscale 2]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from worldtree.priors.imported import balanced_weights, fit_scale_shift_robust


def _exact(scene: Path) -> tuple[list[Path], list[Path]]:
    depth = sorted((scene / "gt_priors" / "depth").glob("*.npy"))
    if not depth:
        raise SystemExit(
            f"error: {scene / 'gt_priors' / 'depth'}: no exact depth; run `nvls gt-priors` first"
        )
    return depth, [scene / "gt_priors" / "masks" / f"{p.stem}.png" for p in depth]


def write(scene: Path, out: Path, seed: int, field: float, noise: float, object_error: float) -> None:
    """Write ``OUT/<frame>.npy`` ``[H, W]`` float32 disparities (see the module docstring)."""
    rng = np.random.default_rng(seed)
    depth_files, mask_files = _exact(scene)
    out.mkdir(parents=True, exist_ok=True)
    bias: dict[int, float] = {}  # region rank by area -> bias, the same object every frame
    for dp, mp in zip(depth_files, mask_files, strict=True):
        z = np.load(dp).astype(np.float64)
        H, W = z.shape
        disp = 1.0 / np.maximum(z, 1e-9)
        smooth = cv2.resize(rng.normal(size=(4, 6)), (W, H), interpolation=cv2.INTER_CUBIC)
        disp *= 1.0 + field * smooth
        dyn = cv2.imread(str(mp), cv2.IMREAD_UNCHANGED) > 0
        n, lab = cv2.connectedComponents(dyn.astype(np.uint8))
        order = np.argsort([-(lab == k).sum() for k in range(1, n)])
        for rank, k in enumerate(order):
            b = bias.setdefault(rank, float(rng.uniform(-object_error, object_error)))
            disp[lab == k + 1] *= 1.0 + b
        disp *= 1.0 + rng.normal(0.0, noise, disp.shape)
        a, s = rng.uniform(5.0, 20.0), rng.uniform(0.0, 5.0) * float(np.median(disp))
        np.save(out / f"{dp.stem}.npy", (a * disp + s).astype(np.float32))
    print(f"wrote {len(depth_files)} disparities to {out} (object biases by size rank: {bias})")


def fit(scene: Path, disp_dir: Path, run: Path | None, downscale: int) -> None:
    """Print the fitted-to-true depth ratio of the smallest moving region per frame and fitting variant."""
    depth_files, mask_files = _exact(scene)
    caches = sorted((scene / "priors" / f"x{downscale}").glob("depth-*"))
    if not caches:
        raise SystemExit(
            f"error: {scene}/priors/x{downscale}: no classical depth cache; run a Base run first"
        )
    run_masks = refined = None
    if run is not None:
        motion = np.load(run / "checkpoints" / "motion.npz")
        run_masks, refined = motion["mask_before"], motion["mask"]
    k7 = np.ones((7, 7), np.uint8)
    rows: dict[str, list[float]] = {}
    for t, (dp, mp) in enumerate(zip(depth_files, mask_files, strict=True)):
        c = np.load(caches[0] / f"{t:05d}.npz")
        ref, conf = c["depth"].astype(np.float64), c["conf"].astype(np.float64)
        H, W = ref.shape
        truth = cv2.resize(np.load(dp), (W, H), interpolation=cv2.INTER_NEAREST)
        dyn = (
            cv2.resize(cv2.imread(str(mp), cv2.IMREAD_UNCHANGED), (W, H), interpolation=cv2.INTER_NEAREST) > 0
        )
        disp = cv2.resize(np.load(disp_dir / f"{dp.stem}.npy"), (W, H), interpolation=cv2.INTER_AREA)
        n, lab = cv2.connectedComponents(dyn.astype(np.uint8))
        if n < 2:
            continue
        obj = lab == 1 + int(np.argmin([(lab == k).sum() for k in range(1, n)]))
        target = 1.0 / np.maximum(ref, 1e-9)
        variants = {"all pixels": conf, "exact mask out": conf * (cv2.dilate(dyn.astype(np.uint8), k7) == 0)}
        if run_masks is not None:
            variants["run masks out"] = conf * (cv2.dilate(run_masks[t].astype(np.uint8), k7) == 0)
            variants["refined masks out"] = conf * (cv2.dilate(refined[t].astype(np.uint8), k7) == 0)
        for name, w in list(variants.items()):
            if name != "all pixels":
                variants[f"{name}, balanced"] = balanced_weights(disp, w, 10)
        for name, w in variants.items():
            a, b = fit_scale_shift_robust(disp, target, w, 2.5)
            z = 1.0 / np.maximum(a * disp[obj] + b, 1e-9)
            rows.setdefault(name, []).append(float(np.median(z / truth[obj])))
    print(f"{'fit':28s} fitted / true depth of the smallest moving region, per frame | median |ratio - 1|")
    for name, r in rows.items():
        print(f"{name:28s} {' '.join(f'{x:.2f}' for x in r)} | {np.median(np.abs(np.array(r) - 1)):.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    w = sub.add_parser("write", help="write a network-like disparity from the exact depth")
    w.add_argument("scene", type=Path)
    w.add_argument("out", type=Path)
    w.add_argument("--seed", type=int, default=0)
    w.add_argument("--field", type=float, default=0.05)
    w.add_argument("--noise", type=float, default=0.02)
    w.add_argument("--object-error", type=float, default=0.1)
    f = sub.add_parser("fit", help="compare the per-frame fits on the smallest moving region")
    f.add_argument("scene", type=Path)
    f.add_argument("disp", type=Path)
    f.add_argument("--run", type=Path, default=None)
    f.add_argument("--downscale", type=int, default=2)
    a = ap.parse_args()
    if a.cmd == "write":
        write(a.scene, a.out, a.seed, a.field, a.noise, a.object_error)
    else:
        fit(a.scene, a.disp, a.run, a.downscale)


if __name__ == "__main__":
    main()
