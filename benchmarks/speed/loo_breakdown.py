"""Where a leave-one-out frame loses: colour, background or the moving object (issue 28's question on real
footage).

Reads what :mod:`benchmarks.evaluation.leave_one_out` wrote (``loo.json`` and the ``k<k>_<method>.png`` renders
of the held-out frame and its kept neighbours, ``_prev`` / ``_next``) and the scene's own frames, and scores each
render four more ways beside its PSNR (all on the 8-bit images, as the harness scores them):

- ``colour``: after the best per-channel gain and bias from the render to the frame (least squares, an oracle
  that looks at the frame): what the rig's cameras' differences in exposure and white balance can cost at most;
- ``object`` / ``background``: the masked PSNR inside the moving region and outside it. The region is the
  frame's mask (``--masks DIR``, one per frame, as the leave-one-out takes them) or a colour key (``--key-hue
  LO,HI`` in degrees: the largest connected region of pixels with a hue in that range and saturation at least
  ``--key-sat``, opened 2 px, closed 4 px and dilated ``--dilate`` px). With a colour key the region is the
  union of the frame's and the render's (an object drawn in the wrong place is wrong on both), so the
  background is what neither covers;
- ``background_aligned``: the background after the homography from the render to the frame that best aligns
  the background (OpenCV's ECC, an oracle again): what a camera placed a pixel off costs; ``shift_px`` is how
  far that homography moves the image's corners and centre at most.

The kept neighbours were fitted to their frames, so they say how well the method fits; the held-out frame, how
well it generalises to a camera and time it did not see.

Usage::

    python -m benchmarks.speed.loo_breakdown LOO_DIR SCENE [--masks DIR | --key-hue 70,170] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from benchmarks.evaluation.leave_one_out import score
from worldtree.infra.errors import UserError

SIDES = (("held", 0), ("prev", -1), ("next", 1))
"""Render suffix and the frame it shows, relative to the held-out frame k."""


def colour_oracle(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The best per-channel affine colour map from ``pred`` to ``gt`` (uint8 ``[H, W, 3]``), applied.

    Returns ``(uint8 [H, W, 3], [3, 2] gain and bias per channel in [0, 1] units)``. A constant channel gets
    gain 0 and its mean difference as bias (the least-squares minimum-norm answer)."""
    p = pred.reshape(-1, 3).astype(np.float64) / 255.0
    g = gt.reshape(-1, 3).astype(np.float64) / 255.0
    out = np.empty_like(p)
    coef = np.zeros((3, 2))
    for c in range(3):
        A = np.stack([p[:, c], np.ones_like(p[:, c])], 1)
        coef[c] = np.linalg.lstsq(A, g[:, c], rcond=None)[0]
        out[:, c] = A @ coef[c]
    img = np.clip(np.rint(out * 255.0), 0, 255).astype(np.uint8).reshape(pred.shape)
    return img, coef


def colour_key(img: np.ndarray, hue: tuple[float, float], min_sat: float, dilate: int) -> np.ndarray:
    """``[H, W]`` bool: the largest connected region of ``img`` (uint8 RGB) whose hue (degrees) lies in ``hue``
    and saturation (0-1) is at least ``min_sat``, opened 2 px, closed 4 px, dilated ``dilate`` px; all False
    when no pixel matches."""
    import cv2
    from scipy import ndimage

    hsv = cv2.cvtColor(img.astype(np.float32) / 255.0, cv2.COLOR_RGB2HSV)  # H in degrees, S and V in 0-1
    lo, hi = hue
    m = (hsv[..., 0] >= lo) & (hsv[..., 0] <= hi) & (hsv[..., 1] >= min_sat)
    m = ndimage.binary_closing(ndimage.binary_opening(m, iterations=2), iterations=4)
    labels, n = ndimage.label(m)
    if n == 0:
        return m
    sizes = ndimage.sum(m, labels, range(1, n + 1))
    m = labels == (int(np.argmax(sizes)) + 1)
    return ndimage.binary_dilation(m, iterations=dilate) if dilate > 0 else m


def align_background(pred: np.ndarray, gt: np.ndarray, region: np.ndarray) -> tuple[np.ndarray, float]:
    """``pred`` warped by the homography that best aligns it to ``gt`` on ``region`` ``[H, W]`` (ECC on the grey
    images), and the largest displacement (px) of the image's corners and centre; ``(pred, nan)`` when ECC
    does not converge."""
    import cv2

    grey = [cv2.cvtColor(x, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0 for x in (gt, pred)]
    warp = np.eye(3, dtype=np.float32)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 200, 1e-6)
    try:
        _, warp = cv2.findTransformECC(grey[0], grey[1], warp, cv2.MOTION_HOMOGRAPHY, crit,
                                       region.astype(np.uint8) * 255, 5)  # fmt: skip
    except cv2.error:
        return pred, float("nan")
    h, w = pred.shape[:2]
    out = cv2.warpPerspective(pred, warp, (w, h), flags=cv2.INTER_LINEAR + cv2.WARP_INVERSE_MAP)
    pts = np.array([[0, w, 0, w, w / 2], [0, 0, h, h, h / 2], [1, 1, 1, 1, 1]], np.float64)
    moved = warp.astype(np.float64) @ pts
    moved = moved[:2] / np.where(np.abs(moved[2]) > 1e-12, moved[2], 1e-12)
    return out, float(np.abs(moved - pts[:2]).max())


