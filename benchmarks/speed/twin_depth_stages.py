"""Where the moving object's depth goes wrong in a Base run on a generated capture: its depth at every stage.

Re-runs the Base stages of a finished run up to the scaffold from the run's own checkpoints (priors from the
scene's cache, BA and static warm-up resumed, so nothing is retrained; the run folder is not written to),
then per training frame, over the scored object's exact mask (:mod:`benchmarks.speed.twin_score`'s
``Truth``), the median ratio to the true depth of:

- ``prior``: the depth prior after BA's per-frame scale (the classical prior fills dynamic pixels from their
  static surroundings);
- ``scaffold``: the depth the scaffold and the dynamic Gaussians are lifted with (after
  ``scaffold.trajectory_depth`` where it runs);
- ``tracks``: that depth at the dynamic tracks' pixels on the object (what the scaffold's nodes are built
  from), and how many there are;
- ``model``: the fitted model's rendered depth (as ``twin_score``);

and ``smooth``: for the object's exact tracks (``SCENE/gt_priors/tracks.npz``, visible in >= 4 frames) lifted
with ``k`` times their exact depth, the mean squared second difference of their 3D paths against ``k``
(relative to ``k = 1``): what a smooth-trajectory triangulation minimises. A minimum at ``k = 1`` would pin the
object's depth; one at the smallest ``k`` means the object's own acceleration dominates the cameras'.

Writes ``OUT/depth_stages.json`` and ``OUT/depth_stages.png`` (rows: frames; columns: image, true depth,
prior, scaffold depth, model depth; the object's outline in white).

    python -m benchmarks.speed.twin_depth_stages RUN --raw RAW --scene SCENE --out DIR [--frames 0,3,6,9]
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import torch


def _base_state(run: Path, scene_dir: Path):
    """``(scene, state, prior depth [T, H, W])``: the Base state of ``run`` after its scaffold stage, rebuilt
    from a copy of its checkpoints, and the depth prior as it was before the scaffold stage."""
    from methods.base import BaseConfig, BaseMethod
    from worldtree.infra.config_json import from_dict
    from worldtree.scene import load_scene
    from worldtree.trainer import TrainContext

    cfg = from_dict(BaseConfig, json.loads((run / "config.json").read_text())["config"])
    scene = load_scene(scene_dir, cfg.downscale)
    m = BaseMethod(cfg, scene, torch.device("cpu"))
    tmp = Path(tempfile.mkdtemp(prefix="twin_stages_"))
    try:
        shutil.copytree(run / "checkpoints", tmp / "checkpoints")
        m.state.ctx = TrainContext(checkpoint_dir=tmp / "checkpoints", progress=False, resume=True)
        prior = None
        for st in m.stages():
            if st.name == "scaffold":
                prior = m.state.depth.clone()
            if st.name == "photometric":
                break
            st.run(m.state)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return scene, m.state, prior.cpu().numpy()


def smoothness_curve(
    tracks: np.ndarray,
    vis: np.ndarray,
    depth_at: np.ndarray,
    Ks: np.ndarray,
    w2cs: np.ndarray,
    ks: np.ndarray,
) -> np.ndarray:
    """Mean over tracks of the summed squared second differences of their 3D paths when lifted with ``k``
    times ``depth_at`` [T, N] (their depth in each frame), for each ``k`` of ``ks``; only runs of three
    consecutive visible frames count. ``tracks`` [T, N, 2], ``vis`` [T, N], ``Ks`` [T, 3, 3], ``w2cs`` [T, 4, 4]."""
    T, N = vis.shape
    Kinv = np.linalg.inv(Ks)
    h = np.concatenate([tracks, np.ones((T, N, 1))], -1)
    rays = np.einsum("tij,tnj->tni", Kinv, h)  # camera rays with z = 1
    R, tv = w2cs[:, :3, :3], w2cs[:, :3, 3]
    C = -np.einsum("tji,tj->ti", R, tv)  # camera centres
    dirs = np.einsum("tji,tnj->tni", R, rays)  # world directions (z-depth units)
    ok = vis[:-2] & vis[1:-1] & vis[2:]
    out = []
    for k in ks:
        X = C[:, None, :] + k * depth_at[..., None] * dirs
        acc = X[:-2] - 2 * X[1:-1] + X[2:]
        out.append(float(((acc**2).sum(-1) * ok).sum() / max(N, 1)))
    return np.asarray(out)


def main(argv: list[str] | None = None) -> None:
    import cv2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from benchmarks.api import load_run
    from benchmarks.speed.twin_score import Truth, erode, render_depth
    from worldtree.pixels import unit_float

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--raw", type=Path, required=True)
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--object", type=int, default=1)
    ap.add_argument("--frames", default="0,3,6,9")
    a = ap.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    scene, st, prior = _base_state(a.run, a.scene)
    T, h, w = prior.shape
    truth = Truth(a.raw, a.scene)
    model = load_run(a.run, device="cpu", scene=a.scene)
    cams = [c for c in model.cameras.values() if c.kind == "train"]  # training frame t -> its camera
    tracks, tvis = st.tracks.numpy(), st.track_vis.numpy()
    rows, pics = [], {}
    for t in range(T):
        d_gt, ids = truth.view(truth.inp.frame_cams[t], truth.inp.frame_times[t], w, h)
        P = erode(ids == a.object, 1)
        frame = model.gaussians_at(t)
        d_m = render_depth(frame, scene.Ks[t], model.model_w2c(cams[t]), w, h)[0] / frame.scene_to_model.scale
        ui = np.clip(np.round(tracks[t, :, 0]).astype(int), 0, w - 1)
        vi = np.clip(np.round(tracks[t, :, 1]).astype(int), 0, h - 1)
        on = tvis[t] & P[vi, ui]
        sd = st.depth[t].cpu().numpy()

        def med(x, m, d_gt=d_gt):
            v = (x[m] / d_gt[m]) if m.any() else np.array([])
            v = v[np.isfinite(v)]
            return float(np.median(v)) if len(v) else float("nan")

        on_px = np.zeros_like(P)
        on_px[vi[on], ui[on]] = True
        rows.append({"frame": t, "prior": med(prior[t], P), "scaffold": med(sd, P), "tracks": med(sd, on_px),
                     "n_tracks": int(on.sum()), "model": med(d_m, P)})  # fmt: skip
        pics[t] = (unit_float(scene.images[t]).numpy(), d_gt, prior[t], sd, d_m, ids == a.object)
    # Smoothness of the object's exact tracks against a global depth scale k.
    z = np.load(a.scene / "gt_priors" / "tracks.npz")
    full_w = int(z["image_size"][0])
    s = w / full_w
    sel = (z["object_id"] == a.object) & (z["visibility"].sum(0) >= 4)
    gtr = (z["tracks"][:, sel] + 0.5) * s - 0.5
    gvis = z["visibility"][:, sel]
    depth_at = np.zeros(gvis.shape)
    for t in range(T):
        d_gt, _ = truth.view(truth.inp.frame_cams[t], truth.inp.frame_times[t], w, h)
        ui = np.clip(np.round(gtr[t, :, 0]).astype(int), 0, w - 1)
        vi = np.clip(np.round(gtr[t, :, 1]).astype(int), 0, h - 1)
        depth_at[t] = np.nan_to_num(d_gt[vi, ui])
    ks = np.round(np.arange(0.3, 3.01, 0.1), 2)
    Kg = scene.Ks.double().numpy()
    Wg = scene.w2cs.double().numpy()
    curve = smoothness_curve(gtr, gvis, depth_at, Kg, Wg, ks)
    curve = curve / curve[np.argmin(np.abs(ks - 1.0))]
    print(
        f"{'frame':>5} {'prior':>6} {'scaff.':>6} {'tracks':>6} {'n':>4} {'model':>6}   (median depth / true)"
    )
    for r in rows:
        print(f"{r['frame']:>5} {r['prior']:>6.2f} {r['scaffold']:>6.2f} {r['tracks']:>6.2f} {r['n_tracks']:>4} "
              f"{r['model']:>6.2f}")  # fmt: skip
    print(f"smoothness of the exact tracks vs depth scale k (1 at k=1): argmin k = {ks[np.argmin(curve)]:.1f}; "
          + ", ".join(f"k={k:.1f}: {c:.2f}" for k, c in zip(ks, curve, strict=True) if k in (0.3, 0.5, 1.0, 2.0, 3.0)))  # fmt: skip
    (a.out / "depth_stages.json").write_text(
        json.dumps(
            {"run": str(a.run), "rows": rows, "smooth_k": ks.tolist(), "smooth": curve.tolist()}, indent=1
        )
    )
    frames = [int(f) for f in a.frames.split(",") if f.strip()]
    titles = [
        "training image",
        "true depth",
        "depth prior (after BA)",
        "scaffold / lift depth",
        "model depth",
    ]
    fig, ax = plt.subplots(len(frames) + 1, 5, figsize=(17, 2.3 * (len(frames) + 1) + 0.5))
    norm = matplotlib.colors.LogNorm(vmin=10, vmax=90)
    for r, t in enumerate(frames):
        img, *deps, m = pics[t]
        cnt, _ = cv2.findContours(m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        for c, im in enumerate([img, *deps]):
            x = ax[r, c]
            if c == 0:
                x.imshow(np.clip(im, 0, 1))
            else:
                x.imshow(np.where(np.isfinite(im) & (im > 0), im, np.nan), cmap="turbo", norm=norm)
            for cc in cnt:
                x.plot(cc[:, 0, 0], cc[:, 0, 1], "w-", lw=0.8)
            x.set_xticks([])
            x.set_yticks([])
            if r == 0:
                x.set_title(titles[c], fontsize=9)
        ax[r, 0].set_ylabel(f"t={t} (cam {truth.inp.frame_cams[t]})", fontsize=9)
    for x in ax[-1]:
        x.axis("off")
    x = fig.add_subplot(len(frames) + 1, 2, 2 * len(frames) + 1)
    tt = [r["frame"] for r in rows]
    for key, style in (("prior", "o-"), ("scaffold", "s-"), ("model", "^-")):
        x.plot(tt, [r[key] for r in rows], style, label=key)
    x.axhline(1.0, color="k", lw=0.8)
    x.set_yscale("log")
    x.set_xlabel("training frame")
    x.set_ylabel("median depth / true (object)")
    x.legend(fontsize=8)
    x = fig.add_subplot(len(frames) + 1, 2, 2 * len(frames) + 2)
    x.plot(ks, curve, "o-")
    x.axvline(1.0, color="k", lw=0.8)
    x.set_xlabel("k: object's exact depth scaled by")
    x.set_ylabel("path acceleration (rel. k=1)")
    fig.colorbar(matplotlib.cm.ScalarMappable(norm=norm, cmap="turbo"), ax=ax[: len(frames)].ravel().tolist(),
                 shrink=0.6, label="depth (scene units)")  # fmt: skip
    fig.savefig(a.out / "depth_stages.png", dpi=80)
    print(f"wrote {a.out / 'depth_stages.png'} and depth_stages.json")


if __name__ == "__main__":
    main()
