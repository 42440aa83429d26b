"""`nvls import`: a scene prepared for other dynamic-view-synthesis codes -> this project's scene format.

Two source layouts (docs/nvidia_ls.md, "Importing"):

- ``dynamicnerf`` -- the layout DynamicNeRF / NSFF / MoSca ship the NVIDIA short protocol in: ``images/``
  (training frame t, sorted by name), LLFF ``poses_bounds.npy`` with one row per training frame, MiDaS
  ``disp/*.npy`` (relative inverse depth), flow ``flow/NNN_fwd.npz`` (frame i -> i+1) / ``NNN_bwd.npz``
  (i -> i-1) or ``flow_raft/<i>_<j>.npy`` (i -> j), ``motion_masks/`` (one mask per frame, white = moving),
  and test views ``v000_tXXX.png`` (in ``gt/``, ``gt_images/``, ``test/`` or the scene folder). The test camera
  is the camera of one training frame (``test_row``, 0 in the 12-frame protocol), so its pose is that row.
- ``nvidia-ls`` -- the paper's release: ``images/``, ``poses_bounds.npy``, ``gt_images/v001_tXXX.png`` and
  ``sam_results/masks/v001_tXXX.png``. ``poses_bounds.npy`` may hold one row per training frame plus one for
  the test camera (row ``test_row``, default 0), or one row per rig camera in id order (camera 1 = test, the
  frames use cameras 2..N in ping-pong order).

Written: ``images/``, ``gt_images/``, ``masks/`` (when test masks exist), ``cameras.json``, ``poses_bounds.npy``
(one row per camera id), ``preview.png``, ``manifest.json``, and the network priors found, at the scene's
size, under ``imported/`` (``disp/`` or ``depth/``, ``flow/<i>_<j>.npy``, ``masks/``) with ``imported.json``
naming the ``wtbench run`` options that use them. The world frame (``--normalize``): by default the rig frame
of ``nvidia_ls.world_frame`` (mean camera at the origin with its axes, median scene depth 1, the depth taken
as each camera's ``sqrt(near * far)``), so the methods' absolute constants act as on the generated scenes;
``none`` keeps the file's frame. Imported metric depth maps follow the world's scale; ``world_transform`` in
``cameras.json`` and ``manifest.json`` records the similarity.
"""

from __future__ import annotations

import io
import re
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from nvidia_ls import llff
from nvidia_ls.manifest import hash_files, write_manifest
from nvidia_ls.preview import contact_sheet
from nvidia_ls.sampling import pingpong
from nvidia_ls.scene_checks import (
    camera_problem,
    depth_map_problem,
    flow_problem,
    read_pose_rows,
    rotation_problem,
)
from nvidia_ls.video_frames import VideoConfig
from nvidia_ls.world_frame import apply_similarity, rig_similarity
from nvidia_ls.writer import cameras_document, frame_file, mask_file, save_image, test_file
from worldtree import __version__
from worldtree.imageio import read_image, read_mask
from worldtree.infra.atomic import atomic_dir, atomic_write_bytes, atomic_write_json
from worldtree.infra.errors import SettingError, UserError
from worldtree.infra.output_paths import check_name, check_output_folder, check_replaceable
from worldtree.priors.imported import _load_array, read_flo, resize_flow

LAYOUTS = ("auto", "dynamicnerf", "nvidia-ls")
NORMALIZE = ("auto", "rig", "none")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
IMPORTED = "imported"
"""Folder of the imported priors inside the written scene."""
_TEST_NAME = re.compile(r"^v(\d+)_t(\d+)$")
_FWD_BWD = re.compile(r"^(\d+)_(fwd|bwd)$")
_PAIR = re.compile(r"^(\d+)[_-](\d+)$")