def breakdown(pred: np.ndarray, gt: np.ndarray, region: np.ndarray | None) -> dict:
    """The scores of one render ``pred`` of frame ``gt`` (uint8 ``[H, W, 3]``) with the moving ``region``
    ``[H, W]`` (None: no region scores). PSNR in dB; None for an empty region."""
    row = {"psnr": score(pred, gt), "colour": score(colour_oracle(pred, gt)[0], gt)}
    if region is not None:
        bg = ~region
        inner = bg.copy()  # the warp leaves the border undefined
        inner[:8], inner[-8:], inner[:, :8], inner[:, -8:] = False, False, False, False
        aligned, shift = align_background(pred, gt, inner) if inner.any() else (pred, float("nan"))
        row.update(object=score(pred, gt, region), background=score(pred, gt, inner),
                   background_aligned=score(aligned, gt, inner), shift_px=shift,
                   region_share=float(region.mean()))  # fmt: skip
    return row


def main(argv: list[str] | None = None) -> None:
    from worldtree.imageio import read_image, read_mask
    from worldtree.pixels import as_uint8
    from worldtree.scene import load_scene

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("loo", type=Path, help="a leave-one-out output folder (loo.json and its renders)")
    ap.add_argument("scene", type=Path, help="the scene the leave-one-out ran on")
    ap.add_argument("--masks", type=Path, default=None, help="per-frame moving-region masks")
    ap.add_argument("--key-hue", default=None, metavar="LO,HI", help="colour key: hue range in degrees")
    ap.add_argument("--key-sat", type=float, default=0.25, help="colour key: least saturation (0-1)")
    ap.add_argument("--dilate", type=int, default=6, help="colour key: dilation in pixels")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.masks is not None and args.key_hue is not None:
        raise UserError("--masks and --key-hue: give one of them")
    hue = None
    if args.key_hue is not None:
        try:
            hue = tuple(float(v) for v in args.key_hue.split(","))
            assert len(hue) == 2 and 0 <= hue[0] < hue[1] <= 360
        except (ValueError, AssertionError):
            raise UserError(f"--key-hue {args.key_hue!r}: give LO,HI in degrees, 0 <= LO < HI <= 360") from None
    record = args.loo / "loo.json"
    if not record.is_file():
        raise UserError(f"{record}: no such file; give the -o folder of a leave-one-out run")
    runs = json.loads(record.read_text())["runs"]
    scenes: dict[tuple, object] = {}
    masks = sorted(p for p in args.masks.iterdir() if p.is_file()) if args.masks is not None else None
    rows = []
    for run in runs:
        k, method, label = int(run["k"]), run["method"], run.get("label", "")
        size = tuple(run.get("scored_size") or ())
        if size not in scenes:
            full = load_scene(args.scene, downscale=1, load_masks=False)
            down = max(1, round(full.width / size[0])) if size else 1
            scenes[size] = full if down == 1 else load_scene(args.scene, downscale=down, load_masks=False)
        scene = scenes[size]
        for side, dk in SIDES:
            name = f"k{k:02d}_{method}.png" if side == "held" else f"k{k:02d}_{method}_{side}.png"
            path = args.loo / name
            if not path.is_file():
                continue
            pred = read_image(path)
            gt = as_uint8(scene.images[k + dk]).numpy()
            if pred.shape != gt.shape:
                raise UserError(f"{path}: {pred.shape[1]}x{pred.shape[0]}, the frame is {gt.shape[1]}x{gt.shape[0]}")
            region = None
            if hue is not None:
                region = colour_key(gt, hue, args.key_sat, args.dilate) | colour_key(pred, hue, args.key_sat, args.dilate)
            elif masks is not None:
                region = read_mask(masks[k + dk])
            rows.append({"label": label, "k": k, "method": method, "side": side, **breakdown(pred, gt, region)})
    cols = ["psnr", "colour", "object", "background", "background_aligned", "shift_px"]
    print("label k method side " + " ".join(cols))
    for r in rows:
        vals = " ".join("-" if r.get(c) is None else f"{r[c]:.2f}" for c in cols)
        print(f"{r['label'] or '-'} {r['k']} {r['method']} {r['side']} {vals}")
    if args.json is not None:
        args.json.write_text(json.dumps({"rows": rows}, indent=1))


if __name__ == "__main__":
    import sys

    try:
        main()
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from None
