"""Leave-one-out scoring on a real capture without its test views (e.g. Balloon1 in the DynamicNeRF layout).

For each held-out training frame k: train a method on the other frames (re-indexed 0..T-2, times kept in
order), render frame k's camera at frame k's time -- a view and a time the model never saw -- and score it
against frame k at the method's working size (``--score-size full``: rendered and scored at the scene's own
size, as the NVIDIA protocol scores at 480x270 whatever the training size): PSNR on the uint8 images, and
masked PSNR (the `worldtree` protocol's: PSNR of the masked pixels' values) when the scene has a mask for
frame k (``--masks DIR``, one per frame); both from :mod:`benchmarks.evaluation.metrics`.

A protocol of the harness, through :class:`methods.registry.Method` alone: frame k's time is ``k - 0.5`` of
the kept frames (between k-1 and k+1, re-indexed k-1 and k), drawn by the method's ``render_between`` (a
method without it: its ``render`` of the nearer kept frame, :func:`methods.registry.render_between`); the
camera is the given one as the method places a camera it did not train with (no test-time pose refinement,
which would look at frame k). k must have both neighbours (1..T-2). The kept neighbours k-1 and k+1 are
rendered at their own training frames through the cameras the method trained them with
(:func:`methods.registry.render_training_frame`; ``k<k>_<method>_prev.png`` / ``_next.png``,
``psnr_train_neighbours``): a blur there is a fitting problem, a sharp fit there and a blur at k an
interpolation problem. A method whose ``node_at`` names a tree node records the one that drew time k
(``tree.rendered_by``). Imported priors (``--depth-maps``, ``--flow``, ``--masks``: the folders `nvls
import` writes) are re-indexed without frame k (flow pairs touching k are dropped) for a method whose config
has ``priors``.

What each method draws between two frames is its own (its ``render_between``; this repository's methods:
docs/evaluation.md). The runs go frame by frame; a method whose first stages another method of ``--methods``
trains alike for the same k (``MethodSpec.shared_root``: WorldTree after Base) takes them from that run
(:mod:`benchmarks.runner.shared_root`; the row's ``root_from``, and ``train_s`` counts the lent stages), unless
``--no-share-root``.

Usage (results appended to OUT/loo.json; a finished (label, k, method) result is reused only when it was
computed with the same configuration -- preset, steps, seed, downscale, every ``--set``, the depth options,
the scene and the prior folders, hashed into its ``config_key`` -- so an interrupted run resumes and a changed
one computes again; ``--set`` keys are checked like ``wtbench run``'s, before any work; ``--set
NAME:KEY=VALUE`` and ``--NAME-steps N`` change one method's config only)::

    nice python -m benchmarks.evaluation.leave_one_out SCENE --frames 3,6,9 --methods static,base -o runs/loo \\
        [--preset quick] [--steps N] [--depth-maps DIR --depth-kind disparity --depth-fit] [--flow DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

import worldtree
from methods.registry import list_methods, node_at, render_between, render_training_frame
from worldtree.imageio import read_mask, write_image
from worldtree.infra.atomic import atomic_write_json
from worldtree.infra.cli_runner import Terminated, signals_raise, stop_report
from worldtree.infra.device import pick_device
from worldtree.infra.errors import UserError
from worldtree.pixels import as_uint8
from worldtree.scene import Scene, load_scene


def drop_frame(scene: Scene, k: int) -> Scene:
    """The scene without training frame ``k`` (frames re-indexed 0..T-2) and without test views."""
    keep = torch.tensor([t for t in range(scene.num_frames) if t != k])
    return dataclasses.replace(
        scene,
        images=scene.images[keep].clone(),
        Ks=scene.Ks[keep].clone(),
        w2cs=scene.w2cs[keep].clone(),
        frame_cameras=scene.frame_cameras[keep].clone(),
        times=torch.arange(scene.num_frames - 1),
        test_images=torch.zeros(0, 1, 1, 3),
        test_times=torch.zeros(0, dtype=torch.long),
        test_masks=None,
        test_files=[],
    )


def _reindex(t: int, k: int) -> int:
    return t if t < k else t - 1


def subset_priors(folders: dict[str, Path], k: int, T: int, tmp: Path) -> dict[str, Path]:
    """Copies of imported prior folders without frame ``k``: per-frame files (sorted) minus the k-th; flow
    files ``<i>_<j>`` with i, j != k renamed to the new indices."""
    import re

    out = {}
    for name, src in folders.items():
        dst = tmp / name
        dst.mkdir(parents=True)
        if name == "flow":
            for p in sorted(src.iterdir()):
                m = re.match(r"^(\d+)[_-](\d+)$", p.stem)
                if m and k not in (int(m.group(1)), int(m.group(2))):
                    i, j = _reindex(int(m.group(1)), k), _reindex(int(m.group(2)), k)
                    shutil.copy(p, dst / f"{i:05d}_{j:05d}{p.suffix}")
        else:
            files = sorted(p for p in src.iterdir() if p.is_file())
            if len(files) != T:
                raise UserError(f"{src}: {len(files)} files for {T} frames; one per frame")
            for n, p in enumerate(f for t, f in enumerate(files) if t != k):
                shutil.copy(p, dst / f"{n:05d}{p.suffix}")
        out[name] = dst
    return out


def score(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray | None = None) -> float | None:
    """PSNR (dB, peak 255) of two uint8 images ``[H, W, 3]`` (:func:`benchmarks.evaluation.metrics.psnr`); with
    ``mask`` ``[H, W]``, the `worldtree` protocol's mPSNR, PSNR of the masked pixels' values
    (:func:`~benchmarks.evaluation.metrics.masked_psnr`), None for an empty mask."""
    from benchmarks.evaluation.metrics import masked_psnr, psnr

    a, b = (torch.from_numpy(np.ascontiguousarray(x))[None] for x in (pred, gt))
    if mask is None:
        return float(psnr(a, b, 255.0)[0])
    value = float(masked_psnr(a, b, torch.from_numpy(np.ascontiguousarray(mask))[None], 255.0)[0])
    return None if np.isnan(value) else value


def _to_u8(img: torch.Tensor) -> np.ndarray:
    """``[H, W, 3]`` in [0, 1] -> uint8, rounded: every score is on the 8-bit images, as written to disk."""
    return as_uint8(img.detach().cpu()).numpy()


def run_one(
    args, spec, cfg, scene: Scene, k: int, device, prior_dirs: dict[str, Path], out: Path,
    score_scene: Scene | None = None, checkpoints: Path | None = None, lent=None,
) -> dict:
    """Train ``spec`` on ``scene`` minus frame k, render frame k's camera at time k, score it (against
    ``score_scene``'s frame k and through its camera when given: the same scene at another size).
    ``checkpoints``: a folder for the method's checkpoints (None: none kept), holding ``lent``'s root
    (:class:`benchmarks.runner.shared_root.LentRoot`, linked there) when another method's run lends it."""
    from worldtree.infra.determinism import deterministic_for
    from worldtree.trainer import TrainContext

    sub = drop_frame(scene, k)
    # Inside OUT, named for the cleanup of a killed run's leftovers (main), removed on any exit here.
    with tempfile.TemporaryDirectory(dir=out, prefix=TMP_PREFIX) as tmp:
        if prior_dirs and hasattr(cfg, "priors"):
            dirs = subset_priors(prior_dirs, k, scene.num_frames, Path(tmp))
            rep = {"depth": "depth_source", "flow": "flow_source", "masks": "masks_source"}
            cfg = dataclasses.replace(
                cfg, priors=dataclasses.replace(cfg.priors, **{rep[n]: str(p) for n, p in dirs.items()})
            )
        if hasattr(cfg, "priors_cache"):
            cfg = dataclasses.replace(cfg, priors_cache=False)  # the subset's priors are not the scene's
        torch.manual_seed(cfg.seed)
        deterministic_for(device)  # as `wtbench run`: one seed, one result
        method = spec.build(cfg, sub, device)
        t0 = time.perf_counter()
        method.fit(TrainContext(checkpoint_dir=checkpoints, progress=args.progress, resume=checkpoints is not None))
        train_s = time.perf_counter() - t0
    target = score_scene if score_scene is not None else scene
    H, W = target.height, target.width
    K, w2c = target.Ks[k], target.w2cs[k]
    t_k = k - 0.5  # frame k's time: halfway between the kept frames k-1 and k+1, re-indexed k-1 and k
    pred, gt = _to_u8(render_between(method, K, w2c, W, H, t_k)), _to_u8(target.images[k])
    write_image(out / f"k{k:02d}_{spec.name}.png", pred)
    if lent is not None:  # the lent stages' time, so that train_s is what the method costs alone
        train_s += sum(lent.stages_s.values())
    row = {"k": k, "method": spec.name, "psnr": score(pred, gt), "train_s": round(train_s, 1),
           "scored_size": [W, H]}
    if lent is not None:
        row["root_from"] = {"method": lent.method, "items": list(lent.items), "stages_s": lent.stages_s}
    stats = method.stats()
    node = node_at(method, t_k)
    if node is not None:  # a method with a tree: the node that drew time k, the tree's nodes and decisions
        tree = stats.get("tree") if isinstance(stats.get("tree"), dict) else {}
        row["tree"] = {"tree_nodes": tree.get("nodes"), "rendered_by": node}
        if tree.get("auto") is not None:  # --depth auto: what the criterion measured and decided, per node
            row["tree"]["auto"] = tree["auto"]
    # How well the kept neighbours themselves are fitted: a blur at time k that is already a blur at k-1 and
    # k+1 is a fitting problem, a sharp fit there and a blur at k an interpolation problem.
    row["psnr_train_neighbours"] = {}
    for side, t in (("prev", k - 1), ("next", k)):
        got = _to_u8(render_training_frame(method, sub.Ks[t], sub.w2cs[t], sub.width, sub.height, t))
        write_image(out / f"k{k:02d}_{spec.name}_{side}.png", got)
        row["psnr_train_neighbours"][side] = score(got, _to_u8(sub.images[t]))
    if args.masks is not None:
        files = sorted(p for p in Path(args.masks).iterdir() if p.is_file())
        m = read_mask(files[k])
        if m.shape != (H, W):
            import cv2

            m = cv2.resize(m.astype(np.uint8) * 255, (W, H), interpolation=cv2.INTER_NEAREST) > 127
        row["mpsnr"] = score(pred, gt, m)
    row["stats"] = {
        key: stats[key]
        for key in ("num_static", "num_dynamic", "scaffold_nodes_final", "migration")
        if key in stats
    }
    if isinstance(row["stats"].get("migration"), dict):
        row["stats"]["migration"] = {k: v for k, v in row["stats"]["migration"].items() if k != "events"}
    for key in ("dynamic_tracks", "scaffold_nodes", "priors", "motion_refine"):
        if key in stats:
            row["stats"][key] = stats[key]
    return row


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument(
        "--frames", required=True, help="Held-out frames, e.g. 3,6,9 (each needs both neighbours)."
    )
    ap.add_argument("--methods", default="static,base")
    ap.add_argument("-o", "--out", type=Path, default=Path("runs/loo"))
    ap.add_argument("--preset", default="quick")
    ap.add_argument("--steps", type=int, default=None, help="Override the steps of every method.")
    for spec in list_methods():  # --static-steps, --base-steps, ...: one method's steps (--set NAME:steps=N)
        ap.add_argument(f"--{spec.name}-steps", type=int, default=None, metavar="N", dest=f"steps_of:{spec.name}",
                        help=f"Override the steps of method {spec.name} only.")  # fmt: skip
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--downscale", type=int, default=None, help="Override the preset's image shrink.")
    ap.add_argument(
        "--score-size", default="train", choices=("train", "full"),
        help="Render and score frame k at the method's training size (default) or at the scene's own size.",
    )
    ap.add_argument("--device", default="auto")
    ap.add_argument("--depth-maps", type=Path, default=None)
    ap.add_argument("--depth-kind", default="depth", choices=("depth", "disparity"))
    ap.add_argument("--depth-fit", action="store_true")
    ap.add_argument("--flow", type=Path, default=None)
    ap.add_argument(
        "--masks", type=Path, default=None, help="Per-frame dynamic masks: used as priors and for mPSNR."
    )
    ap.add_argument(
        "--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
        help="Change a config field of the methods that have it (as wtbench run --set); repeatable. A key "
        "no method of --methods has is an error. NAME:KEY=VALUE changes it for method NAME only (over the "
        "common options: --set NAME:steps=N is --NAME-steps N).",
    )  # fmt: skip
    ap.add_argument(
        "--label", default="", help="Name of this configuration in the results (e.g. before/after)."
    )
    ap.add_argument("--progress", action="store_true")
    ap.add_argument(
        "--no-share-root", dest="share_root", action="store_false",
        help="Train every method's root itself (default: a method whose root another method of --methods "
        "trains alike for the same frame, WorldTree after Base, takes it from that run).",
    )  # fmt: skip
    args = ap.parse_args(argv)
    args.method_steps = {spec.name: getattr(args, f"steps_of:{spec.name}") for spec in list_methods()}

    from worldtree.infra.folder_lock import FolderLock
    from worldtree.infra.output_paths import check_output_folder

    try:
        frames = [int(v) for v in args.frames.split(",") if v.strip()]
    except ValueError:
        raise UserError(f"--frames {args.frames!r}: expected comma-separated frame indices") from None
    if not frames:
        raise UserError(f"--frames {args.frames!r}: give at least one frame index")
    if not args.scene.is_dir():
        raise UserError(f"SCENE {args.scene}: no such folder; give a scene folder (docs/scene_format.md)")
    out = args.out
    check_output_folder(out, "-o")
    prior_dirs = {
        n: p for n, p in (("depth", args.depth_maps), ("flow", args.flow), ("masks", args.masks)) if p
    }
    for n, p in prior_dirs.items():
        if not p.is_dir():
            flag = {"depth": "--depth-maps", "flow": "--flow", "masks": "--masks"}[n]
            raise UserError(f"{flag} {p}: no such folder; give the folder of per-frame files")
    # Every method's config resolved and checked (--set keys, ranges) before any work.
    plans = [(spec, cfg, _config_key(spec.name, cfg, args, prior_dirs))
             for spec, cfg in ((s, _training_size(c, args)) for s, c in resolve_configs(args))]  # fmt: skip
    scenes: dict[int, Scene] = {}
    for _, cfg, _ in plans:  # every held-out frame checked before any training
        if cfg.downscale not in scenes:
            scenes[cfg.downscale] = load_scene(args.scene, downscale=cfg.downscale, load_masks=False)
        n = scenes[cfg.downscale].num_frames
        for k in frames:
            if not 1 <= k <= n - 2:
                raise UserError(f"--frames: {k} needs a frame on each side (1..{n - 2})")
    score_scene = None
    if args.score_size == "full":  # the full-size scene, unless a method already trains on it
        score_scene = scenes[1] if 1 in scenes else load_scene(args.scene, downscale=1, load_masks=False)
    device = pick_device(args.device)
    out.mkdir(parents=True, exist_ok=True)
    # One writer of OUT (loo.json and the temporary prior folders): every temporary folder found while
    # holding the lock is a leftover of a killed run.
    with FolderLock(out, "leave-one-out folder"), signals_raise():
        for stale in sorted(out.glob(f"{TMP_PREFIX}*")):
            shutil.rmtree(stale, ignore_errors=True)
        _run_all(args, plans, scenes, frames, device, prior_dirs, out, score_scene)