@dataclass(frozen=True)
class ImportConfig:
    """Settings of `nvls import` (the CLI's defaults)."""

    layout: str = "auto"
    """auto | dynamicnerf | nvidia-ls (auto: nvidia-ls when gt_images/ holds v001_* views)."""
    size: tuple[int, int] | None = None
    """Output (W, H), same aspect as the images; None keeps the images' size."""
    test_row: int | None = None
    """Row of poses_bounds.npy holding the test camera (None: 0, see the module docstring)."""
    test_images: Path | None = None
    """Folder of the test views (vNNN_tXXX.png); None looks in the layout's usual places."""
    test_masks: Path | None = None
    """Folder of test-view dynamic masks named like the views; None looks in the layout's usual places."""
    name: str | None = None
    """Scene folder name (default: the source folder's name)."""
    no_poses: bool = False
    """A monocular clip without poses_bounds.npy: every frame gets the identity pose and a guessed focal
    length (1.2 x the larger image side), recorded as ``poses.method = "none"``. Enough for 2D priors (flow,
    tracks, masks from the epipolar error of flow with estimated fundamental matrices: ``wtbench prep
    --epi-from-flow``), not for training a 3D method."""
    normalize: str = "auto"
    """World frame: "rig" (mean camera at the origin with its axes, median depth ``sqrt(near * far)`` over the
    cameras scaled to 1), "none" (the file's LLFF frame as is), "auto" (rig, none with ``no_poses``)."""
    force: bool = False
    """Replace an existing scene folder."""
    video: VideoConfig = field(default_factory=VideoConfig)
    """A video file or a folder of frames (no poses): how its cameras are estimated (nvidia_ls.video_import)."""


@dataclass
class _Source:
    """What was found in the source folder."""

    layout: str
    images: list[Path]
    pb: np.ndarray
    test_views: dict[int, Path]
    test_masks: dict[int, Path]
    depth_dir: Path | None
    depth_kind: str
    flow: dict[tuple[int, int], Path]
    motion_masks: list[Path]


# ------------------------------------------------------------------------------------------------ reading
def _images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def _views(folder: Path) -> dict[int, Path]:
    """``{time: path}`` of the ``vNNN_tXXX`` images in ``folder`` (one view index; the lowest if several)."""
    found: dict[int, dict[int, Path]] = {}
    for p in _images(folder) if folder.is_dir() else []:
        m = _TEST_NAME.match(p.stem)
        if m:
            found.setdefault(int(m.group(1)), {})[int(m.group(2))] = p
    return found[min(found)] if found else {}


def _detect_layout(root: Path) -> str:
    if _views(root / "gt_images") and (root / "sam_results").is_dir():
        return "nvidia-ls"
    if any((root / d).is_dir() for d in ("disp", "flow", "flow_raft", "motion_masks")):
        return "dynamicnerf"
    if _views(root / "gt_images"):
        return "nvidia-ls"
    return "dynamicnerf"


def _flow_files(root: Path) -> dict[tuple[int, int], Path]:
    out: dict[tuple[int, int], Path] = {}
    fdir = root / "flow"
    if fdir.is_dir():
        for p in sorted(fdir.iterdir()):
            m = _FWD_BWD.match(p.stem)
            if m and p.suffix in (".npz", ".npy"):
                i = int(m.group(1))
                out[(i, i + 1) if m.group(2) == "fwd" else (i, i - 1)] = p
    rdir = root / "flow_raft"
    if rdir.is_dir():
        for p in sorted(rdir.iterdir()):
            m = _PAIR.match(p.stem)
            if m and p.suffix.lower() in (".npy", ".flo"):
                out.setdefault((int(m.group(1)), int(m.group(2))), p)
    return out


