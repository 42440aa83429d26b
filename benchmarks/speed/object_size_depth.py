"""How far an object's apparent size and the smoothness of its path place it in depth, on generated scenes.

Issue #28 asks for the depth of a moving object seen by one camera per frame. Two cues measure the object
itself rather than the static world around it:

- **size constancy**: a rigid object's image area falls as its depth squared, so ``q_t = 1 / sqrt(area_t)`` is
  its depth up to one factor per object (exact for a sphere, a rotating box's outline adds a few per cent);
- **one smooth path**: that factor is the one that makes the object's centre path ``c_t + s q_t r_t`` smoothest
  (:func:`worldtree.motion.track_depth.trajectory_scale`), measured only where the cameras accelerate.

For every object of a scene written by ``nvls synth`` + ``nvls build --poses`` + ``nvls gt-priors`` this
reports, over the training frames where the object is one whole piece of the mask (its own connected
component, not cut by the image border; a piece belongs to the object whose true centre projects nearest):

- ``size``: the median ``|log(z / z_true)|`` of ``q`` under its best single factor (what size constancy alone
  gives, with the scale known);
- ``path``: the same with the factor from the path, and the path fit's ``fit`` (1: a smooth path exists);
- ``path_exact``: the factor from the path with the exact relative depths (the path cue alone).

``z_true`` is the camera depth of the object's true centre (``RAW/gt/objects.json``, mapped into the scene by
``gt_priors.json``'s alignment), and the ray goes through the centroid of its mask piece. ``--masks-from SUBDIR`` scores
another set of masks instead of the exact ones (``SCENE/SUBDIR``: one PNG per training frame, white = moving).

    python -m benchmarks.speed.object_size_depth FAMILY [NAME ...] [--masks-from SUBDIR] [--json OUT.json]

``FAMILY`` is the folder of ``scripts/tree_family.sh`` (``FAMILY/raw/NAME``, ``FAMILY/scenes/NAME``).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import cv2
import numpy as np
import torch

from worldtree.imageio import read_mask
from worldtree.infra.atomic import atomic_write_json
from worldtree.motion.lift import project_points
from worldtree.motion.track_depth import trajectory_scale
from worldtree.scene import load_scene

__all__ = ["measure_object", "object_pieces"]

MIN_AREA = 6
"""Pieces under this many pixels are noise, not an object."""


def object_pieces(mask: np.ndarray, centres_uv: np.ndarray) -> dict[int, tuple[np.ndarray, float, bool]]:
    """The piece of ``mask`` ``[H, W]`` bool that belongs to each object, by its true centre ``centres_uv``
    ``[O, 2]`` (pixels): each connected piece (8-connected, at least ``MIN_AREA`` px) goes to the object whose
    centre projects nearest. Returns ``{object: (centroid [2] px, area px, touches the border)}`` for the
    objects that own exactly one piece, which no other object's centre lies in, and whose own centre lies in
    no other piece (two objects drawn as one piece measure neither)."""
    H, W = mask.shape
    n, lab, st, cen = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    owned: dict[int, list[int]] = {}
    for k in range(1, n):
        if st[k, 4] < MIN_AREA:
            continue
        o = int(np.argmin(np.linalg.norm(centres_uv - cen[k], axis=1)))
        owned.setdefault(o, []).append(k)
    # the piece under each centre (0: none): two centres in one piece are a merge, and a centre inside a
    # piece it does not own means the pieces were handed out wrongly; neither object is measured then
    under = []
    for u, v in centres_uv:
        x, y = int(round(u)), int(round(v))
        under.append(int(lab[y, x]) if 0 <= x < W and 0 <= y < H else 0)
    out = {}
    for o, ks in owned.items():
        if len(ks) != 1 or under[o] not in (0, ks[0]) or under.count(ks[0]) > 1:
            continue
        x, y, w, h, area = (int(a) for a in st[ks[0]])
        out[o] = (cen[ks[0]].astype(np.float64), float(area), x == 0 or y == 0 or x + w == W or y + h == H)
    return out


def measure_object(
    frames: np.ndarray, centroids: np.ndarray, areas: np.ndarray, z_true: np.ndarray, Ks, w2cs
) -> dict[str, float]:
    """The three figures of the module docstring for one object seen at ``frames`` ``[K]`` with mask piece
    ``centroids`` ``[K, 2]`` px and ``areas`` ``[K]`` px, true centre depths ``z_true`` ``[K]`` (scene units);
    ``Ks`` ``[T, 3, 3]``, ``w2cs`` ``[T, 4, 4]`` tensors. Errors are medians of ``|log(z / z_true)|``; NaN where
    the path gives no positive factor."""
    q = 1.0 / np.sqrt(np.maximum(areas, 1.0))
    best = math.exp(float(np.median(np.log(z_true / q))))
    out = {"frames": float(len(frames)), "size": float(np.median(np.abs(np.log(best * q / z_true))))}
    f, px = torch.as_tensor(frames), torch.as_tensor(centroids)
    for name, rel in (("path", q), ("path_exact", z_true)):
        s, fit = trajectory_scale(f, px, torch.as_tensor(rel, dtype=torch.float64), Ks, w2cs)
        out[name] = float(np.median(np.abs(np.log(s * rel / z_true)))) if s > 0 else float("nan")
        out[f"{name}_fit"] = fit
    return out


def _alignment(scene: Path) -> tuple[float, np.ndarray, np.ndarray]:
    path = scene / "gt_priors" / "gt_priors.json"
    if not path.is_file():
        raise SystemExit(f"error: {path}: missing; write it with `nvls gt-priors RAW {scene}`")
    a = json.loads(path.read_text())["alignment"]
    return float(a["scale"]), np.asarray(a["R"], float), np.asarray(a["t"], float)


def measure_scene(scene: Path, raw: Path, masks_dir: Path | None = None) -> list[dict]:
    """One row per object of the generated ``scene`` (see the module docstring)."""
    objects_file = raw / "gt" / "objects.json"
    if not objects_file.is_file():
        raise SystemExit(f"error: {objects_file}: missing; {raw} is not a capture written by `nvls synth`")
    sc = load_scene(scene, load_masks=False)
    Ks, w2cs = sc.Ks.double(), sc.w2cs.double()
    folder = masks_dir or scene / "gt_priors" / "masks"
    files = sorted(folder.glob("*.png"))
    if len(files) != sc.num_frames:
        raise SystemExit(f"error: {folder}: {len(files)} mask PNGs for {sc.num_frames} training frames")
    masks = [read_mask(p) for p in files]
    H, W = masks[0].shape
    Ks = Ks.clone()
    Ks[:, 0] *= W / sc.width  # intrinsics at the masks' size
    Ks[:, 1] *= H / sc.height
    scale, R_al, t_al = _alignment(scene)
    objs = json.loads(objects_file.read_text())["objects"]
    T = sc.num_frames
    times = sc.times.numpy()
    centres = np.array([[np.asarray(o["world_from_object"][int(t)])[:3, 3] for t in times] for o in objs])
    centres = scale * centres @ R_al.T + t_al  # [O, T, 3] scene units
    projected = [project_points(torch.from_numpy(centres[:, t]), Ks[t], w2cs[t]) for t in range(T)]
    uv = torch.stack([p[0] for p in projected], 1).numpy()  # [O, T, 2]
    z = torch.stack([p[1] for p in projected], 1).numpy()  # [O, T] camera depth
    seen: list[dict[int, tuple]] = [object_pieces(masks[t], uv[:, t]) for t in range(T)]
    rows = []
    for o, ob in enumerate(objs):
        keep = [t for t in range(T) if o in seen[t] and not seen[t][o][2] and z[o, t] > 0]
        row = {"scene": scene.name, "object": ob.get("kind", str(o)), "frames_total": T}
        if len(keep) < 4:
            rows.append(row | {"frames": float(len(keep))})
            continue
        cents = np.array([seen[t][o][0] for t in keep])
        areas = np.array([seen[t][o][1] for t in keep])
        rows.append(row | measure_object(np.array(keep), cents, areas, z[o, keep], Ks, w2cs))
    return rows


def _fmt(v) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.3f}"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("family", type=Path, help="folder of scripts/tree_family.sh (raw/NAME, scenes/NAME)")
    ap.add_argument("names", nargs="*", help="scene names (default: every scene under FAMILY/scenes)")
    ap.add_argument("--masks-from", default=None, help="SCENE/SUBDIR of mask PNGs to score instead of exact")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    a = ap.parse_args(argv)
    names = a.names or sorted(p.name for p in (a.family / "scenes").iterdir() if p.is_dir())
    if not names:
        raise SystemExit(f"error: {a.family / 'scenes'}: no scenes; make them with scripts/tree_family.sh")
    rows = []
    for name in names:
        scene = a.family / "scenes" / name
        masks = scene / a.masks_from if a.masks_from else None
        rows += measure_scene(scene, a.family / "raw" / name, masks)
    cols = ["size", "path", "path_fit", "path_exact", "path_exact_fit"]
    print("| scene | object | frames | " + " | ".join(cols) + " |")
    print("| --- | --- | --: |" + " --: |" * len(cols))
    for r in rows:
        n = f"{int(r['frames'])}/{r['frames_total']}"
        print(f"| {r['scene']} | {r['object']} | {n} | " + " | ".join(_fmt(r.get(c)) for c in cols) + " |")
    if a.json:
        atomic_write_json(a.json, rows)


if __name__ == "__main__":
    main()
