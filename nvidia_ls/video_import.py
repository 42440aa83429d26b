"""`nvls import CLIP.mp4` / `nvls import FRAMES_DIR`: your own monocular video -> a posed scene without test views.

Steps (docs/nvidia_ls.md, "Your own video"):

1. read the kept frames (:mod:`nvidia_ls.video_frames`: stride, max frames, resize to ``--size``);
2. moving-pixel masks from the motion cues of the priors, and incremental SfM with those pixels' features left
   out (:mod:`nvidia_ls.video_sfm`): one shared SIMPLE_RADIAL camera, focal refined;
3. frames SfM could not register are dropped (listed in the manifest and said on the console) or, with
   ``--video-unregistered fail``, stop the import; fewer than ``--video-min-registered`` of them registered
   stop it with one line naming the clip and what to try;
4. the rig world frame of ``nvls build`` (mean camera at the origin with its axes, median SfM point depth 1),
   near/far per frame from the depths of the SfM points it sees;
5. undistorted frames, ``cameras.json`` (camera 1 is a placeholder test camera at frame 0's pose: the clip
   has no test views; frames use cameras 2..T+1), ``poses_bounds.npy``, ``preview.png``, ``manifest.json``.

Everything, the SfM scratch files included, is written in a temporary folder beside the scene that is renamed
into place when complete (:func:`worldtree.infra.atomic.atomic_dir`).
"""

from __future__ import annotations

import io
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

import numpy as np

from nvidia_ls import llff
from nvidia_ls.manifest import hash_files, write_manifest
from nvidia_ls.preview import contact_sheet
from nvidia_ls.scene_checks import camera_problem
from nvidia_ls.undistort import Undistorter
from nvidia_ls.video_frames import Clip, frame_files, is_video, read_clip
from nvidia_ls.video_sfm import clip_sfm, frame_bounds, moving_masks
from nvidia_ls.world_frame import apply_similarity, rig_similarity
from nvidia_ls.writer import cameras_document, frame_file, save_image
from worldtree import __version__
from worldtree.infra.atomic import atomic_dir, atomic_write_bytes, atomic_write_json
from worldtree.infra.errors import UserError
from worldtree.infra.output_paths import (
    check_name,
    check_output_folder,
    check_replaceable,
    remove_new_folders_on_failure,
)
from worldtree.infra.timing import StageClock

SFM_WORK = ".sfm"
"""Scratch folder of pycolmap inside the scene's temporary folder (removed before the files are hashed)."""
MIN_SIZE = 16
"""Smallest frame side: the SSIM window of training is 11 pixels and SIFT needs some room."""


def is_clip_source(path: Path) -> bool:
    """True for a video file, or a folder holding frames directly (no ``images/`` subfolder)."""
    if path.is_file() or (not path.exists() and is_video(path)):
        return True
    return path.is_dir() and not (path / "images").is_dir() and bool(frame_files(path))


def clip_name(path: Path) -> str:
    """Default scene name: the video's stem, or the frames folder's name (its parent's when it is called
    ``images``/``frames``, as in ``train/images``)."""
    path = path.resolve()
    if path.is_dir() and path.name.lower() in ("images", "frames", "rgb") and path.parent.name:
        return path.parent.name
    return path.stem if path.is_file() else path.name


def import_clip(
    source: str | Path,
    out_dir: str | Path,
    cfg,
    log: Callable[[str], None] = print,
    progress: Callable[[str, int, int], None] | None = None,
) -> Path:
    """Write ``out_dir/<name>/`` from a video file or a folder of frames (``cfg``: an
    :class:`nvidia_ls.importer.ImportConfig`, its ``video`` settings and ``size``, ``name``, ``force``).

    Returns the scene folder. Bad input is a one-line :class:`UserError` naming the clip; nothing is left behind.
    """
    from nvidia_ls.build import SCENE_MARKERS

    vcfg = cfg.video
    vcfg.check()
    src = Path(source)
    tick = progress or (lambda _s, _d, _t: None)
    name = check_name(cfg.name if cfg.name is not None else clip_name(src), "--name")
    final = Path(out_dir) / name
    check_output_folder(out_dir, "-o")
    if cfg.force:
        check_replaceable(final, "--force", "scene folder", SCENE_MARKERS)
    elif final.exists() or final.is_symlink():
        raise UserError(f"{final}: exists; pass --force to replace it")
    _refuse_scene_options(cfg)
    timer = StageClock()
    warnings: list[str] = []

    def warn(msg: str) -> None:
        warnings.append(msg)
        log(f"warning: {msg}")

    # A failed import also removes the -o folders it made (nothing is left but what existed before).
    with remove_new_folders_on_failure(out_dir):
        return _import(src, final, clip_cfg=cfg, timer=timer, warn=warn, warnings=warnings, tick=tick)