def scan_source(root: Path, cfg: ImportConfig) -> _Source:
    """Find the files of a DynamicNeRF / NVIDIA-LS scene folder; raises :class:`UserError` naming what is
    missing."""
    if not root.is_dir():
        raise UserError(f"{root}: no such folder; give a scene folder holding images/ and poses_bounds.npy")
    if cfg.layout not in LAYOUTS:
        raise SettingError.of_field(
            cfg, "layout", f"choose one of {', '.join(LAYOUTS)}", shown=repr(cfg.layout)
        )
    if cfg.normalize not in NORMALIZE:
        raise SettingError.of_field(
            cfg, "normalize", f"choose one of {', '.join(NORMALIZE)}", shown=repr(cfg.normalize)
        )
    layout = _detect_layout(root) if cfg.layout == "auto" else cfg.layout
    if not (root / "images").is_dir() or not _images(root / "images"):
        raise UserError(f"{root / 'images'}: missing or holds no .png/.jpg; the training frames go there")
    images = _images(root / "images")
    pb_path = root / "poses_bounds.npy"
    if cfg.no_poses:
        return _Source(layout, images, _identity_rows(images), {}, {}, None, "disparity", {}, [])
    if not pb_path.is_file():
        raise UserError(
            f"{pb_path}: missing; the LLFF poses of the frames are needed (a clip without poses: --no-poses)"
        )
    pb = read_pose_rows(pb_path)

    if cfg.test_images is not None:
        views = _views(Path(cfg.test_images))
        if not views:
            raise UserError(f"--test-images {cfg.test_images}: no vNNN_tXXX.png/.jpg images there")
    else:
        places = ("gt_images",) if layout == "nvidia-ls" else ("gt", "gt_images", "test", ".")
        views = next((v for v in (_views(root / d) for d in places) if v), {})
    if cfg.test_masks is not None:
        tmasks = _views(Path(cfg.test_masks))
        if not tmasks:
            raise UserError(f"--test-masks {cfg.test_masks}: no vNNN_tXXX.png masks there")
    else:
        places = ("sam_results/masks", "masks", "gt_masks") if layout == "nvidia-ls" else ("gt_masks",)
        tmasks = next((v for v in (_views(root / d) for d in places) if v), {})

    depth_dir, kind = None, "disparity"
    for name, k in (("disp", "disparity"), ("depth", "depth")):
        if (root / name).is_dir():
            depth_dir, kind = root / name, k
            break
    motion = _images(root / "motion_masks") if (root / "motion_masks").is_dir() else []
    return _Source(layout, images, pb, views, tmasks, depth_dir, kind, _flow_files(root), motion)


def _identity_rows(images: list[Path]) -> np.ndarray:
    """LLFF rows of identity poses (OpenCV c2w = I) for a clip without poses; focal 1.2 x the larger side."""
    h, w = read_image(images[0]).shape[:2]
    f = 1.2 * max(w, h)
    rows = llff.opencv_to_llff(
        np.tile(np.eye(4), (len(images), 1, 1)), np.tile(np.diag([f, f, 1.0]), (len(images), 1, 1)), h, w,
        np.tile([[0.1, 100.0]], (len(images), 1)),
    )  # fmt: skip
    return rows


def _cameras(src: _Source, T: int, test_row: int | None, pb_path: Path):
    """``(rows of each camera id, camera id of each frame, test camera id, note)`` from the pose rows."""
    n = src.pb.shape[0]
    row = 0 if test_row is None else test_row
    if n == T:
        if not 0 <= row < n:
            raise UserError(f"--test-row {row}: {pb_path} has rows 0..{n - 1}")
        # Camera 1 is the test camera (a copy of the frame's row: the 12-frame protocol's test view is the
        # camera of training frame 0), frames use cameras 2..T+1.
        rows = {1: row} | {t + 2: t for t in range(T)}
        return rows, [t + 2 for t in range(T)], 1, f"one row per frame; test camera = row {row}"
    if n == T + 1:
        if not 0 <= row < n:
            raise UserError(f"--test-row {row}: {pb_path} has rows 0..{n - 1}")
        others = [r for r in range(n) if r != row]
        rows = {1: row} | {t + 2: r for t, r in enumerate(others)}
        return rows, [t + 2 for t in range(T)], 1, f"one row per frame plus the test camera (row {row})"
    if src.layout == "nvidia-ls" and 2 <= n < T and test_row in (None, 0):
        rows = {c + 1: c for c in range(n)}
        return rows, pingpong(list(range(2, n + 1)), T), 1, "one row per rig camera; frames ping-pong 2..N"
    raise UserError(
        f"{pb_path}: {n} pose rows for {T} frames; expected {T} (one per frame) or {T + 1} (plus the test "
        "camera, see --test-row)"
    )


