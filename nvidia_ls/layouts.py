"""Detect and read the three raw capture layouts of a static camera rig.

- multi-view folders: ``RAW/[dense/]mv_images/%05d/cam%02d.{jpg,png}`` (one folder per time step);
- per-camera folders: ``RAW/cam%02d/%05d.{jpg,png}``;
- per-camera videos: ``RAW/cam%02d.mp4`` (also .mov, .avi).

Cameras are numbered from 1 and must be contiguous; time steps are the numbers in the names (the
"source time"). Time steps that some camera lacks are dropped (with a warning).
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from worldtree.imageio import IMAGE_SUFFIXES, check_pixels, read_image
from worldtree.infra.errors import UserError

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv")
_CAM_RE = re.compile(r"^cam(\d+)$", re.IGNORECASE)
_NUM_RE = re.compile(r"^(\d+)$")


def read_frame_file(path: Path) -> np.ndarray:
    """Read one raw image (RGB uint8); a JPEG without its end marker counts as truncated."""
    if path.suffix.lower() in (".jpg", ".jpeg"):
        with open(path, "rb") as f:
            f.seek(0, 2)
            size = f.tell()
            f.seek(max(0, size - 2))
            tail = f.read(2)
        # OpenCV decodes a cut JPEG with only a warning; the missing EOI marker gives it away.
        if size < 4 or tail != b"\xff\xd9":
            raise UserError(f"{path}: truncated JPEG (no end-of-image marker); replace or remove it")
    return read_image(path)


@dataclass
class RawCapture:
    """A raw capture of a static rig.

    Attributes:
        root: the folder the layout was found in.
        layout: "multiview", "camera_folders" or "videos".
        cameras: camera ids, 1..N.
        times: source time indices every camera has, increasing.
        width, height: image size (of the first camera's first frame).
        warnings: notes about dropped time steps etc.
    """

    root: Path
    layout: str
    cameras: list[int]
    times: list[int]
    width: int
    height: int
    files: dict[tuple[int, int], Path] = field(default_factory=dict, repr=False)
    videos: dict[int, Path] = field(default_factory=dict, repr=False)
    warnings: list[str] = field(default_factory=list)

    def _check_size(self, img: np.ndarray, where: str) -> np.ndarray:
        if img.shape[0] != self.height or img.shape[1] != self.width:
            raise UserError(
                f"{where}: image is {img.shape[1]}x{img.shape[0]}, other frames are {self.width}x{self.height}; "
                "all cameras must have the same image size (resize them first)"
            )
        return img

    def read(self, camera: int, time: int) -> np.ndarray:
        """One frame, RGB uint8 ``[H, W, 3]``."""
        for t, img in self.iter_frames(camera, [time]):
            if t == time:
                return img
        raise UserError(f"{self.root}: camera {camera} has no time step {time}")

    def iter_frames(self, camera: int, times: list[int]) -> Iterator[tuple[int, np.ndarray]]:
        """Frames of one camera at increasing source ``times``: yields ``(time, RGB uint8 [H, W, 3])``."""
        if self.layout != "videos":
            for t in times:
                path = self.files[(t, camera)]
                yield t, self._check_size(read_frame_file(path), str(path))
            return
        path = self.videos[camera]
        cap = cv2.VideoCapture(str(path))
        try:
            wanted = sorted(times)
            pos = 0
            for t in wanted:
                # Decoding sequentially is exact; seeking by frame number is not reliable for all codecs.
                while pos < t:
                    if not cap.grab():
                        raise UserError(f"{path}: video ends at frame {pos}, before frame {t} (truncated?)")
                    pos += 1
                ok, bgr = cap.read()
                pos += 1
                if not ok or bgr is None:
                    raise UserError(f"{path}: cannot decode frame {t} (truncated or corrupt video)")
                img = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
                yield t, self._check_size(img, f"{path} frame {t}")
        finally:
            cap.release()


def _camera_id(name: str) -> int | None:
    m = _CAM_RE.match(name)
    return int(m.group(1)) if m else None


def _check_cameras(root: Path, cams: set[int], num_cameras: int | None, what: str) -> list[int]:
    if not cams:
        raise UserError(f"{root}: no cameras found ({what}); expected names like cam01, cam02, ...")
    expected = num_cameras or max(cams)
    missing = [c for c in range(1, expected + 1) if c not in cams]
    if missing:
        names = ", ".join(f"cam{c:02d}" for c in missing)
        raise UserError(f"{root}: missing cameras {names} ({what}); add them or pass the right --num-cameras")
    extra = [c for c in cams if c > expected or c < 1]
    if extra:
        raise UserError(f"{root}: cameras {extra} outside 1..{expected}; remove them or fix --num-cameras")
    return list(range(1, expected + 1))


def _common_times(per_cam: dict[int, set[int]], root: Path, warnings: list[str]) -> list[int]:
    all_times = set().union(*per_cam.values())
    common = set.intersection(*per_cam.values())
    if not common:
        raise UserError(f"{root}: no time step is present for every camera; check the capture")
    if len(common) < len(all_times):
        dropped = sorted(all_times - common)
        lacking = sorted(c for c, ts in per_cam.items() if not all_times <= ts)
        shown = ", ".join(str(t) for t in dropped[:8]) + (" ..." if len(dropped) > 8 else "")
        warnings.append(
            f"{len(dropped)} time steps ({shown}) lack some cameras ({', '.join(f'cam{c:02d}' for c in lacking)}); "
            f"using the {len(common)} time steps every camera has"
        )
    return sorted(common)


def _find_multiview(raw: Path) -> Path | None:
    if raw.name == "mv_images":
        return raw
    for cand in (raw / "mv_images", raw / "dense" / "mv_images"):
        if cand.is_dir():
            return cand
    return None


def _image_files(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def _with_size(cap: RawCapture) -> RawCapture:
    """Take the size from the first camera's first frame and check every camera's first frame against it.

    Every frame the build reads is checked again, so a single odd frame is caught when it is used.
    """
    first = read_frame_file(cap.files[(cap.times[0], cap.cameras[0])])
    cap.height, cap.width = first.shape[:2]
    for c in cap.cameras[1:]:
        path = cap.files[(cap.times[0], c)]
        cap._check_size(read_frame_file(path), str(path))
    return cap


def _open_multiview(mv: Path, num_cameras: int | None) -> RawCapture:
    files: dict[tuple[int, int], Path] = {}
    per_cam: dict[int, set[int]] = {}
    for d in sorted(mv.iterdir()):
        if not d.is_dir() or not _NUM_RE.match(d.name):
            continue
        t = int(d.name)
        for p in _image_files(d):
            c = _camera_id(p.stem)
            if c is None:
                continue
            files[(t, c)] = p
            per_cam.setdefault(c, set()).add(t)
    if not files:
        raise UserError(f"{mv}: no time-step folders with camNN images; expected mv_images/00000/cam01.png")
    warnings: list[str] = []
    cams = _check_cameras(mv, set(per_cam), num_cameras, "in mv_images")
    times = _common_times({c: per_cam[c] for c in cams}, mv, warnings)
    first = read_frame_file(files[(times[0], cams[0])])
    return RawCapture(
        mv, "multiview", cams, times, first.shape[1], first.shape[0], files=files, warnings=warnings
    )


def _open_camera_folders(raw: Path, folders: dict[int, Path], num_cameras: int | None) -> RawCapture:
    cams = _check_cameras(raw, set(folders), num_cameras, "camNN/ folders")
    files: dict[tuple[int, int], Path] = {}
    per_cam: dict[int, set[int]] = {}
    for c in cams:
        ts = set()
        for p in _image_files(folders[c]):
            if _NUM_RE.match(p.stem):
                files[(int(p.stem), c)] = p
                ts.add(int(p.stem))
        if not ts:
            raise UserError(
                f"{folders[c]}: no frames named like 00000.png; add the frames or remove the folder"
            )
        per_cam[c] = ts
    warnings: list[str] = []
    times = _common_times(per_cam, raw, warnings)
    first = read_frame_file(files[(times[0], cams[0])])
    return RawCapture(
        raw, "camera_folders", cams, times, first.shape[1], first.shape[0], files=files, warnings=warnings
    )


def _open_videos(raw: Path, videos: dict[int, Path], num_cameras: int | None) -> RawCapture:
    cams = _check_cameras(raw, set(videos), num_cameras, "camNN video files")
    counts, size = {}, None
    for c in cams:
        cap = cv2.VideoCapture(str(videos[c]))
        try:
            if not cap.isOpened():
                raise UserError(f"{videos[c]}: cannot open the video (unreadable or corrupt); replace it")
            n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
            w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        finally:
            cap.release()
        if n <= 0:
            raise UserError(f"{videos[c]}: the video has no frames (unreadable or truncated); replace it")
        check_pixels(w, h, str(videos[c]))  # before any frame is decoded
        if size is None:
            size = (w, h)
        elif (w, h) != size:
            raise UserError(
                f"{videos[c]}: frames are {w}x{h}, cam{cams[0]:02d} is {size[0]}x{size[1]}; "
                "all cameras must have the same image size"
            )
        counts[c] = n
    warnings: list[str] = []
    n_common = min(counts.values())
    if max(counts.values()) != n_common:
        short = [f"cam{c:02d}" for c, n in counts.items() if n == n_common]
        warnings.append(
            f"videos have {n_common}..{max(counts.values())} frames ({', '.join(short)} shortest); "
            f"using the first {n_common} frames of every camera"
        )
    return RawCapture(
        raw, "videos", cams, list(range(n_common)), size[0], size[1], videos=videos, warnings=warnings
    )


def open_raw(raw_dir: str | Path, num_cameras: int | None = None) -> RawCapture:
    """Detect the layout of ``raw_dir`` and index its frames.

    Args:
        raw_dir: one scene's raw folder.
        num_cameras: expected rig size (default: the highest camera number found).

    Raises:
        UserError: no known layout, missing cameras, no common time step, unreadable first frame.
    """
    raw = Path(raw_dir)
    if not raw.is_dir():
        raise UserError(f"{raw}: not a folder; give the raw scene folder (holding mv_images/ or camNN/)")
    mv = _find_multiview(raw)
    if mv is not None:
        return _open_multiview(mv, num_cameras)
    folders, videos = {}, {}
    for p in sorted(raw.iterdir()):
        c = _camera_id(p.stem if p.is_file() else p.name)
        if c is None:
            continue
        if p.is_dir():
            folders[c] = p
        elif p.suffix.lower() in VIDEO_SUFFIXES:
            videos[c] = p
    if folders:
        return _open_camera_folders(raw, folders, num_cameras)
    if videos:
        return _open_videos(raw, videos, num_cameras)
    raise UserError(
        f"{raw}: no raw layout found; expected mv_images/%05d/cam%02d.png (or dense/mv_images), "
        "cam%02d/%05d.png folders, or cam%02d.mp4 videos"
    )
