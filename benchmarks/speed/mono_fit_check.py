"""How far an imported monocular depth can be trusted next to the moving objects of a finished run.

Issue #28's question on real footage: a relative network depth (MiDaS disparity) is the only measurement of a
moving object's depth, but it comes with unknown units, so it must be fitted to the static scene, whose depth
the run knows (stereo, bundle adjustment, the fitted background). The fit is then *used* on the moving object:
an extrapolation, which nothing in the training video can check directly. What can be checked is the fit on
static pixels it did not see. Per training frame ``t`` of the run:

- reference: the run's rendered inverse depth ``y = 1 / d`` from its own camera ``t``, on static pixels (the
  dynamic Gaussians' own opacity there at most ``--dyn-alpha``; the moving region dilated by ``--dilate`` px left
  out, and ``--margin`` px at the image's left and right sides, which few training cameras see);
- imported: ``x``, the imported map at ``t`` resized to the run's size (disparity, or ``1 / depth``);
- held out: the static pixels within ``--holdout`` px of the moving region (where a fit is used), fitted on
  the rest;
- models of ``y`` from ``x`` (:func:`fit_models`): ``affine`` ``a x + b`` (what ``priors.depth_import``
  fits), ``scale`` ``s x`` (no shift), ``field1`` / ``field2`` ``exp(P(u, v)) x`` with ``P`` a polynomial of
  degree 1 / 2 in the image coordinates (a smooth multiplicative distortion, no shift); all robust (three
  refits without residuals over 2.5 robust standard deviations);
- reported: each model's median ``|log(pred / y)|`` on the held-out pixels (``err_*``), and the median depth
  it gives the moving region (``z_*``, scene units) beside the run's own (``z_run``) and the static median
  (``z_static``); and how far the run's Gaussians spread along the rays (``spread_moving`` /
  ``spread_static``: the median over those pixels with alpha > 0.5 of the blending-weighted standard deviation
  of the Gaussians' camera depths over their mean, :func:`depth_spread_map`): from another camera a spread is
  a smear.

A model that predicts the held-out static pixels well is not thereby right on the moving object: the object is
nearer than any static surface, so its depth is an extrapolation in ``x`` that only a scene with near static
surfaces (or the test views) can check. The figures say how large the network's distortion is on what can be
checked, and how far apart the models put the object (docs/base_method.md).

Usage::

    python -m benchmarks.speed.mono_fit_check RUN_DIR --maps DIR [--kind disparity|depth] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage

MODELS = ("affine", "scale", "field1", "field2")


def _poly(u: np.ndarray, v: np.ndarray, degree: int) -> np.ndarray:
    """``[N, K]`` monomials ``u^i v^j`` with ``i + j <= degree`` (the constant first)."""
    cols = [np.ones_like(u)]
    for n in range(1, degree + 1):
        cols += [u ** (n - j) * v**j for j in range(n + 1)]
    return np.stack(cols, 1)


def _robust_lstsq(
    A: np.ndarray, y: np.ndarray, start: np.ndarray, trim: float = 2.5, rounds: int = 5
) -> np.ndarray:
    """Least squares ``A c = y`` over the pixels whose residual from the current fit is within ``trim`` x
    1.4826 MAD, ``rounds`` times, starting from the robust ``start`` (a plain first fit would be tilted by
    the very outliers the trim is for)."""
    c = np.asarray(start, np.float64)
    keep = np.ones(len(y), bool)
    for _ in range(rounds):
        r = np.abs(A @ c - y)
        # Floor: exact data has rounding-level residuals; never trim those.
        limit = trim * max(1.4826 * float(np.median(r[keep])), 1e-9 * float(np.abs(y).max() + 1e-12))
        new = r <= limit
        if new.sum() < A.shape[1] + 1:
            break
        keep = new
        c = np.linalg.lstsq(A[keep], y[keep], rcond=None)[0]
    return c


def fit_models(x: np.ndarray, y: np.ndarray, fit: np.ndarray) -> dict[str, np.ndarray]:
    """Predictions of the reference inverse depth from the imported one, each model fitted on ``fit``.

    Args:
        x: ``[H, W]`` imported inverse depth (any units; > 0 where used).
        y: ``[H, W]`` reference inverse depth (scene units^-1; finite > 0 where ``fit``).
        fit: ``[H, W]`` bool, the pixels the models are fitted on (needs > 10 with ``x > 0``).

    Returns:
        ``{model: [H, W] predicted inverse depth}`` for the models of :data:`MODELS` (module docstring).
    """
    H, W = x.shape
    use = fit & (x > 0) & np.isfinite(x) & np.isfinite(y) & (y > 0)
    if use.sum() <= 10:
        raise ValueError(f"mono_fit_check: {int(use.sum())} usable fit pixels; need more than 10")
    xs, ys = x[use].astype(np.float64), y[use].astype(np.float64)
    out: dict[str, np.ndarray] = {}
    log_ratio = np.log(ys / xs)
    scale = float(np.exp(np.median(log_ratio)))
    out["scale"] = scale * x
    a, b = _robust_lstsq(np.stack([xs, np.ones_like(xs)], 1), ys, np.array([scale, 0.0]))
    out["affine"] = a * x + b
    vv, uu = np.mgrid[0:H, 0:W]
    u, v = (uu - W / 2) / W, (vv - H / 2) / H  # unit-free coordinates keep the polynomial well conditioned
    for degree in (1, 2):
        A = _poly(u[use], v[use], degree)
        c = _robust_lstsq(A, log_ratio, np.r_[np.log(scale), np.zeros(A.shape[1] - 1)])
        field = np.exp(_poly(u.ravel(), v.ravel(), degree) @ c).reshape(H, W)
        out[f"field{degree}"] = field * x
    return out


def log_error(pred: np.ndarray, y: np.ndarray, mask: np.ndarray) -> float:
    """Median ``|log(pred / y)|`` over ``mask`` where both are positive (NaN when none is)."""
    ok = mask & (pred > 0) & (y > 0) & np.isfinite(pred) & np.isfinite(y)
    return float(np.median(np.abs(np.log(pred[ok] / y[ok])))) if ok.any() else float("nan")


def split_static(dynamic: np.ndarray, valid: np.ndarray, dilate: int, holdout: int, margin: int):
    """``(fit, held)`` [H, W] bool: static valid pixels farther than / within ``holdout`` px of the moving
    region (itself dilated by ``dilate`` px and left out), without ``margin`` px at the left and right sides."""
    moving = ndimage.binary_dilation(dynamic, iterations=dilate) if dilate > 0 and dynamic.any() else dynamic
    static = valid & ~moving
    if margin > 0:
        static[:, :margin] = False
        static[:, -margin:] = False
    dist = ndimage.distance_transform_edt(~dynamic) if dynamic.any() else np.full(dynamic.shape, np.inf)
    return static & (dist > holdout), static & (dist <= holdout)


def depth_spread_map(frame, K, w2c, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """``(relative std [H, W], alpha [H, W])`` of the camera depths of ``frame``'s Gaussians along each ray
    (blending weights; float64, so no centring is needed)."""
    from worldtree.render import rasterize

    m, q, ls, o, _ = (x.detach().double() for x in frame.render_list())
    w2c = torch.as_tensor(w2c, dtype=torch.float64)
    z = m @ w2c[2, :3] + w2c[2, 3]
    cols = torch.stack([z, z * z, torch.zeros_like(z)], 1)
    out = rasterize(m, q, ls, o, cols, torch.as_tensor(K, dtype=torch.float64), w2c, width, height)
    a = out.alpha.clamp_min(1e-12)
    mean, second = out.rgb[..., 0] / a, out.rgb[..., 1] / a
    rel = (second - mean * mean).clamp_min(0.0).sqrt() / mean.clamp_min(1e-12)
    return rel.numpy(), out.alpha.numpy()


def _read_map(folder: Path, t: int, kind: str, size: tuple[int, int]) -> np.ndarray:
    files = sorted(p for p in folder.iterdir() if p.suffix == ".npy")
    if t >= len(files):
        raise SystemExit(f"error: {folder}: {len(files)} .npy maps, frame {t} has none; one map per frame")
    m = torch.from_numpy(np.load(files[t]).astype(np.float32))[None, None]
    m = torch.nn.functional.interpolate(m, size=size, mode="area")[0, 0].numpy().astype(np.float64)
    return m if kind == "disparity" else np.where(m > 0, 1.0 / np.maximum(m, 1e-12), 0.0)


def check_run(run_dir: Path, maps: Path, kind: str, dyn_alpha: float, dilate: int, holdout: int, margin: int):
    """One row per training frame (module docstring); needs a finished run with dynamic Gaussians."""
    from benchmarks.api import load_run
    from worldtree.gaussian_frame import render_frame

    run = load_run(run_dir, device="cpu")
    rows = []
    for t in run.times:
        cam = run.cameras[f"train_{t:03d}"]
        d = run.render(cam, t, mode="depth").numpy().astype(np.float64)
        frame = run.gaussians_at(t)
        spread, alpha = depth_spread_map(frame, cam.K, run.model_w2c(cam, t), cam.width, cam.height)
        moving = render_frame(
            frame.select(frame.dynamic), cam.K, run.model_w2c(cam, t), cam.width, cam.height, "alpha"
        )
        dynamic = moving.numpy() > dyn_alpha
        valid = np.isfinite(d) & (d > 0)
        y = np.where(valid, 1.0 / np.where(valid, d, 1.0), np.nan)
        x = _read_map(maps, t, kind, d.shape)
        fit, held = split_static(dynamic, valid, dilate, holdout, margin)
        row: dict[str, float | int] = {"frame": t, "moving_frac": float(dynamic.mean())}
        for name, where in (("spread_moving", dynamic), ("spread_static", ~dynamic)):
            sel = where & (alpha > 0.5)
            row[name] = float(np.median(spread[sel])) if sel.any() else float("nan")
        if (fit & (x > 0)).sum() <= 10 or not dynamic.any():
            rows.append(row)
            continue
        preds = fit_models(x, y, fit)
        obj = dynamic & valid & (x > 0)
        row["z_run"] = float(np.median(d[obj])) if obj.any() else float("nan")
        row["z_static"] = float(np.median(d[fit]))
        for name, p in preds.items():
            row[f"err_{name}"] = log_error(p, y, held)
            z = 1.0 / p[obj][p[obj] > 0]
            row[f"z_{name}"] = float(np.median(z)) if z.size else float("nan")
        rows.append(row)
    return rows


def format_table(rows: list[dict]) -> str:
    cols = (
        ["frame", "moving_frac", "spread_moving", "spread_static", "z_run", "z_static"]
        + [f"err_{m}" for m in MODELS]
        + [f"z_{m}" for m in MODELS]
    )
    lines = [" ".join(f"{c:>12}" for c in cols)]
    for r in rows:
        lines.append(
            " ".join(f"{r.get(c, float('nan')):>12.3f}" if c != "frame" else f"{r[c]:>12d}" for c in cols)
        )
    med = {c: float(np.nanmedian([r.get(c, np.nan) for r in rows])) for c in cols[1:]}
    lines.append(" ".join([f"{'median':>12}"] + [f"{med[c]:>12.3f}" for c in cols[1:]]))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="finished run folder of a dynamic method (base or worldtree)")
    ap.add_argument("--maps", type=Path, required=True, help="folder of one .npy map per training frame")
    ap.add_argument("--kind", choices=("disparity", "depth"), default="disparity")
    ap.add_argument(
        "--dyn-alpha",
        type=float,
        default=0.3,
        help="opacity of the dynamic Gaussians alone that marks a moving pixel",
    )
    ap.add_argument("--dilate", type=int, default=6, help="px the moving region is dilated by and left out")
    ap.add_argument(
        "--holdout", type=int, default=60, help="static pixels this near the moving region are held out"
    )
    ap.add_argument("--margin", type=int, default=40, help="px at the left and right sides left out")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    if not a.maps.is_dir():
        raise SystemExit(
            f"error: --maps {a.maps}: not a folder; give the folder of .npy maps (e.g. imported/disp)"
        )
    rows = check_run(a.run, a.maps, a.kind, a.dyn_alpha, a.dilate, a.holdout, a.margin)
    print(format_table(rows))
    if a.json is not None:
        a.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