def _read_flow_file(p: Path) -> np.ndarray:
    f = read_flo(p) if p.suffix.lower() == ".flo" else np.asarray(_load_array(p, ("flow",)))
    f = np.squeeze(f)
    if f.ndim == 3 and f.shape[0] == 2 and f.shape[-1] != 2:
        f = np.moveaxis(f, 0, -1)
    why = flow_problem(f)
    if why is not None:
        raise UserError(f"{p}: {why}; re-export the flow")
    return f.astype(np.float32)


def _check_aspect(shape_hw: tuple[int, int], W: int, H: int, path: Path, what: str) -> None:
    h, w = shape_hw
    if abs(w / h - W / H) > 0.01 * W / H:
        raise UserError(
            f"{path}: {what} is {w}x{h}, the scene is {W}x{H} (another aspect ratio); re-export it"
        )


def _resize_map(a: np.ndarray, W: int, H: int) -> np.ndarray:
    h, w = a.shape[:2]
    if (w, h) == (W, H):
        return a
    return cv2.resize(a, (W, H), interpolation=cv2.INTER_AREA if w > W else cv2.INTER_LINEAR)


# ------------------------------------------------------------------------------------------------ writing
@dataclass
class _Geometry:
    """The imported scene's size and cameras, checked before anything is written."""

    size0: tuple[int, int]
    """Source image (width, height)."""
    size: tuple[int, int]
    """Output (width, height)."""
    ids: list[int]
    """Camera ids in ``cameras.json`` order; ``Ks``, ``w2cs``, ``bounds`` follow it."""
    Ks: np.ndarray
    w2cs: np.ndarray
    bounds: np.ndarray
    frame_cams: list[int]
    test_cam: int
    pose_note: object
    world: dict
    """``world_transform`` record: ``world = scale * R @ source + t`` (``w2cs`` and ``bounds`` are in world)."""


def import_scene(
    source: str | Path, out_dir: str | Path, cfg: ImportConfig = ImportConfig(), log=print, progress=None
) -> Path:
    """Write ``out_dir/<name>/`` in the scene format from a DynamicNeRF / NVIDIA-LS folder ``source``, or from a
    video file or a folder of frames (cameras by SfM: :func:`nvidia_ls.video_import.import_clip`).

    Returns the scene folder. Everything is checked before anything is written, and the folder appears in
    one rename when complete (:func:`worldtree.infra.atomic.atomic_dir`).
    """
    from nvidia_ls.build import SCENE_MARKERS
    from nvidia_ls.video_import import import_clip, is_clip_source

    t0 = time.perf_counter()
    root = Path(source)
    if is_clip_source(root):
        return import_clip(root, out_dir, cfg, log=log, progress=progress)
    # The name first: a bad one is refused before the source is read and before anything is deleted.
    name = check_name(cfg.name if cfg.name is not None else root.resolve().name, "--name")
    final = Path(out_dir) / name
    check_output_folder(out_dir, "-o")  # -o FILE/sub: one line, not a traceback after the work
    if cfg.force:
        check_replaceable(final, "--force", "scene folder", SCENE_MARKERS)
    src = scan_source(root, cfg)
    geo = _geometry(root, src, cfg)
    times, has_tmasks, depth_files, warnings = _check_inputs(root, src)
    if (final.exists() or final.is_symlink()) and not cfg.force:
        raise UserError(f"{final}: exists; pass --force to replace it")
    try:
        with atomic_dir(final, force=cfg.force) as tmp:
            thumbs, test_thumbs = _write_images(tmp, src, geo, times, has_tmasks)
            record_priors = _write_priors(tmp, root, src, geo.size, depth_files, geo.world["scale"])
            world = geo.world
            _write_cameras(tmp, geo, len(src.images), has_tmasks, bool(times), world)
            save_image(tmp / "preview.png", contact_sheet(thumbs, test_thumbs))
            files = hash_files(tmp)
            record = _manifest(root, src, cfg, geo, times, has_tmasks, record_priors, world)
            record["timings_s"] = {"total": round(time.perf_counter() - t0, 3)}
            record["warnings"] = warnings
            write_manifest(tmp, record, files)
    except FileExistsError:
        raise UserError(f"{final}: appeared while importing; pass --force to replace it") from None
    for w in warnings:
        log(f"warning: {w}")
    return final


