"""Side-by-side mp4 of a run's test-view renders next to the ground truth (and the mask, when present), and its
WebM re-encoding for browsers."""

from __future__ import annotations

import contextlib
import json
import os
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from worldtree.imageio import read_image, read_mask
from worldtree.infra.errors import UserError
from worldtree.scene_schema import read_cameras, resolve_inside


def _label(img: np.ndarray, text: str) -> np.ndarray:
    out = img.copy()
    scale = max(0.3, img.shape[0] / 400)
    cv2.putText(out, text, (4, int(16 * scale) + 2), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1,
                cv2.LINE_AA)  # fmt: skip
    return out


def mask_overlay(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``image`` (uint8 RGB ``[H, W, 3]``) with the pixels of ``mask`` (bool ``[H, W]``) tinted red, half and
    half, so the scored region and the content under it both show."""
    tint = image.copy()
    tint[mask] = (0.5 * image[mask] + 0.5 * np.array([255, 64, 64])).astype(np.uint8)
    return tint


def compose_frames(run_dir: str | Path) -> tuple[list[np.ndarray], list[str]]:
    """Frames ``[H, 2W (or 3W), 3]`` uint8 RGB: render | ground truth | ground truth with the mask overlaid.

    The scene is found through the run's ``config.json``; renders and ground truth pair by name.
    """
    run_dir = Path(run_dir)
    cfg_path = run_dir / "config.json"
    if not cfg_path.is_file():
        raise UserError(f"{run_dir}: no config.json; give a run folder written by `wtbench run`")
    scene = Path(json.loads(cfg_path.read_text())["scene"])
    meta_path = scene / "cameras.json"
    if not meta_path.is_file():
        raise UserError(f"{meta_path}: missing; the run's scene has moved (config.json names {scene})")
    frames, names = [], []
    for fr in read_cameras(scene).test_frames:
        name = Path(fr.file).stem
        render = run_dir / "renders" / f"{name}.png"
        if not render.is_file():
            raise UserError(f"{render}: missing render; finish the run with `wtbench run` first")
        pred, gt = read_image(render), read_image(resolve_inside(scene, fr.file, meta_path))
        if pred.shape != gt.shape:
            raise UserError(f"{render}: size {pred.shape[:2]} differs from the ground truth's {gt.shape[:2]}")
        panels = [_label(pred, "render"), _label(gt, "ground truth")]
        if fr.mask:
            panels.append(_label(mask_overlay(gt, read_mask(resolve_inside(scene, fr.mask, meta_path))), "mask"))
        frames.append(np.concatenate(panels, axis=1))
        names.append(name)
    if not frames:
        raise UserError(f"{meta_path}: lists no test frames")
    return frames, names


def write_video(frames: list[np.ndarray], out: str | Path, fps: float = 10.0) -> Path:
    """Write RGB uint8 frames to an mp4 (OpenCV mp4v) through a temporary file renamed at the end."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    h, w = frames[0].shape[:2]
    # Even sizes keep every mp4 decoder happy.
    h2, w2 = h - h % 2, w - w % 2
    fd, tmp = tempfile.mkstemp(prefix=f".{out.stem}.", suffix=".mp4", dir=out.parent)
    os.close(fd)
    try:
        vw = cv2.VideoWriter(tmp, cv2.VideoWriter_fourcc(*"mp4v"), fps, (w2, h2))
        if not vw.isOpened():
            raise UserError(f"{out}: OpenCV cannot write mp4 here; write PNG frames instead")
        for f in frames:
            vw.write(cv2.cvtColor(np.ascontiguousarray(f[:h2, :w2]), cv2.COLOR_RGB2BGR))
        vw.release()
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return out


@contextlib.contextmanager
def _quiet_stderr():
    """Silence file descriptor 2 (C code's stderr) for the duration: OpenCV's FFmpeg backend prints a line
    about WebM codec tags when a VP8 writer opens, although the file it writes is fine."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def to_webm(src: str | Path, dst: str | Path) -> int:
    """Re-encode the video ``src`` (e.g. the mp4v of :func:`write_video`, which browsers such as Chromium do not
    play) as VP8 WebM at ``dst``, which every current browser plays. Returns the number of frames written; 0
    when OpenCV cannot read ``src`` or write WebM here (``dst`` is then not left behind)."""
    src, dst = Path(src), Path(dst)
    cap = cv2.VideoCapture(str(src))
    if not cap.isOpened():
        return 0
    fps = cap.get(cv2.CAP_PROP_FPS)
    fps = fps if np.isfinite(fps) and fps > 0 else 10.0
    writer, n = None, 0
    try:
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            if writer is None:
                h, w = frame.shape[:2]
                with _quiet_stderr():
                    writer = cv2.VideoWriter(str(dst), cv2.VideoWriter_fourcc(*"VP80"), fps, (w, h))
                if not writer.isOpened():
                    return 0
            writer.write(frame)
            n += 1
    finally:
        cap.release()
        if writer is not None:
            writer.release()
        if n == 0 and dst.exists():
            dst.unlink()
    return n