#: Prefix of the temporary folders (the priors without the held-out frame) inside OUT.
TMP_PREFIX = ".loo-tmp-"
#: ``--set`` keys that have their own option (refused with it).
_OWN_OPTIONS = {"steps": "--steps", "seed": "--seed", "downscale": "--downscale",
                "priors.depth_source": "--depth-maps", "priors.flow_source": "--flow",
                "priors.masks_source": "--masks"}  # fmt: skip


def split_scope(item: str) -> tuple[str | None, str]:
    """``"NAME:KEY=VALUE"`` -> ``("NAME", "KEY=VALUE")``, a ``--set`` for method NAME only; an item without a
    ``:`` before its ``=`` -> ``(None, item)``, a ``--set`` for every method that has KEY."""
    if ":" not in item.partition("=")[0]:
        return None, item
    name, _, rest = item.partition(":")
    return name.strip(), rest


def resolve_configs(args) -> list[tuple]:
    """``(spec, config)`` of every method of ``--methods``: the preset, ``--steps``/``--seed``/
    ``--downscale``, the ``--set KEY=VALUE`` assignments of the fields each method has, then its own ``--set
    NAME:KEY=VALUE`` (and ``--NAME-steps``; these may override the common options for that method); the prior
    folders and depth import options are set first, so that each ``--set`` is checked against them. Like ``wtbench run``: a ``--set`` key that no method has, a malformed or repeated
    one, one that has its own option, a value that does not parse or a setting outside its range
    (:mod:`worldtree.infra.config_ranges`) is a one-line :class:`UserError`, before any work."""
    from methods.config_overrides import apply_overrides, canonical_sets, split_assignment
    from methods.registry import get_method
    from worldtree.infra.config_ranges import check_config_ranges

    names = [n.strip() for n in args.methods.split(",") if n.strip()]
    if not names:
        raise UserError(f"--methods {args.methods!r}: give method names, e.g. static,base")
    common, scoped = [], {n: {} for n in names}  # scoped: method -> {KEY=VALUE: how it was given}
    for item in args.sets:
        name, rest = split_scope(item)
        if name is None:
            common.append(item)
        elif name not in scoped:
            raise UserError(f"--set {item}: {name!r} is not among --methods {','.join(names)}")
        else:
            scoped[name][rest] = f"--set {item}"
    for name, steps in sorted((getattr(args, "method_steps", None) or {}).items()):
        if steps is None:
            continue
        if name not in scoped:
            raise UserError(f"--{name}-steps {steps}: {name!r} is not among --methods {','.join(names)}")
        scoped[name][f"steps={steps}"] = f"--{name}-steps {steps}"
    canonical_sets(common)  # malformed items, keys given twice
    own = {"steps": args.steps, "seed": args.seed, "downscale": args.downscale,
           "priors.depth_source": args.depth_maps, "priors.flow_source": args.flow,
           "priors.masks_source": args.masks}  # fmt: skip
    for item in common:
        key, _ = split_assignment(item)
        if own.get(key) is not None:
            raise UserError(f"--set {item}: {key} is also given by {_OWN_OPTIONS[key]}; keep one of them")
    for name, items in scoped.items():
        for rest, how in items.items():
            key, _ = split_assignment(rest)
            if key.startswith("priors.") and own.get(key) is not None:  # a prior folder: its option alone
                raise UserError(f"{how}: {key} is also given by {_OWN_OPTIONS[key]}; keep one of them")
        try:
            canonical_sets(list(items))
        except UserError as e:
            raise UserError(f"{e} (method {name}: --set {name}:KEY=VALUE or --{name}-steps)") from None
    options = {"steps": args.steps, "seed": args.seed, "downscale": args.downscale}
    plans, owned = [], set()
    for name in names:
        spec = get_method(name)
        cfg = spec.config(args.preset)
        cfg = dataclasses.replace(cfg, **{k: v for k, v in options.items() if v is not None})
        if args.steps is not None:
            cfg = cfg.with_exact_steps()  # as `wtbench run --steps N`: exactly N on a video of any length
        if hasattr(cfg, "priors"):  # before the --set items: they are checked against the priors the run uses
            sources = {"depth_source": args.depth_maps, "flow_source": args.flow, "masks_source": args.masks}
            cfg = dataclasses.replace(cfg, priors=dataclasses.replace(
                cfg.priors, **{k: str(v) for k, v in sources.items() if v is not None},
                depth_import=dataclasses.replace(
                    cfg.priors.depth_import, kind=args.depth_kind, fit_scale_shift=args.depth_fit)))  # fmt: skip
        mine = [item for item in common if _has_field(cfg, split_assignment(item)[0])]
        owned |= set(mine)
        if mine:
            cfg = apply_overrides(cfg, mine)
        given = {split_assignment(item)[0]: f"--set {item}" for item in mine}
        given |= {k: f"--{k} {v}" for k, v in options.items() if v is not None}
        if scoped[name]:
            if any(split_assignment(rest)[0] == "steps" for rest in scoped[name]):
                cfg = cfg.with_exact_steps()  # --NAME-steps N: exactly N (a scoped steps_per_frame still wins)
            try:
                cfg = apply_overrides(cfg, list(scoped[name]))
            except UserError as e:
                raise UserError(f"{e} (method {name})") from None
            given |= {split_assignment(rest)[0]: how for rest, how in scoped[name].items()}
        for k in ("steps", "downscale"):
            if getattr(cfg, k) < 1:
                raise UserError(f"{given.get(k, f'setting {k}')}: must be at least 1")
        check_config_ranges(cfg, given)
        plans.append((spec, cfg))
    for item in common:
        if item not in owned:
            try:  # the first method's message names its fields and the closest one
                apply_overrides(plans[0][1], [item])
            except UserError as e:
                raise UserError(f"{e} (no method of --methods {','.join(names)} has it)") from None
            raise UserError(f"--set {item}: no method of --methods {','.join(names)} has this setting")
    return plans


