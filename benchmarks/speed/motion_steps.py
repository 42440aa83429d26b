"""How far one frame-to-frame step of the classical cues follows the moving objects of a generated capture.

    python -m benchmarks.speed.motion_steps [--scenes demo,hard] [--size 160x90] [--steps 40] [--tol 1.5]

Why the chained dynamic tracks stay short (issue 11): every track step is a flow step between consecutive
training frames, which on the NVIDIA rig changes camera *and* time. This script separates the two on the
generated scenes of ``benchmarks.speed.motion_proof`` (``demo``: slow then fast; ``hard``: constant, seed 1),
rendered directly at the working size with their exact motion (``nvidia_ls.synth.gt_flow``), and prints per
half of the capture (the demo's slow and fast halves):

- the objects' median exact motion per step (px, camera change included);
- **DIS, camera change**: the fraction of the object pixels of frame t (visible at t+1) whose DIS flow to
  frame t+1 (the next rig camera) lands within ``--tol`` px, started from the exact camera-induced flow
  (the best the pipeline's depth-guided start can give);
- **DIS, same camera**: the same with frame t+1 rendered from frame t's camera -- no camera change, only the
  objects' motion;
- **SIFT**: ratio-test matches between the object regions of frames t and t+1 (camera change), and how many
  of them land within 2 px of the exact position;
- **one affine per object, same camera**: each object's exact region of frame t aligned to frame t+1 by ECC
  with a whole-object affine warp (OpenCV ``findTransformECCWithMask``), started from the object's exact median
  displacement -- an optimistic start -- and scored like DIS: whether a motion model per object, rather than
  per pixel, would follow the objects.

If the same-camera row is not much better than the camera-change row, removing the camera change (by
re-rendering, rectifying or a better depth-guided start) cannot lengthen the tracks: the objects' own motion
per step is the limit. Figures are printed, never asserted.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

import cv2
import numpy as np

SCENES = {"demo": ("slow_fast", 0), "hard": ("constant", 1)}
"""Motion and seed of motion_proof's scenes."""

HAS_ECC_MASK = hasattr(cv2, "findTransformECCWithMask")
"""ECC with the template's mask is OpenCV >= 4.13; without it the per-object affine column stays NaN."""


@dataclass
class StepFigures:
    """One step t -> t+1. NaN where the object shows fewer than 5 usable pixels."""

    speed_px: float
    """Median exact motion of the object pixels of frame t into frame t+1 (camera change included)."""
    dis_change: float
    dis_same_camera: float
    sift_matches: int
    sift_right: int
    affine_same_camera: float = float("nan")


def object_step_accuracy(view0, view1, flow_gt: np.ndarray, flow: np.ndarray, tol: float) -> float:
    """Fraction of the moving-object pixels of ``view0`` still seen on the same object in ``view1`` whose
    ``flow`` [H, W, 2] (px) is within ``tol`` px of ``flow_gt`` [H, W, 2] (NaN where undefined); NaN when
    fewer than 5 such pixels."""
    H, W = flow_gt.shape[:2]
    yy, xx = np.nonzero(view0.object_id > 0)
    gt = flow_gt[yy, xx]
    tgt = np.stack([xx, yy], -1) + gt
    ok = np.isfinite(gt).all(-1)
    tgt = np.where(ok[:, None], tgt, -1.0)
    inside = ok & (tgt[:, 0] >= 0) & (tgt[:, 0] <= W - 1) & (tgt[:, 1] >= 0) & (tgt[:, 1] <= H - 1)
    xi = np.clip(np.round(tgt[:, 0]).astype(np.int64), 0, W - 1)
    yi = np.clip(np.round(tgt[:, 1]).astype(np.int64), 0, H - 1)
    # Visible at t+1: the exact target pixel shows the same object (not hidden, not turned away).
    seen = inside & (view1.object_id[yi, xi] == view0.object_id[yy, xx])
    if seen.sum() < 5:
        return float("nan")
    err = np.linalg.norm(flow[yy, xx] - gt, axis=-1)
    return float((err[seen] < tol).mean())