def _geometry(root: Path, src: _Source, cfg: ImportConfig) -> _Geometry:
    """Output size and cameras from the first image and ``poses_bounds.npy`` (hwf column, bounds and
    rotations checked)."""
    T = len(src.images)
    first = read_image(src.images[0])
    H0, W0 = first.shape[:2]
    W, H = cfg.size if cfg.size is not None else (W0, H0)
    _check_aspect((H0, W0), W, H, src.images[0], "the first image")
    pb_path = root / "poses_bounds.npy"
    rows, frame_cams, test_cam, pose_note = _cameras(src, T, cfg.test_row, pb_path)
    pb = src.pb.astype(np.float64)
    mat = pb[:, :15].reshape(-1, 3, 5)
    h_file, w_file = mat[:, 0, 4], mat[:, 1, 4]
    if (h_file <= 0).any() or (w_file <= 0).any() or (mat[:, 2, 4] <= 0).any():
        raise UserError(f"{pb_path}: non-positive H, W or focal length in the hwf column")
    if np.abs(w_file / h_file - W0 / H0).max() > 0.01 * W0 / H0:
        raise UserError(
            f"{pb_path}: stored size {int(w_file[0])}x{int(h_file[0])} has another aspect "
            f"than the {W0}x{H0} images; give the poses of these images"
        )
    bad = pb[:, 15] <= 0
    if bad.any() or (pb[:, 16] <= pb[:, 15]).any():
        raise UserError(f"{pb_path}: near/far bounds must satisfy 0 < near < far")
    ids = sorted(rows)
    for r in sorted(set(rows.values())):  # before inverting: a zero or non-rotation is refused, not inverted
        why = rotation_problem(mat[r, :, :3])
        if why is not None:
            raise UserError(f"{pb_path}: row {r}: {why}; check the file")
    Ks, w2cs, bounds = llff.llff_to_opencv(pb[[rows[c] for c in ids]], W, H)
    mode = cfg.normalize if cfg.normalize != "auto" else ("none" if cfg.no_poses else "rig")
    if mode == "rig":
        s, R, t = rig_similarity(w2cs, np.sqrt(bounds[:, 0] * bounds[:, 1]))
        w2cs, bounds = apply_similarity(w2cs, s, R, t), bounds * s
    else:
        s, R, t = 1.0, np.eye(3), np.zeros(3)
    # The cameras as written to cameras.json pass the very check `nvls verify` applies to them.
    for k, c in enumerate(ids):
        why = camera_problem(Ks[k], w2cs[k], W, H)
        if why is not None:
            raise UserError(f"{pb_path}: row {rows[c]} (camera {c}): {why}; check the file")
    world = {"scale": s, "R": R.tolist(), "t": t.tolist(), "mode": mode,
             "note": "world = scale * R @ source + t (source: the LLFF frame of poses_bounds.npy)"}  # fmt: skip
    return _Geometry((W0, H0), (W, H), ids, Ks, w2cs, bounds, frame_cams, test_cam, pose_note, world)