def _folder_fingerprint(folder: Path) -> dict:
    """A prior folder as the results key sees it: its absolute path and each file's name and sha256."""
    from worldtree.infra.hashing import sha256_file

    files = sorted(p for p in folder.iterdir() if p.is_file()) if folder.is_dir() else []
    return {"path": str(folder.resolve()), "files": [(p.name, sha256_file(p)) for p in files]}


def _config_key(method: str, cfg, args, prior_dirs: dict[str, Path]) -> str:
    """16 hex digits of the sha256 of everything a result depends on: the method, its whole resolved config
    (preset, --steps/--seed/--downscale, every --set, the depth import options), the scene and the imported
    prior folders (their files). A finished result is reused only under the same key."""
    record = {
        "method": method,
        "config": dataclasses.asdict(cfg),
        "scene": str(args.scene.resolve()),
        "priors": {n: _folder_fingerprint(p) for n, p in sorted(prior_dirs.items())},
    }
    if args.score_size != "train":  # keys of training-size results stay as they were
        record["score_size"] = args.score_size
    text = json.dumps(record, sort_keys=True, default=str)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]


def _run_all(
    args, plans, scenes: dict[int, Scene], frames: list[int], device, prior_dirs: dict[str, Path], out: Path,
    score_scene: Scene | None = None,
) -> None:
    res_path = out / "loo.json"
    try:
        results = json.loads(res_path.read_text()) if res_path.is_file() else {"runs": []}
        if not isinstance(results, dict) or not isinstance(results.get("runs"), list):
            raise ValueError("no 'runs' list")
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise UserError(f"{res_path}: unreadable ({e}); move it away to start a new results file") from None
    done = {(r.get("label"), r.get("k"), r.get("method"), r.get("config_key")) for r in results["runs"]
            if isinstance(r, dict)}  # fmt: skip
    # Frame by frame, so that the runs of one held-out frame can share a root (Base and WorldTree train the
    # same one): the first run of each root keeps its checkpoints until the frame's last run.
    for k in frames:
        with tempfile.TemporaryDirectory(dir=out, prefix=TMP_PREFIX) as roots:
            _run_frame(args, plans, scenes, k, device, prior_dirs, out, score_scene, results, done, Path(roots))
    _summary(results, args.label, {key for _, _, key in plans})


