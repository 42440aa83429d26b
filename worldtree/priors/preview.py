"""PNG previews of the priors a person can check at a glance.

For a few evenly spaced frames: ``depth_<t>.png`` (inverse depth, turbo colour map, near = warm; low-confidence
pixels darkened), ``tracks_<t>.png`` (the last few positions of every visible track over the frame; red =
dynamic, green = static) and ``epi_<t>.png`` (the dynamic mask in red over the frame, with the epipolar error
as a heat strip on the right). ``sheet.png`` stacks them into one contact sheet.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from worldtree.imageio import as_uint8_array, write_image


def _u8(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img)
    # A copy either way: the callers draw on the result.
    return img.copy() if img.dtype == np.uint8 else as_uint8_array(img)


def colorize_depth(
    depth: np.ndarray, conf: np.ndarray | None = None, limits: tuple[float, float] | None = None
) -> np.ndarray:
    """Depth ``[H,W]`` -> RGB uint8 ``[H,W,3]``: inverse depth between ``limits`` (default its 2nd and 98th
    percentiles) through the turbo colour map; pixels with zero confidence darkened."""
    inv = 1.0 / np.maximum(depth, 1e-9)
    lo, hi = limits if limits is not None else np.percentile(inv, [2, 98])
    x = np.clip((inv - lo) / max(hi - lo, 1e-12), 0, 1)
    rgb = cv2.cvtColor(cv2.applyColorMap((x * 255).astype(np.uint8), cv2.COLORMAP_TURBO), cv2.COLOR_BGR2RGB)
    if conf is not None:
        rgb = np.where((conf > 0)[..., None], rgb, (rgb * 0.45).astype(np.uint8))
    return rgb


def draw_tracks(
    image: np.ndarray, tracks: np.ndarray, visible: np.ndarray, dynamic: np.ndarray, t: int, tail: int = 8
) -> np.ndarray:
    """Frame ``t`` with the tracks ``[T,N,2]`` visible there, each with its last ``tail`` positions."""
    out = _u8(image)
    T = tracks.shape[0]
    t0 = max(0, t - tail)
    for n in np.flatnonzero(visible[t]):
        col = (255, 40, 40) if dynamic[n] else (40, 230, 40)
        pts = [tracks[s, n] for s in range(t0, t + 1) if s < T and visible[s, n]]
        for a, b in zip(pts[:-1], pts[1:], strict=False):
            cv2.line(
                out,
                (int(round(a[0])), int(round(a[1]))),
                (int(round(b[0])), int(round(b[1]))),
                col,
                1,
                cv2.LINE_AA,
            )
        x, y = tracks[t, n]
        cv2.circle(out, (int(round(x)), int(round(y))), 1, col, -1)
    return out


def overlay_mask(
    image: np.ndarray, mask: np.ndarray, error: np.ndarray | None = None, scale: float = 3.0
) -> np.ndarray:
    """Frame with ``mask`` tinted red; with ``error`` [H,W] (pixels) a heat map of min(error/scale, 1) beside."""
    out = _u8(image).astype(np.float32)
    red = np.array([255, 0, 0], np.float32)
    out = np.where(mask[..., None], 0.45 * out + 0.55 * red, out).astype(np.uint8)
    if error is None:
        return out
    x = np.clip(error / scale, 0, 1)
    heat = cv2.cvtColor(
        cv2.applyColorMap((x * 255).astype(np.uint8), cv2.COLORMAP_INFERNO), cv2.COLOR_BGR2RGB
    )
    return np.concatenate([out, heat], 1)


def preview_frames(num_frames: int, count: int = 6) -> list[int]:
    """Up to ``count`` evenly spaced frame indices including the first and last."""
    if num_frames <= count:
        return list(range(num_frames))
    return sorted({int(round(v)) for v in np.linspace(0, num_frames - 1, count)})


def write_previews(
    priors, images: np.ndarray, out_dir: str | Path, count: int = 6, threshold: float = 1.5
) -> list[Path]:
    """Write previews of a :class:`worldtree.priors.Priors` for ``images`` [T,H,W,3]; returns the files."""
    out_dir = Path(out_dir)
    written: list[Path] = []
    rows = []
    frames = preview_frames(len(images), count)
    # One colour scale for all previewed frames, so the same depth has the same colour everywhere.
    limits = tuple(np.percentile(1.0 / np.maximum(priors.depth[frames], 1e-9), [2, 98]))
    for t in frames:
        d = colorize_depth(priors.depth[t], priors.depth_conf[t], limits)
        tr = draw_tracks(images[t], priors.tracks, priors.track_vis, priors.track_dynamic, t)
        ep = overlay_mask(images[t], priors.epi_mask[t], priors.epi_error[t], scale=2 * threshold)
        for name, img in (("depth", d), ("tracks", tr), ("epi", ep)):
            p = out_dir / f"{name}_{t:05d}.png"
            write_image(p, img)
            written.append(p)
        rows.append(np.concatenate([d, tr, ep], 1))
    if rows:
        sheet = np.concatenate(rows, 0)
        # Keep the sheet a viewable size.
        if sheet.shape[1] > 2400:
            f = 2400 / sheet.shape[1]
            sheet = cv2.resize(sheet, (2400, max(1, int(sheet.shape[0] * f))), interpolation=cv2.INTER_AREA)
        write_image(out_dir / "sheet.png", sheet)
        written.append(out_dir / "sheet.png")
    return written
