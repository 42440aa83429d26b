"""Build one NVIDIA-LS scene from a raw rig capture (the library behind ``nvls build``).

Stages: index the raw layout -> sample time steps -> rig poses (SfM on one time step, or an LLFF file) ->
normalise the world -> undistort/resize every needed frame -> test masks (background model or imported) ->
write images, cameras.json, poses_bounds.npy, preview.png, manifest.json into a temporary folder that is
renamed into place at the end.
"""

from __future__ import annotations

import io
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from nvidia_ls import llff
from nvidia_ls.layouts import RawCapture, open_raw
from nvidia_ls.manifest import hash_files, write_manifest
from nvidia_ls.masks import MaskConfig, background_masks, import_masks
from nvidia_ls.preview import contact_sheet
from nvidia_ls.sampling import pingpong, sample_times, training_cameras
from nvidia_ls.sfm import CAMERA_MODELS, run_sfm, sfm_candidates
from nvidia_ls.undistort import Undistorter
from nvidia_ls.world_frame import apply_similarity, rig_similarity
from nvidia_ls.writer import cameras_document, frame_file, mask_file, save_image, test_file
from worldtree import __version__
from worldtree.imageio import check_pixels
from worldtree.infra.atomic import atomic_dir, atomic_write_bytes, atomic_write_json, remove_stale_partials
from worldtree.infra.errors import SettingError, UserError
from worldtree.infra.folder_lock import FolderLock, lock_paths
from worldtree.infra.output_paths import (
    check_name,
    check_output_folder,
    check_replaceable,
    remove_new_folders_on_failure,
)
from worldtree.infra.timing import StageClock
from worldtree.losses import SSIM_WINDOW

NORMALIZE = ("auto", "rig", "none")
#: Ways of making the monocular training video and its test view from the rig (BuildConfig.protocol).
PROTOCOLS = ("nvidia-ls", "classic")
# Smallest stored image side: training's SSIM loss needs its whole window inside the image.
MIN_SIZE = SSIM_WINDOW


@dataclass
class BuildConfig:
    """Options of ``nvls build`` (one source of defaults)."""

    frames: int = 160
    """Keep at most this many time steps (uniformly sampled when the capture is longer)."""
    test_camera: int = 1
    """Rig camera of the test view (never a training frame, except frame 0 under the classic protocol)."""
    protocol: str = "nvidia-ls"
    """"nvidia-ls": the test camera held out, the others in ping-pong order over up to --frames time steps;
    "classic": the 12-frame protocol of DynamicNeRF, NSFF and MoSca: the first N time steps (N the rig's
    cameras, at most --frames), frame t from the t-th camera in id order starting at the test camera, so that
    the test view at t = 0 is training frame 0."""
    masks: Path | None = None
    """Folder of imported test-camera masks (by source time: %05d/camNN.png or %05d.png); None = background model."""
    poses: Path | None = None
    """LLFF poses_bounds.npy of the rig cameras; skips SfM."""
    size: tuple[int, int] | None = None
    """Output (width, height); None keeps the raw size."""
    camera_model: str = "shared"
    """SfM intrinsics: "shared" (one SIMPLE_RADIAL for all cameras) or "per-camera"."""
    sfm_tries: int = 8
    """Number of time steps tried for SfM (the first, then spread over the sequence)."""
    sfm_threads: int = 1
    """CPU threads given to pycolmap; 1 makes SfM bit-reproducible (2 is faster but varies run to run)."""
    normalize: str = "auto"
    """World frame: "rig" (axes of the mean camera, origin at the mean camera centre, median SfM point depth 1),
    "none" (keep the SfM / --poses frame), "auto" (rig for SfM, none for --poses)."""
    num_cameras: int | None = None
    """Expected rig size; None = the highest camera number found."""
    name: str | None = None
    """Scene folder name; None = the raw folder's name (its parent's when it is called "dense")."""
    force: bool = False
    """Replace an existing output folder."""
    seed: int = 0
    """Seed of the SfM mapper."""
    mask: MaskConfig = field(default_factory=MaskConfig)
    """Background-model mask settings."""
    preview_frames: int = 8
    """Thumbnails per row of preview.png."""

    def check(self) -> None:
        if self.name is not None:
            check_name(self.name, "--name")
        if self.frames < 1:
            raise SettingError.of_field(self, "frames", "must be at least 1")
        for name, choices in (("camera_model", CAMERA_MODELS), ("normalize", NORMALIZE), ("protocol", PROTOCOLS)):
            if getattr(self, name) not in choices:
                raise SettingError.of_field(
                    self, name, f"choose one of {', '.join(choices)}", shown=repr(getattr(self, name))
                )
        if self.size is not None and min(self.size) < MIN_SIZE:
            raise SettingError.of_field(
                self, "size", f"too small for the {MIN_SIZE}x{MIN_SIZE} SSIM window of training; give WxH of "
                f"at least {MIN_SIZE}x{MIN_SIZE}", shown=f"{self.size[0]}x{self.size[1]}",
            )  # fmt: skip
        for name, least in (("test_camera", 1), ("sfm_tries", 1), ("sfm_threads", 1), ("num_cameras", 2),
                            ("seed", 0), ("preview_frames", 1)):  # fmt: skip
            if getattr(self, name) is not None and getattr(self, name) < least:
                raise SettingError.of_field(self, name, f"must be at least {least}")
        self.mask.check()