def _check_inputs(root: Path, src: _Source) -> tuple[list[int], bool, list[Path], list[str]]:
    """Test views, test masks, motion masks, depth maps and flow pairs against the frame count. Returns the
    test times, whether test masks are used, the depth files and the warnings."""
    T = len(src.images)
    warnings: list[str] = []
    times = sorted(src.test_views)
    if times and times != list(range(T)):
        raise UserError(
            f"{src.test_views[times[0]].parent}: test views for times {times[:3]}...{times[-1]}, expected one "
            f"per training time 0..{T - 1}"
        )
    if not times:
        warnings.append(
            "no test views (vNNN_tXXX.png) found: the scene trains and renders but cannot be scored; "
            "pass --test-images"
        )
    has_tmasks = bool(times) and bool(src.test_masks)
    if has_tmasks and sorted(src.test_masks) != times:
        raise UserError(
            f"{next(iter(src.test_masks.values())).parent}: test masks do not match the views' times"
        )
    if src.motion_masks and len(src.motion_masks) != T:
        raise UserError(
            f"{root / 'motion_masks'}: {len(src.motion_masks)} masks for {T} frames; one per frame"
        )
    depth_files = []
    if src.depth_dir is not None:
        depth_files = sorted(p for p in src.depth_dir.iterdir() if p.suffix in (".npy", ".npz"))
        if len(depth_files) != T:
            raise UserError(
                f"{src.depth_dir}: {len(depth_files)} .npy/.npz maps for {T} frames; one per frame"
            )
    for (i, j), p in src.flow.items():
        if not (0 <= i < T and 0 <= j < T) or i == j:
            raise UserError(f"{p}: flow pair ({i}, {j}) outside frames 0..{T - 1}; remove the file")
    return times, has_tmasks, depth_files, warnings


def _write_images(tmp: Path, src: _Source, geo: _Geometry, times: list[int], has_tmasks: bool):
    """Training frames, test views and test masks at the output size; returns the preview's thumbnails
    (training, test)."""
    (W0, H0), (W, H) = geo.size0, geo.size
    T = len(src.images)
    thumbs = []
    keep = set(np.unique(np.round(np.linspace(0, T - 1, min(6, T))).astype(int)).tolist())
    for t, p in enumerate(src.images):
        img = read_image(p)
        if img.shape[:2] != (H0, W0):
            raise UserError(f"{p}: {img.shape[1]}x{img.shape[0]}, the first frame is {W0}x{H0}")
        img = _resize_map(img, W, H)
        save_image(tmp / frame_file(t), img)
        if t in keep:
            thumbs.append((f"t{t}", img))
    test_thumbs = []
    for t in times:
        img = _resize_map(read_image(src.test_views[t]), W, H)
        save_image(tmp / test_file(t), img)
        m = None
        if has_tmasks:
            m = read_mask(src.test_masks[t])
            m = cv2.resize(m.astype(np.uint8) * 255, (W, H), interpolation=cv2.INTER_NEAREST) > 127
            save_image(tmp / mask_file(t), m)
        if t in keep:
            test_thumbs.append((f"test t{t}", img, m))
    return thumbs, test_thumbs