def _root_record(spec, cfg, args, prior_dirs: dict[str, Path]) -> dict:
    """What :func:`benchmarks.runner.shared_root.root_differences` compares, for one method of the sweep."""
    return {"method": spec.name, "scene": str(Path(args.scene).resolve()), "device": args.device,
            "imported_priors": {n: str(p.resolve()) for n, p in prior_dirs.items()},
            "config": dataclasses.asdict(cfg)}  # fmt: skip


def _run_frame(args, plans, scenes, k: int, device, prior_dirs, out: Path, score_scene, results: dict, done: set,
               roots: Path) -> None:  # fmt: skip
    """Every method's run without frame ``k`` (see :func:`_run_all`); ``roots``: a temporary folder for the
    checkpoints of runs that lend their root (``--no-share-root``: none kept)."""
    from methods.shared_root import lend_root, lendable, root_differences

    res_path = out / "loo.json"
    lenders: list[tuple[dict, Path]] = []
    for i, (spec, cfg, key) in enumerate(plans):
        scene = scenes[cfg.downscale]
        if (args.label, k, spec.name, key) in done:
            continue
        if any((r.get("label"), r.get("k"), r.get("method")) == (args.label, k, spec.name)
               for r in results["runs"] if isinstance(r, dict)):  # fmt: skip
            print(f"[loo] {args.label or '-'} k={k} {spec.name}: {res_path} holds a result computed with "
                  "other settings; computing this configuration's", file=sys.stderr, flush=True)  # fmt: skip
        print(f"[loo] {args.label or '-'} k={k} {spec.name}: training on {scene.num_frames - 1} frames",
              file=sys.stderr, flush=True)  # fmt: skip
        shared = spec.shared_root if args.share_root else None
        folder, lent = None, None
        if shared is not None:
            rec = _root_record(spec, cfg, args, prior_dirs if hasattr(cfg, "priors") else {})
            src = next(((r, f) for r, f in lenders if root_differences(shared, r, rec) is None), None)
            folder = roots / f"{i}-{spec.name}"
            if src is None:
                lenders.append((rec, folder))
            else:
                lent = lendable(src[1], src[0]["method"], shared)
                lend_root(lent, folder / "checkpoints", shared.checkpoints)
                print(f"[loo] k={k} {spec.name}: root from this frame's {lent.method} run", file=sys.stderr,
                      flush=True)  # fmt: skip
        row = run_one(
            args, spec, cfg, scene, k, device, prior_dirs if hasattr(cfg, "priors") else {}, out, score_scene,
            checkpoints=folder / "checkpoints" if folder is not None else None, lent=lent,
        )
        row.update(label=args.label, preset=args.preset, seed=cfg.seed, steps=cfg.steps,
                   downscale=cfg.downscale, version=worldtree.__version__, command=" ".join(sys.argv),
                   config_key=key, sets=sorted(args.sets),
                   priors={n: str(p.resolve()) for n, p in prior_dirs.items()})  # fmt: skip
        results["runs"].append(row)
        atomic_write_json(res_path, results)
        mp = f" mPSNR {row['mpsnr']:.2f}" if row.get("mpsnr") is not None else ""
        nb = row["psnr_train_neighbours"]
        print(f"[loo] k={k} {spec.name}: PSNR {row['psnr']:.2f}{mp} (kept neighbours fitted at "
              f"{nb['prev']:.2f} / {nb['next']:.2f}; {row['train_s']:.0f} s)", flush=True)  # fmt: skip


