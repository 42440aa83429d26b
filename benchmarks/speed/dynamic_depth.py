"""Where a finished run puts its moving objects in depth, against the exact depth of a generated scene.

Issues #27 and #28 ask whether the moving objects stand at the right depth: a child of the tree and the test
camera both depend on it. A generated scene written by ``nvls gt-priors`` holds, per training frame ``k``, the
exact z-depth ``SCENE/gt_priors/depth/%05d.npy`` (scene units) and the exact mask of the moving objects
``SCENE/gt_priors/masks/%05d.png``. For each training frame of the run:

- every Gaussian the run draws as moving at that frame (``GaussianFrame.dynamic``) with opacity above
  ``--opacity`` is projected into the frame's camera as the run renders it (``LoadedRun.model_w2c``, model
  units); its camera depth divided by the scene->model scale is in scene units;
- those landing on a pixel of the exact mask (nearest pixel, in front of the camera) are compared with the
  exact depth there: ``log(z / z_true)`` (0 right, > 0 too far, log 1.5 = 0.41);
- reported per frame: the median of that log ratio (``bias``), the median of its absolute value (``error``),
  the Gaussians compared, and the share of the projected moving Gaussians that land inside the mask.

The run-level figures are the medians of the per-frame ones over frames with at least one Gaussian compared.

    python -m benchmarks.speed.dynamic_depth RUN --scene SCENE [--opacity 0.3] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch

from worldtree.motion.lift import project_points

__all__ = ["frame_depth_errors", "measure_run", "summarise"]


def frame_depth_errors(
    means: torch.Tensor, w2c: torch.Tensor, K: torch.Tensor, scale: float, depth: np.ndarray, mask: np.ndarray
) -> dict[str, float]:
    """Depth of Gaussians ``means`` ``[N, 3]`` (model units) seen by camera ``w2c`` ``[4, 4]`` / ``K`` ``[3, 3]``
    (pixels, at the size of ``depth``) against the exact ``depth`` ``[H, W]`` (scene units, 0 = none) inside
    ``mask`` ``[H, W]`` bool; ``scale`` is the scene->model scale. Returns ``bias`` and ``error`` (medians of
    ``log(z / z_true)`` and of its absolute value; NaN when nothing lands inside), ``n`` and ``inside`` (the
    share of the Gaussians in front of the camera and on the image that land inside the mask)."""
    H, W = depth.shape
    uv, z = project_points(means.double(), K.double(), w2c.double())
    u, v = uv[:, 0].round().long(), uv[:, 1].round().long()
    on = (z > 1e-6) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
    u, v, zs = u[on].numpy(), v[on].numpy(), z[on].numpy() / max(float(scale), 1e-12)
    inside = mask[v, u] & (depth[v, u] > 0)
    nan = float("nan")
    if not inside.any():
        return {"bias": nan, "error": nan, "n": 0, "inside": float(inside.mean()) if len(inside) else nan}
    lr = np.log(zs[inside] / depth[v[inside], u[inside]])
    return {"bias": float(np.median(lr)), "error": float(np.median(np.abs(lr))), "n": int(inside.sum()),
            "inside": float(inside.mean())}  # fmt: skip


def summarise(frames: list[dict[str, float]]) -> dict[str, float]:
    """Medians over the frames with at least one Gaussian compared (NaN when none)."""
    used = [f for f in frames if f["n"] > 0]
    if not used:
        return {"bias": float("nan"), "error": float("nan"), "frames_used": 0}
    return {"bias": float(np.median([f["bias"] for f in used])), "error": float(np.median([f["error"] for f in used])),
            "frames_used": len(used)}  # fmt: skip


def measure_run(run_dir: Path, scene_dir: Path, opacity: float = 0.3) -> dict:
    """Per-frame and run-level figures of the run folder ``run_dir`` against ``scene_dir/gt_priors``."""
    from benchmarks.api import load_run
    from worldtree.imageio import read_mask

    gt = scene_dir / "gt_priors"
    if not (gt / "depth").is_dir() or not (gt / "masks").is_dir():
        raise SystemExit(f"error: {gt}: no exact depth and masks; write them with `nvls gt-priors RAW {scene_dir}`")
    run = load_run(run_dir, device="cpu")
    frames = []
    for cam in run.cameras.values():
        if cam.kind != "train":
            continue
        f = run.gaussians_at(cam.time)
        keep = f.dynamic & (f.opacities > opacity)
        depth = np.load(gt / "depth" / f"{cam.frame:05d}.npy")
        mask = read_mask(gt / "masks" / f"{cam.frame:05d}.png")
        if depth.shape != (cam.height, cam.width) or mask.shape != depth.shape:
            raise SystemExit(f"error: {gt}: frame {cam.frame} is {depth.shape}, the run's camera {cam.height}x"
                             f"{cam.width}; give the scene the run was trained on")  # fmt: skip
        row = frame_depth_errors(f.means[keep], run.model_w2c(cam), cam.K, f.scene_to_model.scale, depth, mask)
        frames.append({"frame": int(cam.frame), **row})
    return {"run": str(run_dir), "scene": str(scene_dir), "opacity": opacity, "frames": frames, **summarise(frames)}


def _fmt(x: float) -> str:
    return "-" if math.isnan(x) else f"{x:+.3f}"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="finished run folder of a dynamic method (base or worldtree)")
    ap.add_argument("--scene", type=Path, required=True, help="the generated scene, with gt_priors/")
    ap.add_argument("--opacity", type=float, default=0.3, help="moving Gaussians above this opacity count")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    a = ap.parse_args(argv)
    if not (a.run / "config.json").is_file():
        raise SystemExit(f"error: {a.run}: not a run folder (no config.json); give RUNS/SCENE/METHOD/TAG")
    out = measure_run(a.run, a.scene, a.opacity)
    for f in out["frames"]:
        print(f"frame {f['frame']:3d}  bias {_fmt(f['bias'])}  error {_fmt(f['error'])}  n {f['n']:6d}  "
              f"inside {f['inside']:.2f}")  # fmt: skip
    print(f"median over {out['frames_used']} frames: "
          f"bias {_fmt(out['bias'])} (log z / z_true), error {_fmt(out['error'])}")  # fmt: skip
    if a.json is not None:
        a.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