def _import(src: Path, final: Path, clip_cfg, timer: StageClock, warn, warnings: list[str], tick) -> Path:
    """:func:`import_clip` once the names and options are checked."""
    cfg, vcfg = clip_cfg, clip_cfg.video
    with timer.stage("read"):
        clip = read_clip(src, vcfg, cfg.size, lambda d, n: tick("reading frames", d, n))
    T, H, W = clip.frames.shape[:3]
    if min(W, H) < MIN_SIZE:
        raise UserError(
            f"{src}: frames of {W}x{H} are smaller than {MIN_SIZE}x{MIN_SIZE}; use a larger --size"
        )
    if clip.truncated:
        warn(f"kept the first {T} frames (--video-max-frames {vcfg.max_frames}); the clip has more")
    try:
        with atomic_dir(final, force=cfg.force) as tmp:
            masks = None
            if vcfg.mask_moving:
                with timer.stage("masks"):
                    masks = moving_masks(clip.frames, lambda d, n: tick("moving-pixel masks", d, n))
            with timer.stage("sfm"):
                cams = clip_sfm(clip.frames, masks, tmp / SFM_WORK, vcfg.sfm_threads, vcfg.seed, tick)
            shutil.rmtree(tmp / SFM_WORK)
            registered = np.zeros(T, bool) if cams is None else cams.registered
            keep = _registered(src, clip, registered, vcfg, warn)
            with timer.stage("write"):
                record = _write_scene(tmp, clip, cams, keep, masks, tick)
            with timer.stage("hash"):
                files = hash_files(tmp)
            record.update(_manifest(src, clip, cfg, cams, keep, masks))
            record["timings_s"] = {k: round(v, 3) for k, v in timer.stages_s.items()}
            record["warnings"] = warnings
            write_manifest(tmp, record, files)
    except FileExistsError:
        raise UserError(f"{final}: appeared while importing; pass --force to replace it") from None
    return final


def _refuse_scene_options(cfg) -> None:
    """Options of a scene-folder import that mean nothing for a clip: refused, not silently ignored."""
    given = [
        flag
        for flag, v in (
            ("--test-images", cfg.test_images), ("--test-masks", cfg.test_masks), ("--test-row", cfg.test_row),
        )
        if v is not None
    ]  # fmt: skip
    if cfg.layout != "auto":
        given.append("--layout")
    if cfg.no_poses:
        given.append("--no-poses")
    if cfg.normalize not in ("auto", "rig"):
        given.append("--normalize")
    if given:
        raise UserError(
            f"{given[0]}: a video or frames folder is imported with SfM poses and no test views; drop {given[0]}"
        )


def _registered(src: Path, clip: Clip, registered: np.ndarray, vcfg, warn) -> np.ndarray:
    """Indices of the frames kept in the scene (the registered ones); the one-line errors of too few."""
    T = len(registered)
    n = int(registered.sum())
    if n < vcfg.min_registered * T or n < 2:
        raise UserError(
            f"{src}: SfM registered {n} of {T} frames ({100 * n / T:.0f} %, under --video-min-registered "
            f"{vcfg.min_registered:g}); try a larger --video-stride (more parallax), a larger --size, or a clip "
            "with more camera motion and texture"
        )
    missing = [clip.source_index[t] for t in np.flatnonzero(~registered)]
    if missing:
        listing = ", ".join(str(i) for i in missing[:20]) + (" ..." if len(missing) > 20 else "")
        if vcfg.unregistered == "fail":
            raise UserError(
                f"{src}: SfM did not register {len(missing)} of {T} frames (source frames {listing}); "
                "use --video-unregistered drop to leave them out"
            )
        warn(f"SfM did not register {len(missing)} of {T} frames; dropped (source frames {listing})")
    return np.flatnonzero(registered)


