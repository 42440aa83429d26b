"""Balloon1's withheld test views, as far as the shared diagnostics image shows them: a proxy score of issue 28.

The real test views of ``../shared/real_nvidia/Balloon1`` (rig camera 0 at every time) are withheld. The
diagnostics image ``../shared/real_nvidia/diagnostics/balloon1_protocol_quick.png`` shows three of them (t = 2,
5, 8) beside renders of older runs: a grid of 3 rows x 5 panels of 320 x 180 pixels (training frame t, the test
view, static, Base, WorldTree), each the 480x270 protocol image shrunk by OpenCV's area filter, its top
``LABEL_ROWS`` rows covered by a caption. That layout was read off the image, and the test checks it: the first
panel of every row equals the shared training frame t shrunk the same way, to the last bit.

This script renders a finished run's test camera (training frame 0's camera, drawn from frame 0's fitted pose)
at those times, shrinks each render as the panels were made and scores it against the test-view panel below the
caption: PSNR of the 8-bit images, inside / outside the balloon (a colour key of its green, the union of
the panel's and the render's, as :mod:`benchmarks.speed.loo_breakdown` keys it) and on the panel's left tenth
(the wall at the rig's end, which few training cameras see: issue 28's under-seen edge). The older runs' panels are
scored the same way, which calibrates the proxy against the full-size scores the issue quotes (at t = 5 static
17.48 / Base 18.54 / WorldTree 18.08 here against 17.21 / 18.18 / 17.65 at 480x270).

With ``--depth`` it also measures the balloon's depth where the capture itself fixes it: SIFT features of the
balloon (its colour key) matched between training frame t (camera t) and the test panel (camera 0 at the same
time), triangulated with the two cameras' given poses (matches reprojecting farther than 3 px are dropped),
give the balloon's depth in camera t at those pixels; the run's rendered depth of frame t at the same pixels is
compared with it (median ``log(run / measured)``: issue 28's depth error, on real footage, at three times).

With ``--dynamic-scale K[,K...]`` it asks what the balloon's depth alone would change: the dynamic Gaussians that
draw the balloon in training frame t (their centre projects inside the frame's colour key, dilated
``SELECT_DILATE_PX``) are moved along their rays from camera t by the factor K (centre ``c + K (x - c)``, sizes
times K), which leaves frame t's own image as it was and moves the balloon in every other camera as a depth K
times the run's would; camera 0 is then scored at each K. Beside the PSNR every line reports where the balloon
lands (:func:`balloon_placement`): the offset of its colour key's centroid from the test view's, in pixels of
the 480x270 protocol image, and the keys' IoU, issue 28's screen error on real footage.

Three small views of one scene, at a third of the protocol's pixels: a check of where a change moves the real
test views, not a benchmark, and not something to choose settings by (that would tune to the scored data).

Usage::

    python -m benchmarks.speed.protocol_thumbnails RUN_DIR [RUN_DIR ...] [--image PNG] [--panels] [--depth]
        [--dynamic-scale K[,K...]] [--save SHEET.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from benchmarks.evaluation.leave_one_out import score
from benchmarks.speed.loo_breakdown import colour_key
from worldtree.infra.errors import UserError

PANEL_W, PANEL_H = 320, 180
"""One panel of the diagnostics image (pixels)."""
LABEL_ROWS = 19
"""Rows at the top of every panel covered by its caption; scored from this row down."""
TIMES = (2, 5, 8)
"""The test times of the image's rows, top to bottom."""
COLUMNS = ("train", "test", "static", "base", "worldtree")
"""The panels of a row, left to right."""
EDGE_COLS = PANEL_W // 10
"""The panel's left tenth: the wall at the rig's end (issue 28's under-seen edge). Training frame 0, taken by
camera 0, scores 34.9-36.2 dB there against the three test panels: the wall is static and the camera the same."""
BALLOON_HUE = (70.0, 170.0)
"""The balloon's green (hue degrees), as leave-one-out's breakdown keys it."""
KEY_SAT = 0.25
"""Least saturation (0-1) of the balloon's colour key."""
SELECT_DILATE_PX = 4
"""Margin (px of training frame t) around the balloon's colour key inside which a dynamic Gaussian's centre counts
as drawing the balloon (``--dynamic-scale``)."""
PROTOCOL_W = 480
"""Width of the protocol image the panels were shrunk from; placement offsets are in its pixels."""
SHARED = Path(__file__).resolve().parents[2].parent / "shared"
DEFAULT_IMAGE = SHARED / "real_nvidia" / "diagnostics" / "balloon1_protocol_quick.png"


