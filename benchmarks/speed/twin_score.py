"""Where a finished run puts a generated scene's moving object: depth, test-camera position and mPSNR per frame.

Issue #28's measurement on a generated capture (``nvls synth``, e.g. ``--kind twin``) built into a scene and
run by ``wtbench run`` (static, base or worldtree). Ground truth comes from the generator itself (the raw
capture's ``gt/``; :mod:`nvidia_ls.gt_priors` re-casts the exact depth and object ids at any pixel).

Per training frame ``t`` (rig camera ``c_t`` at time ``tau_t``), over the pixels ``P`` of the scored object
(``--object``, default 1: the twin's ball) in training view ``t``, eroded by ``--erode`` px so that
silhouette pixels (half object, half wall) do not dominate, at the run's training size:

- ``depth``: median of ``|d_model - d_gt| / d_gt`` over ``P``, where ``d_model`` is the fitted model's
  rendered depth (``sum w z / alpha``, every Gaussian it draws at ``t``) from its own (optimised) camera ``t``,
  divided by the scale of the run's Sim(3) from the given poses to the optimised ones (so both depths are in
  the scene's units); ``bias``: the signed median of ``d_model / d_gt - 1`` (negative: drawn too near);
- ``screen``: where the test camera sees the surface the model draws at ``P``. Each pixel of ``P`` is lifted
  with the model's depth through the model's camera ``t`` and projected by the run's test camera at ``tau_t``
  (the refined test pose the run rendered with; the given test pose for a static run); the same pixel lifted
  with the true depth through the true camera ``t`` and projected by the true test camera gives its true
  test-view position. ``screen`` is the distance between the two centroids (px at the scene's full size);
  ``screen_med`` the median per-pixel distance; ``shift``: how far the object's centroid moves between the
  training view and the test view in truth (px): what a wrong depth is multiplied by;
- ``mpsnr``: PSNR of the run's test render at ``tau_t`` (``RUN/renders``) inside the object's exact mask in
  the test camera (full size, the worldtree protocol's ``sum(m (a-b)^2) / 3M``); ``psnr``: the whole image;
- ``dyn``: the fraction of the model's opacity over ``P`` drawn by its dynamic Gaussians (static runs: 0).

Usage::

    python -m benchmarks.speed.twin_score RUN_DIR --raw RAW --scene SCENE [--object 1] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from worldtree.gaussian_frame import GaussianFrame
from worldtree.pixels import as_uint8


# ------------------------------------------------------------------------------------------------ geometry
def backproject(px: np.ndarray, depth: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> np.ndarray:
    """``[N, 3]`` world points of pixels ``px`` [N, 2] (x, y; pixel centres at integers) at z-depths ``depth``
    [N] seen by camera ``K`` [3, 3] / ``w2c`` [4, 4]."""
    px, depth = np.asarray(px, np.float64), np.asarray(depth, np.float64)
    K, w2c = np.asarray(K, np.float64), np.asarray(w2c, np.float64)
    h = np.concatenate([px, np.ones((len(px), 1))], 1)
    cam = h @ np.linalg.inv(K).T * depth[:, None]
    return (cam - w2c[:3, 3]) @ w2c[:3, :3]


def project(X: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(px [N, 2], z [N])``: pixels and z-depths of world points ``X`` [N, 3] in camera ``K`` / ``w2c``."""
    X, K, w2c = (np.asarray(a, np.float64) for a in (X, K, w2c))
    cam = X @ w2c[:3, :3].T + w2c[:3, 3]
    z = cam[:, 2]
    uv = cam @ K.T
    return uv[:, :2] / np.where(np.abs(z) > 1e-12, z, 1e-12)[:, None], z