def _write_scene(tmp: Path, clip: Clip, cams, keep: np.ndarray, masks, tick) -> dict:
    """Frames, cameras and preview of the registered frames, in the rig world frame; returns the manifest's
    camera record (the world transform, bounds, intrinsics)."""
    T, H, W = len(keep), clip.frames.shape[1], clip.frames.shape[2]
    w2cs_sfm = cams.w2cs[keep]
    remap = {int(t): k for k, t in enumerate(keep)}
    sel = np.isin(cams.obs_frame, keep)
    obs_p, obs_f = cams.obs_point[sel], np.array([remap[int(t)] for t in cams.obs_frame[sel]], np.int64)
    bounds, depths = frame_bounds(cams.points, obs_p, obs_f, w2cs_sfm)
    s, R, t = rig_similarity(w2cs_sfm, depths[depths > 0])
    w2cs = apply_similarity(w2cs_sfm, s, R, t)
    bounds = bounds * s
    undistort = Undistorter(cams.K, cams.dist, (W, H), (W, H))
    K = undistort.K_out
    for k in range(T):
        why = camera_problem(K, w2cs[k], W, H)
        if why is not None:  # pragma: no cover - SfM poses are rotations; a guard against a broken model
            raise UserError(f"{clip.path}: SfM camera of frame {clip.source_index[keep[k]]}: {why}")
    thumbs, masked = [], []
    show = set(np.unique(np.round(np.linspace(0, T - 1, min(8, T))).astype(int)).tolist())
    for k, f in enumerate(keep):
        img = undistort(clip.frames[f])
        save_image(tmp / frame_file(k), img)
        if k in show:
            label = f"t{k} src{clip.source_index[f]}"
            thumbs.append((label, img))
            if masks is not None:  # the second row shows which pixels SfM left out (tinted red)
                masked.append((f"t{k} moving", img, undistort(masks[f].astype(np.uint8) * 255) > 127))
        tick("writing frames", k + 1, T)
    # Camera 1 stands for the test camera a benchmark scene has; a clip has none, so it is frame 0's pose
    # (readers that draw or look up the test camera keep working) and no test frame uses it.
    ids = list(range(1, T + 2))
    Ks = np.tile(K, (T + 1, 1, 1))
    all_w2cs = np.concatenate([w2cs[:1], w2cs])
    all_bounds = np.concatenate([bounds[:1], bounds])
    buf = io.BytesIO()
    np.save(buf, llff.opencv_to_llff(all_w2cs, Ks, H, W, all_bounds))
    atomic_write_bytes(tmp / "poses_bounds.npy", buf.getvalue())
    world = {
        "scale": s,
        "R": R.tolist(),
        "t": t.tolist(),
        "mode": "rig",
        "note": "world = scale * R @ sfm + t",
    }
    doc = cameras_document(
        width=W, height=H, cameras=ids, test_camera=1, Ks=Ks, w2cs=all_w2cs, bounds=all_bounds,
        frame_cameras=list(range(2, T + 2)), source_times=[clip.source_index[f] for f in keep], has_masks=False,
        world_transform=world,
    )  # fmt: skip
    doc["test_frames"] = []  # cameras_document lists a test view per time; a clip has none
    atomic_write_json(tmp / "cameras.json", doc)
    save_image(tmp / "preview.png", contact_sheet(thumbs, masked))
    return {
        "world_transform": world,
        "near_far": [float(all_bounds[:, 0].min()), float(all_bounds[:, 1].max())],
    }


def _manifest(src: Path, clip: Clip, cfg, cams, keep: np.ndarray, masks) -> dict:
    """``manifest.json``'s record of a clip import (without the camera record, timings, warnings, hashes)."""
    T = len(keep)
    H, W = clip.frames.shape[1:3]
    dropped = [clip.source_index[t] for t in np.flatnonzero(~cams.registered)]
    cfg_record = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items()}
    masked = None
    if masks is not None:
        frac = masks.reshape(len(masks), -1).mean(1)
        masked = {"method": "epipolar error of DIS flow, F by LMedS (worldtree.priors)",
                  "mean_fraction": float(frac.mean()), "max_fraction": float(frac.max()),
                  "frames_masked": int((frac > 0).sum())}  # fmt: skip
    return {
        "tool": "nvls import",
        "tool_version": __version__,
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "source": {
            "path": str(src.resolve()),
            "layout": clip.kind,
            "source_frames": clip.source_count,
            "time_steps": clip.source_count,  # the key `nvls info` reads
            "kept_frames": len(clip.source_index),
            "fps": clip.fps,
            "width": clip.source_size[0],
            "height": clip.source_size[1],
        },  # fmt: skip
        "source_times": [clip.source_index[f] for f in keep],
        "image_size": [int(W), int(H)],
        "test_camera": 1,
        "camera_order": list(range(2, T + 2)),
        "counts": {"frames": T, "test_frames": 0, "masks": 0, "cameras": T + 1},
        "poses": {
            "method": "sfm",
            "tool": "pycolmap",
            "camera_model": "SIMPLE_RADIAL (one shared camera)",
            "matching": "sequential",
            "registered": int(cams.registered.sum()),
            "kept_frames": len(cams.registered),
            "dropped_source_frames": dropped,
            "num_points": len(cams.points),
            "reprojection_error_px": cams.reprojection_error,
            "focal_guess_px": cams.focal_guess,
            "intrinsics": cams.K.tolist(),
            "distortion": cams.dist.tolist(),
            "feature_masks": masked,
            "test_camera": "placeholder at frame 0's pose: a clip has no test views",
        },  # fmt: skip
        "masks": {"method": "none"},
        "config": cfg_record,
    }
