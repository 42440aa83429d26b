"""Where a tree node gains or loses against its root: per node, its fit on its own training frames and the
test views it renders, split into the static background and the moving region.

Prints one row per tree node of a finished WorldTree run (``TREE_RUN``), beside the same frames of a
root-only run (``ROOT_RUN``: ``--ablate tpt`` with the same seed and preset):

- ``train``: PSNR of the node's render (with its chain) on its own training frames at the training size,
  against the root's render of the same frames;
- ``test bg`` / ``test dyn``: PSNR of the test-view renders over the frames the node renders, outside and
  inside the test masks (the moving objects), against the root run's renders of those frames.

Usage::

    python -m benchmarks.speed.tree_diagnosis TREE_RUN ROOT_RUN --scene SCENE [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from worldtree.imageio import read_image, read_mask
from worldtree.infra.errors import UserError
from worldtree.pixels import as_uint8
from worldtree.render import rasterize
from worldtree.scene import load_scene
from worldtree.tree.node import NodeState


def _psnr(a: np.ndarray, b: np.ndarray, m: np.ndarray | None = None) -> float:
    """PSNR (dB, uint8 scale) of ``a`` against ``b`` ``[H, W, 3]`` over the pixels of ``m`` (all if None)."""
    d = (a.astype(np.float64) - b.astype(np.float64)) ** 2
    if m is not None:
        if not m.any():
            return float("nan")
        d = d[m]
    mse = max(float(d.mean()), 1e-10)
    return 10.0 * np.log10(255.0**2 / mse)


def _node_train_psnr(st: NodeState, scene, backend: str) -> list[float]:
    """PSNR of node ``st`` on each of its own training frames (its own, optimised cameras)."""
    out = []
    H, W = scene.images.shape[1:3]
    cache = st.dynamic.attach(st.scaffold)
    with torch.no_grad():
        for g in range(st.interval.start, st.interval.end + 1):
            m, q, ls, o, c = st.gaussians_at(g, None, cache)
            img = rasterize(m, q, ls, o, c, scene.Ks[g].float(), st.w2cs[g - st.interval.start].float(), W, H,
                            backend=backend).rgb  # fmt: skip
            pred = as_uint8(img).numpy()
            gt = as_uint8(scene.images[g]).numpy()
            out.append(_psnr(pred, gt))
    return out


def _test_psnr(run: Path, scene_dir: Path, frames: list[str]) -> tuple[list[float], list[float]]:
    """Background and moving-region PSNR of ``run``'s test renders named ``frames`` (stems)."""
    bg, dyn = [], []
    for f in frames:
        pred = read_image(run / "renders" / f"{f}.png")
        gt = read_image(scene_dir / "gt_images" / f"{f}.png")
        mp = scene_dir / "masks" / f"{f}.png"
        m = read_mask(mp) if mp.exists() else np.zeros(gt.shape[:2], bool)
        bg.append(_psnr(pred, gt, ~m))
        dyn.append(_psnr(pred, gt, m))
    return bg, dyn


def diagnose(tree_run: Path, root_run: Path, scene_dir: Path) -> list[dict]:
    """One dict per node of ``tree_run`` (see the module docstring)."""
    runs = ((tree_run, "TREE_RUN: a WorldTree run"), (root_run, "ROOT_RUN: a WorldTree run with --ablate tpt"))
    for run, what in runs:
        for need in ("config.json", "timing.json", "model/tree/node1.pt"):
            if not (run / need).is_file():
                raise UserError(f"{run / need}: missing; give {what} folder written by `wtbench run`")
    cfg = json.loads((tree_run / "config.json").read_text())
    downscale = int(cfg["config"].get("downscale", 1))
    backend = cfg["config"]["photometric"].get("backend", "auto")
    scene = load_scene(scene_dir, downscale)
    timing = json.loads((tree_run / "timing.json").read_text())
    tree = timing["method_stats"].get("tree", {})
    renders = {int(j): v for j, v in tree.get("renders", {"1": [[0, scene.num_frames - 1]]}).items()}
    root = NodeState.load(root_run / "model" / "tree" / "node1.pt")
    test_files = sorted(p.stem for p in (tree_run / "renders").glob("*.png"))
    test_times = dict(zip(test_files, [int(t) for t in scene.test_times.tolist()], strict=False))
    root_train = _node_train_psnr(root, scene, backend)  # every frame once, sliced per node below
    rows = []
    for path in sorted((tree_run / "model" / "tree").glob("node*.pt"), key=lambda p: int(p.stem[4:])):
        st = NodeState.load(path)
        j = st.index
        own = _node_train_psnr(st, scene, backend)
        sl = slice(st.interval.start, st.interval.end + 1)
        ref = root_train[sl] if j != 1 else own
        frames = [f for f in test_files
                  if any(a <= test_times[f] <= b for a, b in renders.get(j, []))]  # fmt: skip
        bg_t, dyn_t = _test_psnr(tree_run, scene_dir, frames)
        bg_r, dyn_r = _test_psnr(root_run, scene_dir, frames)
        rows.append({
            "node": j, "frames": [st.interval.start, st.interval.end], "renders": len(frames),
            "train": float(np.mean(own)), "train_root": float(np.mean(ref)),
            "test_bg": float(np.nanmean(bg_t)) if frames else None,
            "test_bg_root": float(np.nanmean(bg_r)) if frames else None,
            "test_dyn": float(np.nanmean(dyn_t)) if frames else None,
            "test_dyn_root": float(np.nanmean(dyn_r)) if frames else None,
        })  # fmt: skip
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("tree_run", type=Path)
    ap.add_argument("root_run", type=Path)
    ap.add_argument("--scene", type=Path, required=True)
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args(argv)
    try:
        rows = diagnose(a.tree_run, a.root_run, a.scene)
    except UserError as e:  # e.g. a root run that is not a WorldTree run (`--ablate tpt`) has no tree nodes
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from None

    def f(x):
        return "-" if x is None else f"{x:6.2f}"

    print(f"{'node':>4} {'frames':>9} {'n':>3}  {'train':>6} {'root':>6}  {'bg':>6} {'root':>6}  {'dyn':>6} {'root':>6}")
    for r in rows:
        print(f"{r['node']:>4} {r['frames'][0]:>4}-{r['frames'][1]:<4} {r['renders']:>3}  {f(r['train'])} "
              f"{f(r['train_root'])}  {f(r['test_bg'])} {f(r['test_bg_root'])}  {f(r['test_dyn'])} "
              f"{f(r['test_dyn_root'])}")  # fmt: skip
    if a.json is not None:
        a.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
