"""Frames of a monocular clip: a video file (decoded with OpenCV) or a folder of frames, for ``nvls import``.

A clip is read once, in order: every ``stride``-th frame is kept, at most ``max_frames`` of them, each resized
to the output size as it is read (so a long 4K clip never sits in memory at full size). The kept frames carry
their *source index* (frame number in the video, or position in the sorted folder), which the scene records as
``source_time``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from worldtree.imageio import read_image
from worldtree.infra.errors import SettingError, UserError

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v")
FRAME_SUFFIXES = (".png", ".jpg", ".jpeg")
MIN_FRAMES = 3
"""Fewer kept frames than this give no usable two-view geometry, so no camera path."""


@dataclass(frozen=True)
class VideoConfig:
    """How a clip (video file or folder of frames) becomes a posed scene (``nvls import CLIP``)."""

    stride: int = 1
    """Keep every k-th frame of the clip (1 = all); a larger stride gives more parallax between frames."""
    max_frames: int | None = None
    """Keep at most this many frames (the first ones after --video-stride); None keeps all."""
    mask_moving: bool = True
    """Leave features on moving objects out of SfM (a per-frame moving-pixel mask from the epipolar error of
    optical flow, worldtree.priors); --no-video-mask-moving uses every feature."""
    min_registered: float = 0.8
    """SfM must register at least this fraction of the kept frames, else the import stops (0..1)."""
    unregistered: str = "drop"
    """Frames SfM cannot register: drop (left out of the scene, listed in the manifest) | fail (stop)."""
    sfm_threads: int = 1
    """pycolmap threads; 1 makes SfM reproducible, more is faster but varies from run to run."""
    seed: int = 0
    """SfM mapper seed."""

    def check(self) -> None:
        """Raise :class:`UserError` for a value the import cannot honour."""
        if self.stride < 1:
            raise SettingError.of_field(self, "stride", "must be at least 1")
        if self.max_frames is not None and self.max_frames < MIN_FRAMES:
            raise SettingError.of_field(self, "max_frames", f"keep at least {MIN_FRAMES} frames")
        if not 0.0 <= self.min_registered <= 1.0:
            raise SettingError.of_field(self, "min_registered", "give a fraction in 0..1")
        if self.unregistered not in ("drop", "fail"):
            raise SettingError.of_field(
                self, "unregistered", "choose drop or fail", shown=repr(self.unregistered)
            )
        if self.sfm_threads < 1:
            raise SettingError.of_field(self, "sfm_threads", "must be at least 1")


@dataclass
class Clip:
    """Kept frames of a clip.

    Attributes:
        path: the video file or frames folder.
        kind: ``"video"`` or ``"frames"``.
        frames: ``[T, H, W, 3]`` uint8 RGB at the output size.
        source_index: ``[T]`` frame number in the source of each kept frame.
        source_count: frames in the source (decoded, or files in the folder).
        source_size: ``(W, H)`` of the source frames.
        fps: the video's frame rate (None for a folder or when the container does not say).
        truncated: True when ``max_frames`` stopped the reading before the end.
    """

    path: Path
    kind: str
    frames: np.ndarray
    source_index: list[int]
    source_count: int
    source_size: tuple[int, int]
    fps: float | None
    truncated: bool


def is_video(path: Path) -> bool:
    return path.suffix.lower() in VIDEO_SUFFIXES


def frame_files(folder: Path) -> list[Path]:
    """The frame images directly inside ``folder``, sorted by name."""
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in FRAME_SUFFIXES)


def _fit(img: np.ndarray, size: tuple[int, int] | None, where: Path) -> np.ndarray:
    """``img`` [H, W, 3] at ``size`` (W, H), which must keep its aspect (1 %)."""
    h, w = img.shape[:2]
    if size is None or size == (w, h):
        return img
    W, H = size
    if abs(W / H - w / h) > 0.01 * w / h:
        raise UserError(f"--size {W}x{H}: {where} has {w}x{h} frames (another aspect); keep the aspect")
    return cv2.resize(img, (W, H), interpolation=cv2.INTER_AREA if W < w else cv2.INTER_CUBIC)


def read_clip(
    source: str | Path,
    cfg: VideoConfig,
    size: tuple[int, int] | None = None,
    tick: Callable[[int, int], None] | None = None,
) -> Clip:
    """Read the kept frames of a video file or a frames folder (see the module docstring).

    ``size`` is the output ``(W, H)`` (None: the source size); ``tick(done, total)`` reports progress (total 0
    when unknown). Errors are one-line :class:`UserError` naming the file.
    """
    cfg.check()
    path = Path(source)
    if not path.exists():
        raise UserError(
            f"{path}: no such file or folder; give a video (.mp4, .mov, ...) or a folder of frames"
        )
    if path.is_dir():
        return _read_folder(path, cfg, size, tick)
    if not is_video(path):
        raise UserError(
            f"{path}: not a video ({', '.join(VIDEO_SUFFIXES)}) or a folder; give a clip or a folder of frames"
        )
    return _read_video(path, cfg, size, tick)


def _read_folder(folder: Path, cfg: VideoConfig, size, tick) -> Clip:
    files = frame_files(folder)
    if not files:
        raise UserError(f"{folder}: holds no .png/.jpg frames; give a folder of frames or a video file")
    picked = list(range(0, len(files), cfg.stride))
    truncated = cfg.max_frames is not None and len(picked) > cfg.max_frames
    picked = picked[: cfg.max_frames] if cfg.max_frames is not None else picked
    _enough(folder, len(picked), cfg)
    frames, first = [], None
    for k, i in enumerate(picked):
        img = read_image(files[i])  # RGB; unreadable or truncated: a UserError naming the file
        if first is None:
            first = img.shape[:2]
        elif img.shape[:2] != first:
            raise UserError(
                f"{files[i]}: {img.shape[1]}x{img.shape[0]}, the first frame is {first[1]}x{first[0]}; "
                "all frames must have one size"
            )
        frames.append(_fit(img, size, files[i]))
        if tick:
            tick(k + 1, len(picked))
    return Clip(folder, "frames", np.stack(frames), picked, len(files), (first[1], first[0]), None, truncated)


def _read_video(path: Path, cfg: VideoConfig, size, tick) -> Clip:
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise UserError(
                f"{path}: OpenCV cannot open this video; re-encode it (e.g. H.264 .mp4) or give frames"
            )
        fps = float(cap.get(cv2.CAP_PROP_FPS)) or None
        expected = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        total = expected if cfg.max_frames is None else min(expected, cfg.max_frames * cfg.stride)
        frames, kept, index, truncated, src_size = [], [], 0, False, None
        # Sequential decoding (grab every frame, retrieve the kept ones): seeking lands on key frames in
        # some containers, so frame numbers would not be exact.
        while cap.grab():
            if index % cfg.stride == 0:
                if cfg.max_frames is not None and len(kept) == cfg.max_frames:
                    truncated = True
                    break
                ok, bgr = cap.retrieve()
                if not ok or bgr is None:
                    raise UserError(f"{path}: frame {index} cannot be decoded; re-encode the video")
                src_size = (bgr.shape[1], bgr.shape[0])
                frames.append(_fit(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), size, path))
                kept.append(index)
                if tick:
                    tick(index + 1, total)
            index += 1
    finally:
        cap.release()
    if not frames:
        raise UserError(
            f"{path}: no frame could be decoded (empty or damaged video); re-encode it or give frames"
        )
    _enough(path, len(frames), cfg)
    return Clip(path, "video", np.stack(frames), kept, index, src_size, fps, truncated)


def _enough(path: Path, n: int, cfg: VideoConfig) -> None:
    if n < MIN_FRAMES:
        hint = " (lower --video-stride)" if cfg.stride > 1 else ""
        raise UserError(f"{path}: {n} frame(s) kept, at least {MIN_FRAMES} are needed{hint}")