def _write_priors(
    tmp: Path, root: Path, src: _Source, size: tuple[int, int], depth_files: list[Path], world_scale: float
) -> dict:
    """The network priors at the scene's size under ``imported/``, and ``imported.json`` naming them (with
    the ``wtbench run`` options that use them). Metric depth maps are multiplied by ``world_scale`` (the
    world's scale against the source frame); disparity is relative and kept. Returns the manifest's record."""
    W, H = size
    record_priors: dict = {}
    args: list[str] = []
    optional: list[str] = []  # options of an imported prior measured below the classical one on real footage
    if depth_files:
        sub = "disp" if src.depth_kind == "disparity" else "depth"
        ddir = _mkdir(tmp / IMPORTED / sub)
        for t, p in enumerate(depth_files):
            a = np.squeeze(np.asarray(_load_array(p, ("disp", "disparity", "depth", "pred"))))
            why = depth_map_problem(a, src.depth_kind)
            if why is not None:
                raise UserError(f"{p}: {why}; re-export the maps")
            a = a.astype(np.float32)
            _check_aspect(a.shape, W, H, p, "the map")
            if src.depth_kind == "depth":
                a = a * np.float32(world_scale)
            np.save(ddir / f"{t:05d}.npy", _resize_map(a, W, H))
        record_priors["depth"] = {"path": f"{IMPORTED}/{sub}", "kind": src.depth_kind,
                                  "source": str(src.depth_dir.resolve()),
                                  "scaled_by": world_scale if src.depth_kind == "depth" else 1.0}  # fmt: skip
        depth_args = ["--depth-maps", f"{IMPORTED}/{sub}", "--set", f"priors.depth_import.kind={src.depth_kind}"]
        if src.depth_kind == "disparity":  # relative (MiDaS-like): its scale is unknown
            # Used only on the moving pixels, where stereo measures nothing (on Balloon1 MiDaS is 11-16% off
            # the static background where stereo is 1-2% off, and extrapolated into the strips only an end
            # camera sees it tilts the wall by 40 %: docs/priors.md, "What the static pixels stereo is unsure
            # of get under fill"), scaled per frame to the stereo without a shift: one wall's narrow range of
            # depth fixes no shift, and the one a line fits there puts a nearer moving object far too far
            # (docs/priors.md, "A scale without a shift").
            depth_args += ["--set", "priors.depth_import.fit_scale_shift=true",
                           "--set", "priors.depth_import.fit_shift=false",
                           "--set", "priors.depth_import.merge=fill",
                           "--set", "priors.depth_import.fill_static=classical"]  # fmt: skip
            # Even so, not suggested: see OPTIONAL_WHY.
            optional += depth_args
        else:
            args += depth_args
    if src.flow:
        fdir = _mkdir(tmp / IMPORTED / "flow")
        sizes = set()
        for (i, j), p in sorted(src.flow.items()):
            f = _read_flow_file(p)
            _check_aspect(f.shape[:2], W, H, p, "the flow")
            sizes.add((f.shape[1], f.shape[0]))
            np.save(fdir / f"{i:05d}_{j:05d}.npy", resize_flow(f, H, W))
        record_priors["flow"] = {"path": f"{IMPORTED}/flow", "pairs": len(src.flow),
                                 "source": str(next(iter(src.flow.values())).parent.resolve()),
                                 "source_sizes": sorted(sizes)}  # fmt: skip
        args += ["--flow", f"{IMPORTED}/flow"]
        # The frame gaps the run's flow settings ask for and the folder lacks (DynamicNeRF ships neighbours only)
        # come from DIS: RAFT's neighbour pairs alone left Balloon1's person and half its balloon out of the
        # masks (docs/priors.md, "The pairs an imported flow folder lacks").
        args += ["--set", "priors.flow.import_missing=classical"]
    if src.motion_masks:
        mdir = _mkdir(tmp / IMPORTED / "masks")
        for t, p in enumerate(src.motion_masks):
            m = read_mask(p)
            _check_aspect(m.shape, W, H, p, "the mask")
            m = cv2.resize(m.astype(np.uint8) * 255, (W, H), interpolation=cv2.INTER_NEAREST) > 127
            save_image(mdir / f"{t:05d}.png", m)
        record_priors["masks"] = {"path": f"{IMPORTED}/masks", "source": str(root / "motion_masks")}
        args += ["--masks", f"{IMPORTED}/masks"]
    if record_priors:
        doc = {"priors": record_priors, "wtbench_run_args": args}
        if optional:
            doc["wtbench_run_args_optional"] = optional
            doc["optional_why"] = OPTIONAL_WHY
        atomic_write_json(tmp / "imported.json", doc)
    return record_priors