def depth_errors(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """``(median |pred - gt| / gt, median (pred / gt - 1))`` over ``mask`` where both depths are finite and
    positive; ``(nan, nan)`` where no pixel qualifies."""
    ok = np.asarray(mask, bool) & np.isfinite(pred) & np.isfinite(gt) & (gt > 0) & (pred > 0)
    if not ok.any():
        return float("nan"), float("nan")
    r = pred[ok] / gt[ok] - 1.0
    return float(np.median(np.abs(r))), float(np.median(r))


def screen_errors(
    px: np.ndarray,
    depth_model: np.ndarray,
    cam_model: tuple[np.ndarray, np.ndarray],
    test_model: tuple[np.ndarray, np.ndarray],
    depth_gt: np.ndarray,
    cam_gt: tuple[np.ndarray, np.ndarray],
    test_gt: tuple[np.ndarray, np.ndarray],
) -> tuple[float, float, np.ndarray, np.ndarray]:
    """Where the test camera sees the surface drawn at pixels ``px`` [N, 2] of a training view, by the model
    and in truth (see the module docstring): each pixel lifted with ``depth_model`` [N] through the model's
    camera ``cam_model = (K, w2c)`` and projected by ``test_model``; and lifted with ``depth_gt`` through
    ``cam_gt``, projected by ``test_gt``.

    Returns ``(centroid distance px, median per-pixel distance px, model px [N, 2], true px [N, 2])``."""
    um, _ = project(backproject(px, depth_model, *cam_model), *test_model)
    ug, _ = project(backproject(px, depth_gt, *cam_gt), *test_gt)
    if not len(px):
        return float("nan"), float("nan"), um, ug
    return (
        float(np.linalg.norm(um.mean(0) - ug.mean(0))),
        float(np.median(np.linalg.norm(um - ug, axis=1))),
        um,
        ug,
    )


def masked_psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR (dB, uint8 scale) of ``a`` against ``b`` [H, W, 3] over ``mask`` [H, W] (all pixels if None):
    ``MSE = sum(m (a - b)^2) / (3 M)`` as the worldtree protocol's mPSNR; nan for an empty mask, inf for equal
    images."""
    d = (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2
    if mask is not None:
        mask = np.asarray(mask, bool)
        if not mask.any():
            return float("nan")
        d = d[mask]
    mse = float(d.mean())
    return float("inf") if mse == 0 else 10.0 * np.log10(255.0**2 / mse)


def erode(mask: np.ndarray, px: int) -> np.ndarray:
    """``mask`` eroded by a ``(2 px + 1)`` square (``px = 0``: unchanged)."""
    if px <= 0:
        return np.asarray(mask, bool)
    import cv2

    k = np.ones((2 * px + 1, 2 * px + 1), np.uint8)
    return cv2.erode(np.asarray(mask, np.uint8), k, borderValue=0) > 0


# ------------------------------------------------------------------------------------------------ the model
# The finished run is read through the Python API (benchmarks.api.load_run): its Gaussians at a frame
# (LoadedRun.gaussians_at), the pose the model draws a training or test camera from (LoadedRun.model_w2c) and
# the scene->model Sim(3) scale (GaussianFrame.scene_to_model).


@torch.no_grad()
def render_depth(frame: GaussianFrame, K, w2c, width: int, height: int):
    """``(depth [H, W], alpha [H, W], dynamic alpha [H, W])`` of a frame (model units; depth = ``sum w z /
    alpha``, nan where alpha < 0.5; dynamic alpha: the frame's dynamic Gaussians alone)."""
    from worldtree.render import rasterize

    K = torch.as_tensor(K, dtype=torch.float32)
    w2c = torch.as_tensor(w2c, dtype=torch.float32)
    black = torch.zeros(len(frame), 3)  # colour plays no part in depth or alpha
    out = rasterize(frame.means, frame.quats, frame.log_scales, frame.opacities, black, K, w2c, width, height)
    alpha = out.alpha.cpu().numpy()
    depth = np.where(alpha >= 0.5, out.depth.cpu().numpy() / np.maximum(alpha, 1e-6), np.nan)
    dyn = np.zeros_like(alpha)
    if bool(frame.dynamic.any()):
        d = frame.select(frame.dynamic)
        dyn = rasterize(d.means, d.quats, d.log_scales, d.opacities, black[: len(d)], K, w2c, width,
                        height).alpha.cpu().numpy()  # fmt: skip
    return depth, alpha, dyn


# ------------------------------------------------------------------------------------------------ truth
class Truth:
    """Exact depth (scene units) and object ids of a generated capture's training frames and test camera,
    re-cast by the generator (:mod:`nvidia_ls.gt_priors`) at the pixel centres of a grid of any size."""

    def __init__(self, raw: Path, scene_dir: Path):
        from nvidia_ls.gt_priors import GtPriorsConfig, _Renderer, load_inputs

        self.inp = load_inputs(raw, scene_dir, GtPriorsConfig())
        self._renderers: dict[tuple[int, int], _Renderer] = {}
        self._make = _Renderer
        man = json.loads((Path(scene_dir) / "manifest.json").read_text())
        self.test_camera = int(man.get("test_camera", 1))

    def view(self, cam: int, time: float, width: int, height: int):
        """``(depth [H, W] scene units, nan = no hit; object_id [H, W])`` of rig camera ``cam`` at ``time`` at
        the pixel centres of a ``width`` x ``height`` grid over the scene's image."""
        W, H = self.inp.size
        key = (width, height)
        if key not in self._renderers:
            self._renderers[key] = self._make(self.inp.scene)
        u, v = np.meshgrid(
            (np.arange(width) + 0.5) * W / width - 0.5, (np.arange(height) + 0.5) * H / height - 0.5
        )
        q = self.inp.maps[cam].to_raw(np.stack([u, v], -1))
        fv = self._renderers[key].render(cam, self.inp.Ks[cam - 1], self.inp.w2cs[cam - 1], q, float(time))
        depth = np.where(np.isfinite(fv.depth), fv.depth * self.inp.align.scale, np.nan)
        return depth, fv.object_id


# ------------------------------------------------------------------------------------------------ scoring
def score_run(run: Path, raw: Path, scene_dir: Path, object_id: int = 1, erode_px: int = 2) -> list[dict]:
    """One dict per training frame of ``run`` (see the module docstring)."""
    from benchmarks.api import load_run
    from worldtree.imageio import read_image
    from worldtree.scene import load_scene

    cfg = json.loads((Path(run) / "config.json").read_text())
    ds = int(cfg["config"].get("downscale", 1))
    scene = load_scene(scene_dir, ds, load_masks=False)
    full = load_scene(scene_dir, 1, load_masks=False)
    T, h, w = scene.images.shape[:3]
    Hf, Wf = full.test_images.shape[1:3]
    model = load_run(run, device="cpu", scene=scene_dir)
    truth = Truth(raw, scene_dir)
    tc = truth.test_camera
    test_index = {int(t): k for k, t in enumerate(full.test_times.tolist())}
    model_camera = [c for c in model.cameras.values() if c.kind == "train"]  # training frame t -> its camera
    rows = []
    yy, xx = np.mgrid[0:h, 0:w]
    for t in range(T):
        cam, tau = truth.inp.frame_cams[t], truth.inp.frame_times[t]
        d_gt, ids = truth.view(cam, tau, w, h)
        P = erode(ids == object_id, erode_px)
        frame = model.gaussians_at(t)
        w2c_t = model.model_w2c(model_camera[t])  # the model's own (fitted) camera t
        d_m, alpha, dyn = render_depth(frame, scene.Ks[t], w2c_t, w, h)
        d_m_scene = d_m / frame.scene_to_model.scale
        err, bias = depth_errors(d_m_scene, d_gt, P)
        row = {"frame": t, "camera": cam, "time": tau, "pixels": int(P.sum()), "depth": err, "bias": bias,
               "dyn": float(dyn[P].sum() / max(alpha[P].sum(), 1e-9)) if P.any() else float("nan")}  # fmt: skip
        ok = P & np.isfinite(d_m) & np.isfinite(d_gt)
        k = test_index.get(int(tau))
        if ok.any() and "test" in model.cameras and int(tau) in model.times:
            px = np.stack([xx[ok], yy[ok]], 1).astype(np.float64)
            # Pixels of the working grid, scored in the test camera at the scene's full size.
            Ktr = scene.Ks[t].double().numpy()
            Kte = full.test_K.double().numpy()
            c, cm, um, ug = screen_errors(
                px, d_m[ok], (Ktr, w2c_t.double().numpy()),
                (Kte, model.model_w2c("test", int(tau)).double().numpy()),
                d_gt[ok], (Ktr, scene.w2cs[t].double().numpy()), (Kte, full.test_w2c.double().numpy()),
            )  # fmt: skip
            src = (px + 0.5) * np.array([Wf / w, Hf / h]) - 0.5
            row.update(screen=c, screen_med=cm, shift=float(np.linalg.norm(ug.mean(0) - src.mean(0))))
        if k is not None:
            name = full.test_files[k]
            pred_path = Path(run) / "renders" / name
            if pred_path.is_file():
                _, ids_test = truth.view(tc, tau, Wf, Hf)
                pred = read_image(pred_path)
                gt = as_uint8(full.test_images[k]).numpy()
                row["mpsnr"] = masked_psnr(pred, gt, ids_test == object_id)
                row["psnr"] = masked_psnr(pred, gt)
        rows.append(row)
    return rows


COLUMNS = [("frame", "d"), ("camera", "d"), ("time", "d"), ("pixels", "d"), ("depth", ".1%"),
           ("bias", "+.1%"), ("screen", ".1f"), ("screen_med", ".1f"), ("shift", ".1f"), ("mpsnr", ".2f"),
           ("psnr", ".2f"), ("dyn", ".2f")]  # fmt: skip
"""Table columns and their formats (``screen_med`` is printed as ``scr_med``)."""
MEDIAN_KEYS = ["depth", "bias", "screen", "screen_med", "shift", "mpsnr", "psnr", "dyn"]


def medians(rows: list[dict]) -> dict[str, float]:
    """Median over the frames of each scored column (frames without a finite value left out)."""
    out = {}
    for k in MEDIAN_KEYS:
        v = np.array([r[k] for r in rows if r.get(k) is not None], float)
        v = v[np.isfinite(v)]
        out[k] = float(np.median(v)) if len(v) else float("nan")
    return out


def format_table(rows: list[dict]) -> str:
    """The per-frame table and a last row of medians."""

    def cell(v, f: str) -> str:
        if v is None or (isinstance(v, float) and not np.isfinite(v)):
            return f"{'-':>8}"
        return f"{format(v, f):>8}"

    lines = [" ".join(f"{k.replace('screen_med', 'scr_med'):>8}" for k, _ in COLUMNS)]
    lines += [" ".join(cell(r.get(k), f) for k, f in COLUMNS) for r in rows]
    med = medians(rows)
    lines.append(" ".join(cell(med[k], f) if k in med else f"{'median' if k == 'frame' else '':>8}"
                          for k, f in COLUMNS))  # fmt: skip
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="finished run folder (holding model/, renders/, config.json)")
    ap.add_argument("--raw", type=Path, required=True, help="the generated raw capture (with gt/)")
    ap.add_argument("--scene", type=Path, required=True, help="the scene built from it")
    ap.add_argument("--object", type=int, default=1, help="moving object id scored (twin: 1 ball, 2 person)")
    ap.add_argument("--erode", type=int, default=2, help="px the object's training-view mask is eroded by")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    rows = score_run(a.run, a.raw, a.scene, a.object, a.erode)
    print(format_table(rows))
    if a.json is not None:
        a.json.write_text(json.dumps({"run": str(a.run), "object": a.object, "rows": rows,
                                      "median": medians(rows)}, indent=1))  # fmt: skip


if __name__ == "__main__":
    main()