# Files every scene folder written by `nvls build` / `nvls import` holds: --force replaces only such a folder.
SCENE_MARKERS = ("manifest.json", "cameras.json")


def parse_size(text: str | None) -> tuple[int, int] | None:
    """``"480x270"`` -> ``(480, 270)``; None stays None."""
    if text is None:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise UserError(f"--size {text!r}: expected WxH, e.g. 480x270") from None
    if w < 1 or h < 1:
        raise UserError(f"--size {text}: width and height must be positive, e.g. 480x270")
    check_pixels(w, h, f"--size {text}")  # before any image is read or resized to it
    return w, h


def scene_name(raw_dir: Path, cfg: BuildConfig) -> str:
    if cfg.name:
        return cfg.name
    raw_dir = raw_dir.resolve()
    return raw_dir.parent.name if raw_dir.name in ("dense", "mv_images") else raw_dir.name


def _point_depths(points: np.ndarray, obs_p: np.ndarray, obs_c: np.ndarray, w2cs: np.ndarray) -> np.ndarray:
    cam = np.einsum("nij,nj->ni", w2cs[obs_c, :3, :3], points[obs_p]) + w2cs[obs_c, :3, 3]
    return cam[:, 2]


def build_scene(
    raw_dir: str | Path,
    out_dir: str | Path,
    cfg: BuildConfig | None = None,
    log: Callable[[str], None] | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> Path:
    """Build ``out_dir/<name>/`` from the raw capture in ``raw_dir``.

    Args:
        raw_dir: one scene's raw folder (any layout of :mod:`nvidia_ls.layouts`).
        out_dir: parent folder of the scene folder.
        cfg: options (defaults: :class:`BuildConfig`).
        log: optional callable receiving warnings and notes (one line each).
        progress: optional callable ``(stage, done, total)``.

    Returns:
        The scene folder. Raises :class:`UserError` for bad input; nothing is left half-written.
    """
    cfg = cfg or BuildConfig()
    cfg.check()
    check_output_folder(out_dir, "-o")
    raw_dir = Path(raw_dir)
    final = Path(out_dir) / check_name(scene_name(raw_dir, cfg), "--name")
    if cfg.force:
        check_replaceable(final, "--force", "scene folder", SCENE_MARKERS)
    # One builder per scene folder; a failed build removes the -o folders it made (and its lock files there).
    leftovers = tuple(p.name for p in lock_paths(final))
    with remove_new_folders_on_failure(out_dir, leftovers), FolderLock(final, "scene"):
        for stale in remove_stale_partials(final):
            (log or print)(f"removed {stale}, left by an interrupted build")
        return _build(raw_dir, final, cfg, log, progress)


@dataclass
class _Plan:
    """What a build will write, decided (and checked) before anything is written."""

    raw: RawCapture
    train: list[int]
    """Training cameras (in the order frames use them)."""
    kept: list[int]
    """Source time steps kept, in order (frame ``i`` is source time ``kept[i]``)."""
    frame_cams: list[int]
    """Camera of each training frame (ping-pong over ``train``; ``train`` in order under the classic protocol)."""
    out_wh: tuple[int, int]
    """Output (width, height)."""


@dataclass
class _Poses:
    """Rig cameras (intrinsics, distortion, world-to-camera, near/far) and how they were found."""

    Ks: np.ndarray
    dists: np.ndarray
    w2cs: np.ndarray
    bounds: np.ndarray
    depths: np.ndarray
    """Depths of the SfM points (or one per camera from the bounds file), for the normalisation."""
    info: dict


def _build(
    raw_dir: Path,
    final: Path,
    cfg: BuildConfig,
    log: Callable[[str], None] | None,
    progress: Callable[[str, int, int], None] | None,
) -> Path:
    """:func:`build_scene` of ``final`` with its lock held."""
    say = log or (lambda _msg: None)
    tick = progress or (lambda _s, _d, _t: None)
    timer = StageClock()  # seconds per build step, for the manifest
    warnings: list[str] = []

    def warn(msg: str) -> None:
        warnings.append(msg)
        say(f"warning: {msg}")

    plan = _plan(raw_dir, final, cfg, warn, timer)
    with timer.stage("sfm"):
        poses = _rig_poses(plan.raw, cfg, say)
    world = _normalise(poses, cfg)
    undist = _undistorters(plan, poses)
    masks, mask_info = None, {}
    if cfg.masks is not None:  # imported masks are checked before any frame is processed
        with timer.stage("masks"):
            masks = import_masks(cfg.masks, plan.kept, cfg.test_camera, *plan.out_wh)
        mask_info = {"method": "imported", "source": str(Path(cfg.masks).resolve())}
    try:
        with atomic_dir(final, force=cfg.force) as tmp:
            test_frames, thumbs = _write_frames(tmp, plan, undist, cfg, timer, tick)
            with timer.stage("masks"):
                if masks is None:
                    masks = background_masks(test_frames, cfg.mask)
                    mask_info = {"method": "background-median", **asdict(cfg.mask)}
            with timer.stage("write"):
                _write_cameras(tmp, plan, poses, np.stack([u.K_out for u in undist]), masks, world, cfg)
                sheet = contact_sheet(
                    [(f"t{i} cam{plan.frame_cams[i]:02d}", thumbs[i]) for i in sorted(thumbs)],
                    [(f"test t{i}", test_frames[i], masks[i]) for i in sorted(thumbs)],
                )
                save_image(tmp / "preview.png", sheet)
            with timer.stage("hash"):
                files = hash_files(tmp)
            record = _manifest(raw_dir, plan, poses, mask_info, world, cfg)
            record["timings_s"] = {k: round(v, 4) for k, v in timer.stages_s.items()}
            record["warnings"] = warnings
            write_manifest(tmp, record, files)
    except FileExistsError:
        raise UserError(f"{final}: appeared while building; pass --force to replace it") from None
    return final


def _plan(raw_dir: Path, final: Path, cfg: BuildConfig, warn: Callable[[str], None], timer: StageClock) -> _Plan:
    """Index the raw capture, sample its time steps and check the output size against it."""
    with timer.stage("index"):
        raw: RawCapture = open_raw(raw_dir, cfg.num_cameras)
    for w in raw.warnings:
        warn(w)
    if (final.exists() or final.is_symlink()) and not cfg.force:
        raise UserError(f"{final}: already exists; pass --force to replace it")
    train = training_cameras(raw.cameras, cfg.test_camera)  # also checks the test camera is in the rig
    if cfg.protocol == "classic":
        # Frame t is the t-th camera from the test camera on (wrapping), at consecutive time steps.
        i = raw.cameras.index(cfg.test_camera)
        train = raw.cameras[i:] + raw.cameras[:i]
        n = min(cfg.frames, len(train))
        if len(raw.times) < n:
            warn(f"only {len(raw.times)} time steps available, fewer than the {n} frames of the classic protocol")
        kept = list(raw.times[:n])
        frame_cams = train[: len(kept)]
    else:
        kept = sample_times(raw.times, cfg.frames)
        if len(raw.times) < cfg.frames:
            warn(f"only {len(raw.times)} time steps available, fewer than --frames {cfg.frames}; keeping all")
        frame_cams = pingpong(train, len(kept))
    out_wh = cfg.size or (raw.width, raw.height)
    if min(out_wh) < MIN_SIZE:
        raise UserError(
            f"{raw_dir}: images of {out_wh[0]}x{out_wh[1]} are smaller than {MIN_SIZE}x{MIN_SIZE}, the "
            "SSIM window of training; use larger images"
        )
    if abs(out_wh[0] / out_wh[1] - raw.width / raw.height) > 0.01 * raw.width / raw.height:
        raise UserError(
            f"--size {out_wh[0]}x{out_wh[1]}: aspect differs from the raw {raw.width}x{raw.height}; keep the aspect"
        )
    return _Plan(raw, train, kept, frame_cams, out_wh)


def _rig_poses(raw: RawCapture, cfg: BuildConfig, say: Callable[[str], None]) -> _Poses:
    """The rig's cameras from the ``--poses`` file, or from SfM on one time step (near/far from its points)."""
    n = len(raw.cameras)
    if cfg.poses is not None:
        Ks, w2cs, bounds = llff.load_poses_bounds(cfg.poses, n, raw.width, raw.height)
        info = {"method": "file", "file": str(Path(cfg.poses).resolve())}
        return _Poses(Ks, np.zeros((n, 5)), w2cs, bounds, np.sqrt(bounds[:, 0] * bounds[:, 1]), info)
    res = run_sfm(
        raw, sfm_candidates(raw.times, cfg.sfm_tries), cfg.camera_model, cfg.sfm_threads, cfg.seed, log=say
    )
    depths = _point_depths(res.points, res.obs_point, res.obs_cam, res.w2cs)
    bounds = np.zeros((n, 2))
    for i in range(n):
        d = depths[(res.obs_cam == i) & (depths > 0)]
        if d.size < 5:  # too few own points for percentiles: use the whole reconstruction's
            d = depths[depths > 0]
        if d.size == 0:
            raise UserError("SfM triangulated no points in front of the cameras; pass --poses FILE")
        bounds[i] = [0.9 * np.percentile(d, 1), 1.1 * np.percentile(d, 99)]
    info = {
        "method": "sfm",
        "tool": "pycolmap",
        "camera_model": cfg.camera_model,
        "sfm_time": res.time,
        "tried_times": res.tried,
        "num_points": len(res.points),
        "reprojection_error_px": res.reprojection_error,
        "distortion": res.dists.tolist(),
        "raw_intrinsics": res.Ks.tolist(),
    }
    return _Poses(res.Ks, res.dists, res.w2cs, bounds, depths, info)


def _normalise(poses: _Poses, cfg: BuildConfig) -> dict:
    """Move ``poses`` into the world frame of ``--normalize`` (in place); returns the transform's record."""
    mode = cfg.normalize if cfg.normalize != "auto" else ("none" if cfg.poses is not None else "rig")
    if mode == "rig":
        s, R, t = rig_similarity(poses.w2cs, poses.depths[poses.depths > 0])
        poses.w2cs = apply_similarity(poses.w2cs, s, R, t)
        poses.bounds = poses.bounds * s
    else:
        s, R, t = 1.0, np.eye(3), np.zeros(3)
    poses.info["normalize"] = mode
    return {"scale": s, "R": R.tolist(), "t": t.tolist(), "mode": mode, "note": "world = scale * R @ sfm + t"}


def _undistorters(plan: _Plan, poses: _Poses) -> list[Undistorter]:
    """One undistort/resize map per rig camera (cameras sharing a model share one remap table)."""
    raw = plan.raw
    tables: dict[tuple, Undistorter] = {}
    undist: list[Undistorter] = []
    for i in range(len(raw.cameras)):
        key = (tuple(np.round(poses.Ks[i].ravel(), 9)), tuple(np.round(poses.dists[i], 12)))
        if key not in tables:
            tables[key] = Undistorter(poses.Ks[i], poses.dists[i], (raw.width, raw.height), plan.out_wh)
        undist.append(tables[key])
    return undist


def _write_frames(tmp: Path, plan: _Plan, undist: list[Undistorter], cfg: BuildConfig, timer: StageClock, tick):
    """Undistort and write every training frame and test view; returns the test views ``[T, H, W, 3]`` (for
    the background masks) and the preview's training thumbnails by frame."""
    raw, kept, T = plan.raw, plan.kept, len(plan.kept)
    test_frames = np.zeros((T, plan.out_wh[1], plan.out_wh[0], 3), np.uint8)
    thumbs_idx = set(np.unique(np.round(np.linspace(0, T - 1, min(cfg.preview_frames, T))).astype(int)))
    thumbs: dict[int, np.ndarray] = {}
    time_pos = {s_: i for i, s_ in enumerate(kept)}
    for k, cid in enumerate(raw.cameras):
        test = cid == cfg.test_camera
        own = {kept[i] for i in range(T) if plan.frame_cams[i] == cid}  # its training frames (classic: frame 0)
        need = kept if test else [t for t in kept if t in own]
        it = raw.iter_frames(cid, need)
        while True:
            with timer.stage("read"):
                item = next(it, None)
            if item is None:
                break
            src_t, img = item
            with timer.stage("undistort"):
                img = undist[k](img)
            ti = time_pos[src_t]
            names = ([test_file(ti)] if test else []) + ([frame_file(ti)] if src_t in own else [])
            if test:
                test_frames[ti] = img
            if src_t in own and ti in thumbs_idx:
                thumbs[ti] = img
            with timer.stage("write"):
                for name in names:
                    save_image(tmp / name, img)
        tick("frames", k + 1, len(raw.cameras))
    return test_frames, thumbs


def _write_cameras(tmp: Path, plan: _Plan, poses: _Poses, K_out: np.ndarray, masks, world: dict, cfg) -> None:
    """The test masks, ``poses_bounds.npy`` (LLFF) and ``cameras.json`` of the output images."""
    T = len(plan.kept)
    for ti in range(T):
        save_image(tmp / mask_file(ti), masks[ti])
    pb = llff.opencv_to_llff(poses.w2cs, K_out, plan.out_wh[1], plan.out_wh[0], poses.bounds)
    buf = io.BytesIO()
    np.save(buf, pb)
    atomic_write_bytes(tmp / "poses_bounds.npy", buf.getvalue())
    doc = cameras_document(
        width=plan.out_wh[0], height=plan.out_wh[1], cameras=plan.raw.cameras, test_camera=cfg.test_camera,
        Ks=K_out, w2cs=poses.w2cs, bounds=poses.bounds, frame_cameras=plan.frame_cams, source_times=plan.kept,
        has_masks=True, world_transform=world,
    )  # fmt: skip
    atomic_write_json(tmp / "cameras.json", doc)


def _manifest(raw_dir: Path, plan: _Plan, poses: _Poses, mask_info: dict, world: dict, cfg: BuildConfig) -> dict:
    """``manifest.json``'s record of the build (without timings, warnings and the file hashes)."""
    raw, T = plan.raw, len(plan.kept)
    cfg_record = asdict(cfg)
    for key in ("masks", "poses"):
        cfg_record[key] = None if cfg_record[key] is None else str(cfg_record[key])
    return {
        "tool": "nvls build",
        "tool_version": __version__,
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "source": {
            "path": str(raw_dir.resolve()),
            "layout": raw.layout,
            "root": str(raw.root),
            "cameras": raw.cameras,
            "time_steps": len(raw.times),
            "width": raw.width,
            "height": raw.height,
        },
        "source_times": plan.kept,
        "image_size": list(plan.out_wh),
        "test_camera": cfg.test_camera,
        "protocol": cfg.protocol,
        "train_cameras": plan.train,
        "camera_order": plan.frame_cams,
        "counts": {"frames": T, "test_frames": T, "masks": T, "cameras": len(raw.cameras)},
        "poses": poses.info,
        "masks": mask_info,
        "world_transform": world,
        "config": cfg_record,
    }