def _write_cameras(tmp: Path, geo: _Geometry, T: int, has_tmasks: bool, has_views: bool, world: dict) -> None:
    """``poses_bounds.npy`` (LLFF) and ``cameras.json`` of the output images."""
    W, H = geo.size
    buf = io.BytesIO()
    np.save(buf, llff.opencv_to_llff(geo.w2cs, geo.Ks, H, W, geo.bounds))
    atomic_write_bytes(tmp / "poses_bounds.npy", buf.getvalue())
    doc = cameras_document(
        width=W, height=H, cameras=geo.ids, test_camera=geo.test_cam, Ks=geo.Ks, w2cs=geo.w2cs,
        bounds=geo.bounds, frame_cameras=geo.frame_cams, source_times=list(range(T)), has_masks=has_tmasks,
        world_transform=world,
    )  # fmt: skip
    if not has_views:  # cameras_document lists a test view per time; there are none to list
        doc["test_frames"] = []
    atomic_write_json(tmp / "cameras.json", doc)


def _manifest(root: Path, src: _Source, cfg: ImportConfig, geo: _Geometry, times: list[int], has_tmasks: bool,
              record_priors: dict, world: dict) -> dict:  # fmt: skip
    """``manifest.json``'s record of the import (without timings, warnings and the file hashes)."""
    T = len(src.images)
    cfg_record = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items()}
    return {
        "tool": "nvls import",
        "tool_version": __version__,
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "source": {
            "path": str(root.resolve()),
            "layout": src.layout,
            "time_steps": T,
            "width": geo.size0[0],
            "height": geo.size0[1],
        },  # fmt: skip
        "source_times": list(range(T)),
        "image_size": list(geo.size),
        "test_camera": geo.test_cam,
        "camera_order": geo.frame_cams,
        "counts": {
            "frames": T,
            "test_frames": len(times),
            "masks": len(times) if has_tmasks else 0,
            "cameras": len(geo.ids),
        },  # fmt: skip
        "poses": {"method": "none", "note": "identity poses, focal guessed (--no-poses)"}
        if cfg.no_poses
        else {"method": "file", "rows": geo.pose_note},
        "masks": {"method": "imported" if has_tmasks else "none"},
        "imported_priors": record_priors,
        "world_transform": world,
        "config": cfg_record,
    }


def _mkdir(p: Path) -> Path:
    p.mkdir(parents=True, exist_ok=True)
    return p


# Options of `wtbench run` whose value is a folder of the scene; imported.json stores them relative to the
# scene so that a moved or copied scene still works, and they are confined to it when read.
PATH_OPTIONS = ("--depth-maps", "--flow", "--masks")


OPTIONAL_WHY = (
    "relative (MiDaS-like) disparity, scaled per frame to the stereo and used on the moving pixels, drew "
    "Balloon1's balloon and person worse from its test camera than the classical depth (the three test views "
    "the shared diagnostics image shows, Base quick, two seeds, 20.04 dB with RAFT's flow against 21.70 with "
    "RAFT's flow alone and 21.28 with classical priors; docs/priors.md)"
)
"""Why ``imported.json``'s optional options are not among those ``nvls import`` suggests."""


def run_args(scene: str | Path, optional: bool = False) -> list[str]:
    """The ``wtbench run`` options that use a scene's imported priors (from ``imported.json``; [] if none);
    with ``optional``, those of the priors imported but not suggested (``wtbench_run_args_optional``: relative
    disparity, :data:`OPTIONAL_WHY`).

    Folder values are stored relative to the scene and returned as absolute paths inside it; a value that is
    absolute or leads outside the scene is a one-line :class:`UserError` naming ``imported.json``.
    """
    import json

    from worldtree.scene_schema import resolve_inside

    path = Path(scene) / "imported.json"
    if not path.is_file():
        return []
    try:
        doc = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise UserError(
            f"{path}: not readable JSON ({e}); import the scene again with `nvls import`"
        ) from None
    key = "wtbench_run_args_optional" if optional else "wtbench_run_args"
    args = doc.get(key, []) if isinstance(doc, dict) else None
    if not isinstance(args, list) or not all(isinstance(a, str) for a in args):
        raise UserError(f"{path}: '{key}' must be a list of strings; import the scene again")
    out = list(args)
    for i, a in enumerate(out[:-1]):
        if a in PATH_OPTIONS:
            out[i + 1] = str(resolve_inside(scene, out[i + 1], path))
    return out
