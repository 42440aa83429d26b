"""Speed of `wtbench eval` against a naive per-frame scikit-image loop; prints frames per second.

    python -m benchmarks.speed.eval [--frames 160] [--width 480] [--height 270] [--device auto]

Generates ``--frames`` prediction / ground-truth / mask PNGs (seeded noise over smooth images) in a
temporary folder, then times, each reading the files from disk:

1. the naive loop: per frame read the three files, then scikit-image PSNR and SSIM (defaults), and the
   worldtree protocol's masked PSNR and SSIM of the masked BGR value vectors;
2. ``evaluate_folder`` (worldtree protocol) computing the same four metrics (LPIPS off);
3. ``evaluate_folder`` with LPIPS too (installed weights if found, else random weights of the same shape);
4. the same for the dycheck protocol.

Timings depend on the machine and its load; run it on an idle machine to compare.
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np


def make_frames(folder: Path, frames: int, width: int, height: int, seed: int = 0) -> None:
    """Write pred/, gt/, mask/ PNGs: smooth colour ramps plus noise, and a moving disc as the mask."""
    from worldtree.imageio import write_image

    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width]
    for d in ("pred", "gt", "mask"):
        (folder / d).mkdir(parents=True, exist_ok=True)
    for t in range(frames):
        base = np.stack([xx / width, yy / height, (xx + yy + t) % 64 / 64.0], -1) * 255
        gt = np.clip(base + rng.normal(0, 8, base.shape), 0, 255).astype(np.uint8)
        pred = np.clip(gt + rng.normal(0, 6, base.shape), 0, 255).astype(np.uint8)
        cx, cy = width * (0.2 + 0.6 * t / max(1, frames - 1)), height / 2
        mask = (xx - cx) ** 2 + (yy - cy) ** 2 < (0.2 * height) ** 2
        name = f"v000_t{t:03d}.png"
        write_image(folder / "gt" / name, gt)
        write_image(folder / "pred" / name, pred)
        write_image(folder / "mask" / name, mask)


def naive_loop(folder: Path) -> list[tuple[float, float, float, float]]:
    """Per-frame scikit-image scores, as a plain script would compute them."""
    try:  # the reference of this comparison only; not a dependency of the toolkit
        from skimage.metrics import peak_signal_noise_ratio, structural_similarity
    except ImportError as e:
        raise SystemExit(
            f"error: this speed script needs scikit-image ({e}); pip install 'worldtree-bench[speed]'"
        ) from e

    from worldtree.imageio import list_images, read_image, read_mask

    out = []
    for p in list_images(folder / "pred"):
        pred, gt = read_image(p), read_image(folder / "gt" / p.name)
        m = read_mask(folder / "mask" / p.name)
        m3 = np.repeat(m[..., None], 3, axis=2)
        pb, gb = pred[..., ::-1], gt[..., ::-1]
        out.append(
            (
                peak_signal_noise_ratio(gt, pred),
                structural_similarity(gt, pred, channel_axis=-1),
                peak_signal_noise_ratio(gb[m3], pb[m3]),
                structural_similarity(gb[m3], pb[m3]),
            )
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=160)
    ap.add_argument("--width", type=int, default=480)
    ap.add_argument("--height", type=int, default=270)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--repeats", type=int, default=1, help="best of this many runs is reported")
    args = ap.parse_args()

    import torch

    from benchmarks.evaluation import lpips_weights as lw
    from benchmarks.evaluation.evaluate import evaluate_folder
    from benchmarks.evaluation.lpips import LPIPS, random_state_dicts

    warnings.simplefilter("ignore")
    try:
        lpips_model, lpips_src = lw.load_lpips()[0], "installed weights"
    except Exception:
        lpips_model = LPIPS.from_state_dicts(*random_state_dicts(0))
        lpips_src = "random weights (none installed)"

    def best(fn) -> float:
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        return min(times)

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        make_frames(folder, args.frames, args.width, args.height)
        n = args.frames
        print(
            f"{n} frames {args.width}x{args.height} with masks; device {args.device}; "
            f"torch threads {torch.get_num_threads()}; best of {args.repeats}"
        )
        ref = naive_loop(folder)
        t_naive = best(lambda: naive_loop(folder))
        res = evaluate_folder(
            folder / "pred", folder / "gt", folder / "mask", lpips_weights=False, device=args.device
        )
        got = res.table.iloc[:-1][["psnr", "ssim", "mpsnr", "mssim"]].to_numpy(float)
        err = float(np.abs(got - np.asarray(ref)).max())
        t_ours = best(
            lambda: evaluate_folder(
                folder / "pred", folder / "gt", folder / "mask", lpips_weights=False, device=args.device
            )
        )
        rows = [
            ("naive scikit-image loop (PSNR, SSIM, mPSNR, mSSIM)", t_naive),
            ("wtbench eval worldtree, same metrics (no LPIPS)", t_ours),
        ]
        for proto in ("worldtree", "dycheck"):
            rows.append(
                (
                    f"wtbench eval {proto}, all metrics, LPIPS {lpips_src}",
                    best(
                        lambda p=proto: evaluate_folder(
                            folder / "pred",
                            folder / "gt",
                            folder / "mask",
                            protocol=p,
                            lpips_weights=lpips_model,
                            device=args.device,
                        )
                    ),
                )
            )
        for label, t in rows:
            print(f"{label:<75} {n / t:8.1f} frames/s  ({t:.2f} s)")
        print(
            f"speed-up over the naive loop (same metrics): {t_naive / t_ours:.2f}x; "
            f"max |difference| of the per-frame values: {err:.2e}"
        )


if __name__ == "__main__":
    main()