def sift_step(view0, view1, flow_gt: np.ndarray, right_px: float = 2.0) -> tuple[int, int]:
    """``(ratio-test matches, matches within right_px of the exact position)`` of SIFT features detected on the
    moving objects (object mask dilated by 2 px) of ``view0`` and ``view1``."""
    sift = cv2.SIFT_create(contrastThreshold=0.01)
    feats = []
    for v in (view0, view1):
        mask = cv2.dilate((v.object_id > 0).astype(np.uint8) * 255, np.ones((5, 5), np.uint8))
        feats.append(sift.detectAndCompute(cv2.cvtColor(v.rgb, cv2.COLOR_RGB2GRAY), mask))
    (k0, d0), (k1, d1) = feats
    if d0 is None or d1 is None or len(k0) < 2 or len(k1) < 2:
        return 0, 0
    pairs = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d0, d1, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < 0.8 * p[1].distance]
    H, W = flow_gt.shape[:2]
    right = 0
    for m in good:
        p0, p1 = np.array(k0[m.queryIdx].pt), np.array(k1[m.trainIdx].pt)
        f = flow_gt[min(max(round(p0[1]), 0), H - 1), min(max(round(p0[0]), 0), W - 1)]
        right += int(np.isfinite(f).all() and np.linalg.norm(p0 + f - p1) < right_px)
    return len(good), right


def object_affine_flow(view0, gray0: np.ndarray, gray1: np.ndarray, flow_gt: np.ndarray) -> np.ndarray:
    """[H, W, 2] flow (px) of ``view0``'s objects from one affine warp per object, fitted by ECC between the
    grey images ``gray0`` and ``gray1`` [H, W] over the object's pixels and started from its exact median
    displacement (``flow_gt`` [H, W, 2]); zero off the objects and where ECC fails to converge (the start is
    kept then)."""
    H, W = gray0.shape
    g0, g1 = gray0.astype(np.float32), gray1.astype(np.float32)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
    flow = np.zeros((H, W, 2), np.float32)
    stop = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-5)
    everywhere = np.ones((H, W), np.uint8)
    for oid in np.unique(view0.object_id):
        m = view0.object_id == oid
        f = flow_gt[m]
        f = f[np.isfinite(f).all(-1)]
        if oid == 0 or len(f) < 10:
            continue
        warp = np.eye(2, 3, dtype=np.float32)
        warp[:, 2] = np.median(f, 0)
        try:
            # The mask is frame t's (the template's): findTransformECC's own mask belongs to the input image.
            _, warp = cv2.findTransformECCWithMask(g0, g1, m.astype(np.uint8), everywhere, warp,
                                                   cv2.MOTION_AFFINE, stop, 3)  # fmt: skip
        except cv2.error:  # no convergence (flat or vanishing region): keep the start
            pass
        pts = np.stack([xx[m], yy[m], np.ones(int(m.sum()), np.float32)], -1)
        flow[m] = pts @ warp.T - pts[:, :2]
    return flow