def _training_size(cfg, args):
    """``cfg`` with the shrink it trains at on the scene without one frame (its ``downscale_for`` that video,
    as ``wtbench run``), unless ``--downscale`` or a ``--set downscale`` gave one."""
    from methods.config_overrides import split_assignment
    from methods.registry import at_training_size

    given = args.downscale is not None or any(split_assignment(split_scope(i)[1])[0] == "downscale"
                                              for i in args.sets)  # fmt: skip
    return cfg if given else at_training_size(cfg, args.scene, dropped_frames=1)


def _has_field(cfg, dotted: str) -> bool:
    obj = cfg
    for part in dotted.strip().split("."):
        if not dataclasses.is_dataclass(obj) or part not in {f.name for f in dataclasses.fields(obj)}:
            return False
        obj = getattr(obj, part)
    return True


def _summary(results: dict, label: str, keys: set[str] | None = None) -> None:
    """Mean scores per method of the rows of ``label`` (and, given ``keys``, of these configurations only)."""
    rows = [
        r for r in results["runs"] if r["label"] == label and (keys is None or r.get("config_key") in keys)
    ]
    by = {}
    for r in rows:
        by.setdefault(r["method"], []).append(r)
    for m, rs in sorted(by.items()):
        ks = ",".join(str(r["k"]) for r in rs)
        kept = np.mean([v for r in rs for v in r["psnr_train_neighbours"].values()])
        print(f"{label or '-'} {m:8s} frames {ks}: mean PSNR {np.mean([r['psnr'] for r in rs]):.2f} "
              f"(kept neighbours fitted at {kept:.2f})")  # fmt: skip


INTERRUPTED = (
    "interrupted: finished (k, method) results are in OUT/loo.json; re-run the same command to compute the "
    "rest (the interrupted training starts again)"
)


if __name__ == "__main__":
    try:
        main()
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    except (KeyboardInterrupt, Terminated) as e:
        # The temporary folder and the lock were released by the finally blocks on the way here. Leave without
        # interpreter shutdown: a SIGINT arriving during it (CI saw one) ends the process as killed by the
        # signal instead of with the documented status.
        line, code = stop_report(e, INTERRUPTED)
        print(line, file=sys.stderr)
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
