"""Balloon1's withheld test views, as far as the shared diagnostics image shows them: a proxy score of issue 28.

The real test views of ``../shared/real_nvidia/Balloon1`` (rig camera 0 at every time) are withheld. The
diagnostics image ``../shared/real_nvidia/diagnostics/balloon1_protocol_quick.png`` shows three of them (t = 2,
5, 8) beside renders of older runs: a grid of 3 rows x 5 panels of 320 x 180 pixels (training frame t, the test
view, static, Base, WorldTree), each the 480x270 protocol image shrunk with bilinear filtering, its top
``LABEL_ROWS`` rows covered by a caption. That layout was read off the image, and the test checks it: the first
panel of every row equals the shared training frame t shrunk the same way to about 40 dB.

This script renders a finished run's test camera (training frame 0's camera, drawn from frame 0's fitted pose)
at those times, shrinks each render as the panels were made and scores it against the test-view panel below the
caption: PSNR of the 8-bit images, and inside / outside the balloon (a colour key of its green, the union of
the panel's and the render's, as :mod:`benchmarks.speed.loo_breakdown` keys it). The older runs' panels are
scored the same way, which calibrates the proxy against the full-size scores the issue quotes (at t = 5 static
17.48 / Base 18.54 / WorldTree 18.08 here against 17.21 / 18.18 / 17.65 at 480x270).

Three small views of one scene, at a third of the protocol's pixels: a check of where a change moves the real
test views, not a benchmark, and not something to choose settings by (that would tune to the scored data).

Usage::

    python -m benchmarks.speed.protocol_thumbnails RUN_DIR [RUN_DIR ...] [--image PNG] [--panels]
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
BALLOON_HUE = (70.0, 170.0)
"""The balloon's green (hue degrees), as leave-one-out's breakdown keys it; saturation >= 0.25, dilated 6 px."""
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
    """uint8 ``[H, W, 3]`` -> the uncovered part of a panel, ``[PANEL_H - LABEL_ROWS, PANEL_W, 3]`` (PIL's
    bilinear filter, which reproduces the image's training panels best of PIL's filters)."""
    from PIL import Image

    small = np.asarray(Image.fromarray(img).resize((PANEL_W, PANEL_H), Image.BILINEAR))
    return np.ascontiguousarray(small[LABEL_ROWS:])


def panel_scores(pred: np.ndarray, ref: np.ndarray) -> dict[str, float | None]:
    """PSNR (dB) of ``pred`` against the test panel ``ref`` (both uint8, the same shape): whole, inside the
    balloon (the union of both images' colour keys) and outside it; None for an empty region."""
    region = colour_key(ref, BALLOON_HUE, 0.25, 6) | colour_key(pred, BALLOON_HUE, 0.25, 6)
    return {
        "psnr": score(pred, ref),
        "balloon": score(pred, ref, region) if region.any() else None,
        "background": score(pred, ref, ~region) if (~region).any() else None,
    }


def run_scores(run_dir: Path, panels: dict[int, dict[str, np.ndarray]]) -> dict[int, dict[str, float | None]]:
    """Scores of training frame 0's camera of the run in ``run_dir`` at every time in :data:`TIMES`."""
    from benchmarks.api import load_run
    from worldtree.pixels import as_uint8

    run = load_run(run_dir, device="cpu")
    if "train_000" not in run.cameras:
        raise UserError(f"{run_dir}: no training frame 0")
    missing = [t for t in TIMES if t not in set(int(x) for x in run.times)]
    if missing:
        raise UserError(f"{run_dir}: no time {missing[0]}; the image shows times {TIMES}")
    out = {}
    for t in TIMES:
        img = as_uint8(run.render("train_000", t)).numpy()
        out[t] = panel_scores(shrink(img), panels[t]["test"])
    return out


def _line(name: str, scores: dict[int, dict[str, float | None]]) -> str:
    def f(v):
        return "-" if v is None else f"{v:.2f}"

    cells = [f"t={t}: {f(s['psnr'])} ({f(s['balloon'])} / {f(s['background'])})" for t, s in scores.items()]
    mean = np.mean([s["psnr"] for s in scores.values()])
    return f"{name}: " + "  ".join(cells) + f"  mean {mean:.2f}"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("runs", type=Path, nargs="*", help="Finished runs on Balloon1 (12-frame protocol).")
    ap.add_argument("--image", type=Path, default=DEFAULT_IMAGE, help="The diagnostics image.")
    ap.add_argument(
        "--panels", action="store_true", help="Also score the image's own static/Base/WorldTree panels."
    )
    args = ap.parse_args(argv)
    panels = read_panels(args.image)
    print("PSNR dB against the test-view panels (balloon / background)")
    if args.panels or not args.runs:
        for col in COLUMNS[2:]:
            print(_line(f"image's {col}", {t: panel_scores(p[col], p["test"]) for t, p in panels.items()}))
    for run in args.runs:
        print(_line(str(run), run_scores(run, panels)))


if __name__ == "__main__":
    import sys

    try:
        main()
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2) from None