def measure(name: str, size: tuple[int, int], steps: int, tol: float) -> list[StepFigures]:
    """Per-step figures of scene ``name`` (``demo`` or ``hard``) at ``size`` (W, H) over ``steps`` time steps."""
    from nvidia_ls.sampling import pingpong
    from nvidia_ls.synth import SynthConfig, gt_flow, make_scene, render_view
    from worldtree.priors.flow import dis_flow, to_gray_u8

    motion, seed = SCENES[name]
    W, H = size
    sc = make_scene(SynthConfig(steps=steps, width=W, height=H, motion=motion, seed=seed))
    cams = pingpong(list(range(1, len(sc.Ks))), steps)  # camera 0 is the held-out test camera
    cache: dict = {}

    def view(c: int, t: int):
        if (c, t) not in cache:
            cache[(c, t)] = render_view(sc, sc.Ks[c], sc.w2cs[c], W, H, t, supersample=2)
        return cache[(c, t)]

    def flow_gt(a: int, t0: int, b: int, t1: int) -> np.ndarray:
        return gt_flow(sc, sc.Ks[a], sc.w2cs[a], t0, sc.Ks[b], sc.w2cs[b], t1, W, H)[0]

    out = []
    for t in range(steps - 1):
        a, b = cams[t], cams[t + 1]
        v0, v1, v1_same = view(a, t), view(b, t + 1), view(a, t + 1)
        gt, gt_same = flow_gt(a, t, b, t + 1), flow_gt(a, t, a, t + 1)
        obj = v0.object_id > 0
        speeds = np.linalg.norm(gt[obj], axis=-1)
        speed = float(np.nanmedian(speeds)) if np.isfinite(speeds).any() else float("nan")
        camera_only = np.nan_to_num(flow_gt(a, t, b, t))  # the objects held still: the camera's share
        g0 = to_gray_u8(v0.rgb)
        f_change = dis_flow(g0, to_gray_u8(v1.rgb), "medium", camera_only)
        g1_same = to_gray_u8(v1_same.rgb)
        f_same = dis_flow(g0, g1_same, "medium")
        affine = (
            object_step_accuracy(v0, v1_same, gt_same, object_affine_flow(v0, g0, g1_same, gt_same), tol)
            if HAS_ECC_MASK
            else float("nan")
        )
        out.append(
            StepFigures(
                speed,
                object_step_accuracy(v0, v1, gt, f_change, tol),
                object_step_accuracy(v0, v1_same, gt_same, f_same, tol),
                *sift_step(v0, v1, gt),
                affine,
            )
        )
    return out


def summary(rows: list[StepFigures]) -> dict[str, dict[str, float]]:
    """Means (median speed) of the figures over the first and second half of the steps."""
    half = (len(rows) + 1) // 2
    res = {}
    for label, part in (("first half", rows[:half]), ("second half", rows[half:])):
        col = {k: np.array([getattr(r, k) for r in part], float) for k in StepFigures.__dataclass_fields__}
        m, r = col["sift_matches"].sum(), col["sift_right"].sum()
        with np.errstate(all="ignore"):
            res[label] = {
                "speed_px": float(np.nanmedian(col["speed_px"])),
                "dis_change": float(np.nanmean(col["dis_change"])),
                "dis_same_camera": float(np.nanmean(col["dis_same_camera"])),
                "affine_same_camera": float(np.nanmean(col["affine_same_camera"])),
                "sift_matches": float(col["sift_matches"].mean()),
                "sift_right": float(col["sift_right"].mean()),
                "sift_right_frac": float(r / m) if m > 0 else float("nan"),
            }
    return res


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="demo,hard")
    ap.add_argument("--size", default="160x90", help="working size WxH (the quick preset's 160x90)")
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--tol", type=float, default=1.5, help="px: a flow step is right within this")
    args = ap.parse_args(argv)
    try:
        W, H = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        ap.error(f"--size {args.size!r}: expected WxH, e.g. 160x90")
    names = [s.strip() for s in args.scenes.split(",") if s.strip()]
    unknown = [n for n in names if n not in SCENES]
    if unknown:
        ap.error(f"--scenes {','.join(unknown)}: choose among {', '.join(SCENES)}")
    print(f"| scene | half | object px/step | DIS, camera change (< {args.tol} px) | DIS, same camera | "
          "SIFT matches / step | right (< 2 px) | affine per object, same camera |")  # fmt: skip
    print("|---|---|--:|--:|--:|--:|--:|--:|")
    for name in names:
        for label, s in summary(measure(name, (W, H), args.steps, args.tol)).items():
            print(f"| {name} {W}x{H} | {label} | {s['speed_px']:.1f} | {s['dis_change']:.2f} | "
                  f"{s['dis_same_camera']:.2f} | {s['sift_matches']:.1f} | {s['sift_right']:.1f} "
                  f"({s['sift_right_frac']:.2f}) | {s['affine_same_camera']:.2f} |")  # fmt: skip


if __name__ == "__main__":
    main()