def read_panels(image: Path) -> dict[int, dict[str, np.ndarray]]:
    """``{t: {column: uint8 [PANEL_H - LABEL_ROWS, PANEL_W, 3]}}``: the uncovered part of every panel."""
    from worldtree.imageio import read_image

    if not image.is_file():
        raise UserError(f"{image}: no such file; give the diagnostics image with --image")
    grid = read_image(image)[..., :3]
    want = (PANEL_H * len(TIMES), PANEL_W * len(COLUMNS))
    if grid.shape[:2] != want:
        raise UserError(f"{image}: {grid.shape[1]}x{grid.shape[0]}, the layout needs {want[1]}x{want[0]}")
    out: dict[int, dict[str, np.ndarray]] = {}
    for row, t in enumerate(TIMES):
        top = row * PANEL_H + LABEL_ROWS
        out[t] = {
            name: np.ascontiguousarray(grid[top : (row + 1) * PANEL_H, c * PANEL_W : (c + 1) * PANEL_W])
            for c, name in enumerate(COLUMNS)
        }
    return out


def shrink(img: np.ndarray) -> np.ndarray:
    """uint8 ``[H, W, 3]`` -> the uncovered part of a panel, ``[PANEL_H - LABEL_ROWS, PANEL_W, 3]`` (OpenCV's
    area filter: the image's training panels are the shared frames brought to 480x270 and shrunk by it, to the
    last bit)."""
    import cv2

    small = cv2.resize(np.ascontiguousarray(img), (PANEL_W, PANEL_H), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(small[LABEL_ROWS:])


def panel_scores(pred: np.ndarray, ref: np.ndarray) -> dict[str, float | None]:
    """PSNR (dB) of ``pred`` against the test panel ``ref`` (both uint8, the same shape): whole, inside the
    balloon (the union of both images' colour keys), outside it, and on the panel's left :data:`EDGE_COLS`
    columns (``edge``: wall that only camera 0's neighbours see); None for an empty region."""
    region = colour_key(ref, BALLOON_HUE, KEY_SAT, 6) | colour_key(pred, BALLOON_HUE, KEY_SAT, 6)
    return {
        "psnr": score(pred, ref),
        "balloon": score(pred, ref, region) if region.any() else None,
        "background": score(pred, ref, ~region) if (~region).any() else None,
        "edge": score(pred[:, :EDGE_COLS], ref[:, :EDGE_COLS]),
    }


def balloon_placement(pred: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    """Where ``pred`` draws the balloon against the test panel ``ref`` (both uint8 ``[h, w, 3]`` panels): the offset
    ``dx, dy`` of its colour key's centroid from the panel's and its length ``offset_px``, in pixels of the
    protocol image (:data:`PROTOCOL_W` wide), and the IoU of the two keys; NaN offsets (IoU 0) when either image
    shows no balloon."""
    keys = [colour_key(x, BALLOON_HUE, KEY_SAT, 0) for x in (pred, ref)]
    union = int((keys[0] | keys[1]).sum())
    iou = float((keys[0] & keys[1]).sum() / union) if union else 0.0
    if not (keys[0].any() and keys[1].any()):
        return {"dx": float("nan"), "dy": float("nan"), "offset_px": float("nan"), "iou": iou}
    (yp, xp), (yr, xr) = (np.argwhere(k).mean(0) for k in keys)
    up = PROTOCOL_W / ref.shape[1]
    dx, dy = float((xp - xr) * up), float((yp - yr) * up)
    return {"dx": dx, "dy": dy, "offset_px": float(np.hypot(dx, dy)), "iou": iou}


def scale_about(frame, centre, select, k: float):
    """``frame`` (:class:`worldtree.gaussian_frame.GaussianFrame`) with the Gaussians ``select`` (``[N]`` bool)
    moved along their rays from ``centre`` (``[3]``, model world units) by the factor ``k`` > 0: centres
    ``centre + k (x - centre)``, log-scales ``+ log k``. Seen from a camera at ``centre`` they cover the same
    pixels; from any other camera they sit where a depth ``k`` times theirs would put them."""
    import dataclasses
    import math

    import torch

    if not k > 0.0 or not math.isfinite(k):
        raise UserError(f"--dynamic-scale {k}: give factors > 0, e.g. 0.85,1.0")
    sel = select.to(frame.means.device)[:, None]
    c = torch.as_tensor(centre, dtype=frame.means.dtype, device=frame.means.device)
    means = torch.where(sel, c + k * (frame.means - c), frame.means)
    log_scales = torch.where(sel, frame.log_scales + math.log(k), frame.log_scales)
    return dataclasses.replace(frame, means=means, log_scales=log_scales)


def load_protocol_run(run_dir: Path):
    """The finished run in ``run_dir`` (:class:`benchmarks.api.LoadedRun`, on the CPU), checked to have
    training frame 0 and every time of :data:`TIMES`."""
    from benchmarks.api import load_run

    run = load_run(run_dir, device="cpu")
    if "train_000" not in run.cameras:
        raise UserError(f"{run_dir}: no training frame 0")
    missing = [t for t in TIMES if t not in set(int(x) for x in run.times)]
    if missing:
        raise UserError(f"{run_dir}: no time {missing[0]}; the image shows times {TIMES}")
    return run


def run_renders(run) -> dict[int, np.ndarray]:
    """Training frame 0's camera of a loaded run (:func:`load_protocol_run`) at every time in :data:`TIMES`,
    shrunk as the panels (:func:`shrink`)."""
    from worldtree.pixels import as_uint8

    return {t: shrink(as_uint8(run.render("train_000", t)).numpy()) for t in TIMES}


def training_image(run, doc, t: int) -> np.ndarray:
    """Training frame t of a loaded run's scene as stored (uint8 ``[H, W, C]``); ``doc`` its
    :func:`worldtree.scene_schema.read_cameras`."""
    from worldtree.imageio import read_image
    from worldtree.scene_schema import resolve_inside

    ct = run.cameras[f"train_{t:03d}"]
    return read_image(resolve_inside(run.scene_dir, doc.frames[ct.frame].file, run.scene_dir / "cameras.json"))


def balloon_gaussians(run, t: int, key: np.ndarray):
    """The frame a loaded run draws at ``t`` and ``[N]`` bool: its dynamic Gaussians whose centre projects, in front
    of training camera t (its fitted pose), inside ``key`` (``[H, W]`` bool at that camera's size)."""
    import torch

    from worldtree.motion.lift import project_points

    frame = run.gaussians_at(t)
    ct = run.cameras[f"train_{t:03d}"]
    w2c = run.model_w2c(ct, t)
    uv, z = project_points(frame.means, ct.K.float(), w2c.float())
    inside = (z > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] < key.shape[1] - 0.5) & (uv[:, 1] >= -0.5)
    inside &= uv[:, 1] < key.shape[0] - 0.5
    x = uv[:, 0].round().long().clamp(0, key.shape[1] - 1)
    y = uv[:, 1].round().long().clamp(0, key.shape[0] - 1)
    on_key = torch.from_numpy(np.ascontiguousarray(key))[y, x]
    return frame, frame.dynamic & inside & on_key


def dynamic_scale_renders(run, ks: list[float]) -> dict[float, dict[int, np.ndarray]]:
    """``{k: {t: panel}}``: training frame 0's camera at every time of :data:`TIMES`, with the balloon's dynamic
    Gaussians (:func:`balloon_gaussians`, the key of training frame t dilated :data:`SELECT_DILATE_PX`) moved
    by :func:`scale_about` about camera t's centre, shrunk as the panels."""
    import torch

    from worldtree.gaussian_frame import render_frame
    from worldtree.pixels import as_uint8
    from worldtree.scene_schema import read_cameras
    from worldtree.stages.cameras import centres

    doc = read_cameras(run.scene_dir)
    backend = run.config.photometric.backend
    c0 = run.cameras["train_000"]
    out: dict[float, dict[int, np.ndarray]] = {k: {} for k in ks}
    for t in TIMES:
        key = colour_key(training_image(run, doc, t)[..., :3], BALLOON_HUE, KEY_SAT, SELECT_DILATE_PX)
        frame, sel = balloon_gaussians(run, t, key)
        centre = centres(run.model_w2c(run.cameras[f"train_{t:03d}"], t))
        pose0 = run.model_w2c(c0, t)
        for k in ks:
            moved = scale_about(frame, centre, sel, k)
            with torch.no_grad():
                rgb = render_frame(moved, c0.K, pose0, c0.width, c0.height, "rgb", backend)
            out[k][t] = shrink(as_uint8(rgb.cpu()).numpy())
    return out


def contact_sheet(panels: dict[int, dict[str, np.ndarray]], renders: list[dict[int, np.ndarray]]) -> np.ndarray:
    """uint8 ``[rows, cols, 3]``: a row per time of :data:`TIMES`, the test panel first, then each run's render
    (:func:`run_renders`) in the order given."""
    rows = [np.concatenate([panels[t]["test"]] + [r[t] for r in renders], axis=1) for t in TIMES]
    return np.concatenate(rows, axis=0)


def match_points(
    img_a: np.ndarray, img_b: np.ndarray, region_a: np.ndarray, region_b: np.ndarray, ratio: float = 0.75
) -> tuple[np.ndarray, np.ndarray]:
    """SIFT matches inside ``region_a`` / ``region_b`` (``[H, W]`` bool) of two uint8 RGB images, kept by Lowe's
    ratio test: pixel coordinates ``[N, 2]`` (x, y) in each image."""
    import cv2

    sift = cv2.SIFT_create(4000)
    found = [
        sift.detectAndCompute(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), reg.astype(np.uint8) * 255)
        for img, reg in ((img_a, region_a), (img_b, region_b))
    ]
    (ka, da), (kb, db) = found
    if da is None or db is None or len(ka) < 2 or len(kb) < 2:
        return np.zeros((0, 2), np.float64), np.zeros((0, 2), np.float64)
    pairs = cv2.BFMatcher().knnMatch(da, db, k=2)
    good = [m[0] for m in pairs if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    pa = np.array([ka[g.queryIdx].pt for g in good], np.float64).reshape(-1, 2)
    pb = np.array([kb[g.trainIdx].pt for g in good], np.float64).reshape(-1, 2)
    return pa, pb


def triangulate_depth(
    K_a: np.ndarray, w2c_a: np.ndarray, K_b: np.ndarray, w2c_b: np.ndarray,
    pa: np.ndarray, pb: np.ndarray, max_px: float = 3.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Depth in camera a (scene units) of the point matched at ``pa`` in a and ``pb`` in b (``[N, 2]`` pixels;
    ``K`` ``[3, 3]``, ``w2c`` ``[4, 4]``), by linear triangulation; and ``[N]`` bool: in front of both cameras
    and reprojecting within ``max_px`` in both."""  # fmt: skip
    import cv2

    if len(pa) == 0:
        return np.zeros(0), np.zeros(0, bool)
    P = [np.asarray(K, np.float64) @ np.asarray(w, np.float64)[:3] for K, w in ((K_a, w2c_a), (K_b, w2c_b))]
    Xh = cv2.triangulatePoints(P[0], P[1], pa.T.astype(np.float64), pb.T.astype(np.float64))
    w = np.where(np.abs(Xh[3]) > 1e-12, Xh[3], 1e-12)
    X = np.vstack([Xh[:3] / w, np.ones(len(pa))])
    keep = np.ones(len(pa), bool)
    depths = []
    for Pi, pix in ((P[0], pa), (P[1], pb)):
        x = Pi @ X
        depths.append(x[2])
        proj = (x[:2] / np.where(np.abs(x[2]) > 1e-12, x[2], 1e-12)).T
        keep &= (x[2] > 0) & (np.linalg.norm(proj - pix, axis=1) <= max_px)
    return depths[0], keep


def panel_to_image(points: np.ndarray, width: int, height: int) -> np.ndarray:
    """Pixel coordinates ``[N, 2]`` in a panel's uncovered part -> the same points in the ``width`` x ``height``
    image it was shrunk from (pixel centres mapped onto pixel centres)."""
    sx, sy = width / PANEL_W, height / PANEL_H
    return np.stack([(points[:, 0] + 0.5) * sx - 0.5, (points[:, 1] + LABEL_ROWS + 0.5) * sy - 0.5], 1)


def _depth_against(run, ct, depth: np.ndarray, img, up, region_img, region_up) -> dict[str, float]:
    """Triangulate the matches of two regions (training frame, test panel brought to the frame's width) and
    compare the run's ``depth`` ``[H, W]`` of frame t with it at the same pixels."""
    c0 = run.cameras["train_000"]
    pa, pb_up = match_points(img, up, region_img, region_up)
    pb = panel_to_image(pb_up * (PANEL_W / ct.width), ct.width, ct.height)
    z, keep = triangulate_depth(ct.K.numpy(), ct.w2c.numpy(), c0.K.numpy(), c0.w2c.numpy(), pa, pb)
    x = np.clip(np.rint(pa[:, 0]).astype(int), 0, ct.width - 1)
    y = np.clip(np.rint(pa[:, 1]).astype(int), 0, ct.height - 1)
    d = depth[y, x]
    ok = keep & np.isfinite(d) & (d > 0)
    if not ok.any():
        return {"points": 0.0, "measured": float("nan"), "run": float("nan"), "log_ratio": float("nan")}
    return {"points": float(ok.sum()), "measured": float(np.median(z[ok])), "run": float(np.median(d[ok])),
            "log_ratio": float(np.median(np.log(d[ok] / z[ok])))}  # fmt: skip


def balloon_depth(run, panels: dict[int, dict[str, np.ndarray]]) -> dict[int, dict[str, dict]]:
    """Per time of :data:`TIMES`, for the balloon and for the wall of a loaded run (:func:`load_protocol_run`): the depth in camera t triangulated from
    training frame t and the test panel (median, scene units; ``points`` used), the run's rendered depth at
    those pixels (median) and the median ``log(run / measured)``. The wall is the left quarter of both images
    outside the balloon (dilated 20 px), where nothing moves on Balloon1: its ratio is the run's own scale
    against the given cameras' (bundle adjustment moves them), so the balloon's ratio less the wall's is its
    depth error in the run's own frame."""
    import cv2

    from worldtree.scene_schema import read_cameras

    doc = read_cameras(run.scene_dir)
    out = {}
    for t in TIMES:
        ct = run.cameras[f"train_{t:03d}"]
        img = training_image(run, doc, t)
        test = panels[t]["test"]
        # Matched at the run's scale: the panel brought up to the image's width.
        up = cv2.resize(test, (ct.width, round(test.shape[0] * ct.width / PANEL_W)), interpolation=cv2.INTER_CUBIC)
        depth = run.render(ct, t, mode="depth").numpy()
        keys = [colour_key(x, BALLOON_HUE, KEY_SAT, 0) for x in (img, up)]
        walls = []
        for x in (img, up):
            wall = np.zeros(x.shape[:2], bool)
            wall[:, : x.shape[1] // 4] = True
            walls.append(wall & ~colour_key(x, BALLOON_HUE, KEY_SAT, 20))
        out[t] = {
            "balloon": _depth_against(run, ct, depth, img, up, *keys),
            "wall": _depth_against(run, ct, depth, img, up, *walls),
        }
    return out


def _line(name: str, scores: dict[int, dict[str, float | None]]) -> str:
    def f(v):
        return "-" if v is None else f"{v:.2f}"

    cells = [f"t={t}: {f(s['psnr'])} ({f(s['balloon'])} / {f(s['background'])} / {f(s.get('edge'))})"
             for t, s in scores.items()]  # fmt: skip
    mean = np.mean([s["psnr"] for s in scores.values()])
    return f"{name}: " + "  ".join(cells) + f"  mean {mean:.2f}"


def _placement_line(renders: dict[int, np.ndarray], panels) -> str:
    cells = []
    for t, img in renders.items():
        p = balloon_placement(img, panels[t]["test"])
        cells.append(f"t={t}: {p['offset_px']:.0f} px ({p['dx']:+.0f}, {p['dy']:+.0f}) IoU {p['iou']:.2f}")
    return "  balloon placement (centroid offset at 480x270): " + "  ".join(cells)


def _factors(text: str) -> list[float]:
    try:
        ks = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise UserError(f"--dynamic-scale {text}: give comma-separated factors, e.g. 0.85,1.0") from None
    if not ks or not all(np.isfinite(k) and k > 0 for k in ks):
        raise UserError(f"--dynamic-scale {text}: give factors > 0, e.g. 0.85,1.0")
    return ks


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", type=Path, nargs="*", help="Finished runs on Balloon1 (12-frame protocol).")
    ap.add_argument("--image", type=Path, default=DEFAULT_IMAGE, help="The diagnostics image.")
    ap.add_argument(
        "--panels", action="store_true", help="Also score the image's own static/Base/WorldTree panels."
    )
    ap.add_argument("--depth", action="store_true", help="Also measure the balloon's depth against each run's.")
    ap.add_argument(
        "--save", type=Path, default=None, metavar="PNG",
        help="Also write a sheet: a row per time, the test view then each run's render.",
    )  # fmt: skip
    ap.add_argument(
        "--dynamic-scale", default=None, metavar="K[,K...]",
        help="Also score each run with its balloon's dynamic Gaussians moved to K times their depth in camera t.",
    )  # fmt: skip
    args = ap.parse_args(argv)
    ks = _factors(args.dynamic_scale) if args.dynamic_scale is not None else []
    if args.save is not None and args.save.suffix.lower() not in (".png", ".jpg", ".jpeg"):
        raise UserError(f"--save {args.save}: give a .png or .jpg file")
    panels = read_panels(args.image)
    print("PSNR dB against the test-view panels (balloon / background / left tenth)")
    if args.panels or not args.runs:
        for col in COLUMNS[2:]:
            print(_line(f"image's {col}", {t: panel_scores(p[col], p["test"]) for t, p in panels.items()}))
    sheets = []
    for run_dir in args.runs:
        run = load_protocol_run(run_dir)  # loaded once for the renders and the depth
        renders = run_renders(run)
        sheets.append(renders)
        print(_line(str(run_dir), {t: panel_scores(img, panels[t]["test"]) for t, img in renders.items()}))
        print(_placement_line(renders, panels))
        for k, moved in dynamic_scale_renders(run, ks).items() if ks else ():
            scores = {t: panel_scores(img, panels[t]["test"]) for t, img in moved.items()}
            print(_line(f"  balloon at {k:g} x its depth", scores))
            print("  " + _placement_line(moved, panels))
        if args.depth:
            cells = []
            for t, r in balloon_depth(run, panels).items():
                b, w = r["balloon"], r["wall"]
                cells.append(
                    f"t={t}: {b['measured']:.3f} measured ({b['points']:.0f} points), run {b['run']:.3f} "
                    f"({b['log_ratio']:+.2f}; wall {w['log_ratio']:+.2f}, {w['points']:.0f} points)"
                )
            print("  balloon depth in camera t, log(run / measured): " + "  ".join(cells))
    if args.save is not None:
        from worldtree.imageio import write_image

        write_image(args.save, contact_sheet(panels, sheets))  # atomic: a whole sheet or none
        print(f"wrote {args.save}")


if __name__ == "__main__":
    try:
        main()
    except UserError as e:  # a one-line message naming the file or option, no traceback
        raise SystemExit(f"error: {e}") from None
