"""The evaluation harness as a Python API: score predictions against ground truth under a named protocol.

>>> res = evaluate_folder("run/renders", "scene/test/images", "scene/test/masks", out_csv="run/metrics.csv")
>>> res.table.iloc[-1]   # the "mean" row

Frames are paired by file stem, read in background threads, scored in batches of one size on the chosen
device (CUDA when available), and written as a CSV plus a JSON record beside it. The rules for missing
LPIPS weights, infinite PSNR and empty masks are in docs/evaluation.md.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import math
import re
import shlex
import sys
import warnings
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from worldtree.imageio import as_uint8_array
from worldtree.infra import thread_governor
from worldtree.infra.cores import available_cores
from worldtree.infra.errors import UserError

#: CSV columns, in order.
COLUMNS = ("frame", "psnr", "ssim", "lpips", "avge", "mpsnr", "mssim", "mlpips", "mavge")
#: Pixels (H * W) scored together in one batch; bounds memory (about 40 bytes per pixel per frame).
BATCH_PIXELS = 2_000_000
MAX_BATCH = 16
#: CPU worker threads at most (each holds one frame's LPIPS activations, ~50 MB at 480x270).
MAX_CPU_WORKERS = 16


class EvalWarning(UserWarning):
    """Something the user should know about a finished evaluation (missing LPIPS, empty masks, inf PSNR)."""


@dataclass
class EvalResult:
    """Result of one evaluation.

    ``table``: one row per frame then a row whose ``frame`` is ``"mean"``; columns :data:`COLUMNS`; NaN
    where a value is not defined (written as an empty CSV cell). ``record``: the JSON record (protocol,
    LPIPS weights, input hashes, frame count, tool version, time, command, means, warnings).
    """

    table: pd.DataFrame
    record: dict[str, Any]

    @property
    def mean(self) -> pd.Series:
        """The ``mean`` row."""
        return self.table.iloc[-1]


@dataclass(frozen=True)
class FrameFiles:
    """Files of one frame, paired by stem."""

    name: str  #: the shared file stem, used as the frame name
    pred: Path
    gt: Path
    mask: Path | None


# ----------------------------------------------------------------------------------------------- pairing


def _natural_key(name: str) -> list:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def _by_stem(folder: Path, what: str) -> dict[str, Path]:
    from worldtree.imageio import list_images

    if not folder.is_dir():
        raise UserError(f"{what} {folder}: not a folder; give the folder holding the frames")
    files = list_images(folder)
    if not files:
        raise UserError(
            f"{what} {folder}: no PNG/JPG images there; point it at the folder holding the frames"
        )
    out: dict[str, Path] = {}
    for f in files:
        if f.stem in out:
            raise UserError(
                f"{what} {folder}: {out[f.stem].name} and {f.name} share the frame name {f.stem!r}; keep one"
            )
        out[f.stem] = f
    return out


def _listing(names: Sequence[str], limit: int = 8) -> str:
    names = sorted(names, key=_natural_key)
    more = f" and {len(names) - limit} more" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more


def pair_files(
    pred_dir: str | Path, gt_dir: str | Path, mask_dir: str | Path | None = None
) -> list[FrameFiles]:
    """Pair frames by file stem (``0001.png`` matches ``0001.jpg``), sorted naturally by name.

    Every ground-truth frame needs a prediction and vice versa, and with ``mask_dir`` every frame needs
    exactly one mask; otherwise a :class:`UserError` lists the unpaired names.
    """
    preds = _by_stem(Path(pred_dir), "predictions")
    gts = _by_stem(Path(gt_dir), "--gt")
    problems = []
    if missing := set(gts) - set(preds):
        problems.append(f"no prediction for {len(missing)} ground-truth frame(s): {_listing(missing)}")
    if extra := set(preds) - set(gts):
        problems.append(f"no ground truth for {len(extra)} prediction(s): {_listing(extra)}")
    masks: dict[str, Path] = {}
    if mask_dir is not None:
        masks = _by_stem(Path(mask_dir), "--masks")
        if missing := set(gts) - set(masks):
            problems.append(f"no mask for {len(missing)} frame(s): {_listing(missing)}")
        if extra := set(masks) - set(gts):
            problems.append(f"{len(extra)} mask(s) match no frame: {_listing(extra)}")
    if problems:
        raise UserError(
            f"frames of {pred_dir} and {gt_dir}"
            + (f" and {mask_dir}" if mask_dir else "")
            + " do not pair up: "
            + "; ".join(problems)
            + "; make the file names (without suffix) match"
        )
    if "mean" in gts:
        raise UserError(
            f"{gts['mean']}: a frame named 'mean' clashes with the mean row of the table; rename it"
        )
    return [FrameFiles(n, preds[n], gts[n], masks.get(n)) for n in sorted(gts, key=_natural_key)]


# ------------------------------------------------------------------------------------------------ inputs

Frame = tuple[np.ndarray, np.ndarray, "np.ndarray | None"]


def _read_frame(f: FrameFiles) -> Frame:
    from worldtree.imageio import read_image, read_mask

    pred, gt = read_image(f.pred), read_image(f.gt)
    if pred.shape != gt.shape:
        raise UserError(
            f"{f.pred} is {pred.shape[1]}x{pred.shape[0]} but {f.gt} is {gt.shape[1]}x{gt.shape[0]}; "
            "render at the ground-truth size"
        )
    mask = None
    if f.mask is not None:
        mask = read_mask(f.mask)
        if mask.shape != gt.shape[:2]:
            raise UserError(
                f"{f.mask} is {mask.shape[1]}x{mask.shape[0]} but {f.gt} is {gt.shape[1]}x{gt.shape[0]}; "
                "masks must have the image size"
            )
    return pred, gt, mask


def _as_uint8(a: np.ndarray, what: str) -> np.ndarray:
    a = np.asarray(a)
    if a.ndim != 3 or a.shape[2] != 3:
        raise UserError(f"{what}: expected an [H, W, 3] image, got shape {a.shape}")
    if a.dtype == np.uint8:
        return a
    if np.issubdtype(a.dtype, np.floating):
        if not np.isfinite(a).all():
            # A NaN would be scored as a black pixel: say so instead of scoring it.
            raise UserError(f"{what}: the image holds NaN or Inf values; check the method's render")
        # Quantise as a saved 8-bit image would be: values in [0, 1], rounded to the nearest level.
        return as_uint8_array(a)
    raise UserError(f"{what}: dtype {a.dtype} is not supported; pass uint8 or float in [0, 1]")


def _array_hash(arrays: Sequence[np.ndarray | None], names: Sequence[str]) -> str:
    h = hashlib.sha256()
    for n, a in zip(names, arrays, strict=True):
        if a is not None:
            h.update(f"{n} {a.dtype} {a.shape}\n".encode())
            h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


# ----------------------------------------------------------------------------------------------- scoring

_LPIPS_CACHE: dict[tuple, tuple] = {}


def _lpips_model(lpips_weights, device, warn_list: list[str]):
    """-> (model on device or None, record dict). ``lpips_weights``: folder, LPIPS instance, None or False."""
    import torch

    from benchmarks.evaluation import lpips_weights as lw
    from benchmarks.evaluation.lpips import LPIPS

    if lpips_weights is False:
        return None, {"net": "alex", "version": "0.1", "available": False, "reason": "disabled by the caller"}
    if isinstance(lpips_weights, LPIPS):
        rec = {
            "net": "alex",
            "version": "0.1",
            "available": True,
            "source": "in-memory model (files unchecked)",
        }
        return lpips_weights.to(device), rec
    try:
        folder = lw.locate(lpips_weights).path
    except lw.WeightsNotFound as e:
        warn_list.append(f"LPIPS columns (lpips, mlpips, avge, mavge) left empty: {e}")
        return None, {"net": "alex", "version": "0.1", "available": False, "reason": str(e)}
    # Checking and loading 240 MB costs seconds; reuse while the files are unchanged.
    files = (folder / lw.ALEXNET_FILE, folder / lw.LIN_FILE)
    key = tuple((str(p.resolve()), p.stat().st_size, p.stat().st_mtime_ns) for p in files)
    if key not in _LPIPS_CACHE:
        _LPIPS_CACHE.clear()
        _LPIPS_CACHE[key] = lw.load_lpips(folder, device=torch.device("cpu"))
    model, info = _LPIPS_CACHE[key]
    return model.to(device), {**info.record(), "available": True}


def _batches(shapes: Sequence[tuple[int, ...]], limit_pixels: int) -> list[list[int]]:
    """Consecutive indices grouped into runs of one shape, each of at most ``limit_pixels`` pixels."""
    out: list[list[int]] = []
    for i, s in enumerate(shapes):
        limit = max(1, min(MAX_BATCH, limit_pixels // max(1, s[0] * s[1])))
        if out and shapes[out[-1][0]] == s and len(out[-1]) < limit:
            out[-1].append(i)
        else:
            out.append([i])
    return out


def _score_all(
    n: int,
    load: Callable[[int], Frame],
    has_masks: bool,
    protocol,
    lpips,
    device,
    progress: Callable[[int], None] | None,
) -> dict[str, np.ndarray]:
    """Per-frame metrics for frames ``0..n-1`` read by ``load``.

    On the CPU each worker thread reads and scores one frame at a time with ONE intra-op thread, one
    worker per usable CPU (at most :data:`MAX_CPU_WORKERS`): frames are independent, and this avoids
    OpenMP threads spinning against each other on a busy machine. On CUDA, batches of frames (up to :data:`MAX_BATCH`, :data:`BATCH_PIXELS`)
    go to the device, with two batches in flight so that reading overlaps computing.
    """
    import torch

    results = {k: np.full(n, np.nan) for k in ("psnr", "ssim", "lpips", "mpsnr", "mssim", "mlpips")}
    cpu = device.type == "cpu"
    workers = min(MAX_CPU_WORKERS, available_cores()) if cpu else 2
    chunk = 1 if cpu else MAX_BATCH

    def task(idx: list[int], reader: ThreadPoolExecutor | None) -> tuple[list[int], dict[str, np.ndarray]]:
        if cpu:
            torch.set_num_threads(1)  # per thread: OpenMP's thread count is a per-thread setting
        frames = list(reader.map(load, idx)) if reader else [load(i) for i in idx]
        got: dict[str, np.ndarray] = {k: np.full(len(idx), np.nan) for k in results}
        for sub in _batches([fr[1].shape for fr in frames], BATCH_PIXELS):
            pred = torch.from_numpy(np.stack([frames[j][0] for j in sub])).to(device)
            gt = torch.from_numpy(np.stack([frames[j][1] for j in sub])).to(device)
            mask = torch.from_numpy(np.stack([frames[j][2] for j in sub])).to(device) if has_masks else None
            for k, v in protocol.score(pred, gt, mask, lpips).items():
                got[k][sub] = v.numpy()
        return idx, got

    chunks = [list(range(i, min(n, i + chunk))) for i in range(0, n, chunk)]
    with (
        thread_governor.threads_for_block(1 if cpu else torch.get_num_threads()),
        ThreadPoolExecutor(max_workers=workers) as pool,
        ThreadPoolExecutor(max_workers=4) if not cpu else contextlib.nullcontext() as reader,
    ):
        # Bounded look-ahead keeps at most 2 * workers chunks of images in memory.
        pending = [pool.submit(task, c, reader) for c in chunks[: 2 * workers]]
        next_chunk = len(pending)
        while pending:
            idx, got = pending.pop(0).result()
            for k, v in got.items():
                results[k][idx] = v
            if next_chunk < len(chunks):
                pending.append(pool.submit(task, chunks[next_chunk], reader))
                next_chunk += 1
            if progress:
                progress(len(idx))
    return results


def _finite_mean(v: np.ndarray) -> float:
    ok = np.isfinite(v)
    if ok.any():
        return float(v[ok].mean())
    return float("inf") if (v == np.inf).any() else float("nan")


def _build_table(names: Sequence[str], m: dict[str, np.ndarray], warn_list: list[str]) -> pd.DataFrame:
    from benchmarks.evaluation.metrics import avge

    df = pd.DataFrame({"frame": list(names), **m})
    df["avge"] = avge(df["psnr"], df["ssim"], df["lpips"])
    df["mavge"] = avge(df["mpsnr"], df["mssim"], df["lpips"])
    mean: dict[str, Any] = {"frame": "mean"}
    infinite = []
    for k in ("psnr", "mpsnr"):
        v = df[k].to_numpy()
        if np.isposinf(v).any():
            names_inf = [n for n, x in zip(names, v, strict=True) if x == np.inf]
            infinite.append(f"{k} = inf for {len(names_inf)} frame(s) ({_listing(names_inf)})")
        mean[k] = _finite_mean(v)
    if infinite:
        warn_list.append(
            "prediction identical to the ground truth: "
            + "; ".join(infinite)
            + "; the mean row averages the finite values (inf only if none is finite)"
        )
    for k in ("ssim", "lpips", "mssim", "mlpips"):
        v = df[k].to_numpy()
        mean[k] = float(np.nanmean(v)) if np.isfinite(v).any() else float("nan")
    # As in the paper's tables: AVGE of the mean row is computed from the mean PSNR, SSIM and LPIPS.
    mean["avge"] = float(avge(mean["psnr"], mean["ssim"], mean["lpips"]))
    mean["mavge"] = float(avge(mean["mpsnr"], mean["mssim"], mean["lpips"]))
    table = pd.concat([df, pd.DataFrame([mean])], ignore_index=True)
    return table[list(COLUMNS)]


def _mask_warnings(names, counts: np.ndarray | None, protocol, warn_list: list[str]) -> None:
    if counts is None:
        return
    empty = [n for n, c in zip(names, counts, strict=True) if c == 0]
    if empty:
        warn_list.append(
            f"{len(empty)} frame(s) have an empty mask, their masked metrics are left empty and out of the means: "
            f"{_listing(empty)}"
        )
    small = [n for n, c in zip(names, counts, strict=True) if 0 < c < protocol.min_mask_pixels]
    if small:
        warn_list.append(
            f"{len(small)} frame(s) have fewer than {protocol.min_mask_pixels} mask pixels, too few for "
            f"{protocol.name} masked SSIM (left empty): {_listing(small)}"
        )


def _evaluate(
    names: Sequence[str],
    load: Callable[[int], Frame],
    has_masks: bool,
    protocol: str,
    lpips_weights,
    device,
    inputs: dict[str, Any],
    progress,
) -> EvalResult:
    import torch

    import worldtree
    from benchmarks.evaluation.metrics import get_protocol
    from benchmarks.evaluation.metrics.protocols import LPIPS_MIN_SIDE
    from worldtree.infra.device import pick_device

    proto = get_protocol(protocol)
    dev = pick_device(device if not isinstance(device, torch.device) else str(device))
    warn_list: list[str] = []
    model, lpips_rec = _lpips_model(lpips_weights, dev, warn_list)
    mask_counts: list[tuple[int, int]] = []  # (frame index, masked pixels), appended by reader threads
    min_side = max(proto.min_side, LPIPS_MIN_SIDE if model is not None else 0)

    def counting_load(i: int) -> Frame:
        fr = load(i)
        h, w = fr[1].shape[:2]
        if min(h, w) < min_side:
            raise UserError(
                f"frame {names[i]} is {w}x{h}; the {proto.name} protocol needs at least {min_side} pixels per "
                f"side ({proto.min_side} for SSIM, {LPIPS_MIN_SIDE} for LPIPS)"
            )
        if fr[2] is not None:
            mask_counts.append((i, int(fr[2].sum())))
        return fr

    m = _score_all(len(names), counting_load, has_masks, proto, model, dev, progress)
    counts = None
    if has_masks:
        counts = np.zeros(len(names), dtype=np.int64)
        for i, c in mask_counts:
            counts[i] = c
    _mask_warnings(names, counts, proto, warn_list)
    table = _build_table(names, m, warn_list)
    mean = table.iloc[-1]
    record = {
        "tool": "worldtree-bench",
        "tool_version": worldtree.__version__,
        "timestamp": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "command": shlex.join(sys.argv),
        "protocol": proto.record(),
        "lpips": lpips_rec,
        "inputs": inputs,
        "frame_count": len(names),
        "masked": has_masks,
        "device": str(dev),
        "mean": {k: _json_number(mean[k]) for k in COLUMNS[1:]},
        "warnings": warn_list,
    }
    for w in warn_list:
        warnings.warn(w, EvalWarning, stacklevel=3)
    return EvalResult(table, record)


def _json_number(v) -> float | str | None:
    v = float(v)
    if math.isnan(v):
        return None
    if math.isinf(v):
        return "inf" if v > 0 else "-inf"
    return v


# -------------------------------------------------------------------------------------------- public API


def evaluate_folder(
    pred_dir: str | Path,
    gt_dir: str | Path,
    mask_dir: str | Path | None = None,
    protocol: str = "worldtree",
    out_csv: str | Path | None = None,
    lpips_weights=None,
    device=None,
    *,
    progress: Callable[[int], None] | None = None,
) -> EvalResult:
    """Score the images of ``pred_dir`` against those of ``gt_dir`` (and masks of ``mask_dir``).

    Frames are paired by file stem (:func:`pair_files`). ``protocol``: "worldtree" or "dycheck".
    ``lpips_weights``: a weights folder, an :class:`benchmarks.evaluation.lpips.LPIPS` instance, None (then
    ``$WTBENCH_LPIPS_WEIGHTS`` or the user cache; without weights the LPIPS columns stay empty and an
    :class:`EvalWarning` says how to install them), or False (no LPIPS, no warning). ``device``: "auto"/None, "cpu", "cuda", ... .
    ``out_csv``: when given, the table is written there and the record beside it (``.json``), atomically.
    ``progress``: called with the number of frames finished after each batch.
    Bad inputs raise :class:`UserError` naming the files.
    """
    from worldtree.infra.hashing import sha256_files

    frames = pair_files(pred_dir, gt_dir, mask_dir)
    inputs = {
        "pred_dir": str(Path(pred_dir).resolve()),
        "gt_dir": str(Path(gt_dir).resolve()),
        "mask_dir": str(Path(mask_dir).resolve()) if mask_dir is not None else None,
        "pred_sha256": sha256_files(f.pred for f in frames),
        "gt_sha256": sha256_files(f.gt for f in frames),
        "mask_sha256": sha256_files(f.mask for f in frames) if mask_dir is not None else None,
        "frames": [f.name for f in frames],
    }
    res = _evaluate(
        [f.name for f in frames],
        lambda i: _read_frame(frames[i]),
        mask_dir is not None,
        protocol,
        lpips_weights,
        device,
        inputs,
        progress,
    )
    if out_csv is not None:
        write_result(res, out_csv)
    return res


def evaluate_arrays(
    preds: Sequence[np.ndarray],
    gts: Sequence[np.ndarray],
    masks: Sequence[np.ndarray] | None = None,
    names: Sequence[str] | None = None,
    protocol: str = "worldtree",
    lpips_weights=None,
    device=None,
    *,
    progress: Callable[[int], None] | None = None,
) -> EvalResult:
    """Score in-memory frames: ``preds``, ``gts`` sequences of [H, W, 3] RGB (uint8, or float in [0, 1]
    which is quantised to uint8 first); ``masks`` of bool [H, W]; ``names`` default "0000", "0001", ....

    Same rules and result as :func:`evaluate_folder`; the record hashes the array bytes instead of files.
    """
    n = len(preds)
    if len(gts) != n or (masks is not None and len(masks) != n):
        raise UserError(
            f"{n} predictions, {len(gts)} ground-truth images"
            + (f" and {len(masks)} masks" if masks is not None else "")
            + ": pass one of each per frame"
        )
    if n == 0:
        raise UserError("no frames to evaluate: pass at least one prediction/ground-truth pair")
    names = [f"{i:04d}" for i in range(n)] if names is None else [str(s) for s in names]
    if len(names) != n or len(set(names)) != n or "mean" in names:
        raise UserError("names: give one distinct name per frame, none of them 'mean'")
    p = [_as_uint8(a, f"prediction {names[i]}") for i, a in enumerate(preds)]
    g = [_as_uint8(a, f"ground truth {names[i]}") for i, a in enumerate(gts)]
    mk = None if masks is None else [np.asarray(a).astype(bool) for a in masks]
    for i in range(n):
        if p[i].shape != g[i].shape:
            raise UserError(
                f"frame {names[i]}: prediction {p[i].shape} and ground truth {g[i].shape} differ in size"
            )
        if mk is not None and mk[i].shape != g[i].shape[:2]:
            raise UserError(f"frame {names[i]}: mask {mk[i].shape} does not match the image {g[i].shape[:2]}")
    inputs = {
        "pred_sha256": _array_hash(p, names),
        "gt_sha256": _array_hash(g, names),
        "mask_sha256": _array_hash(mk, names) if mk is not None else None,
        "frames": list(names),
    }
    return _evaluate(
        names,
        lambda i: (p[i], g[i], None if mk is None else mk[i]),
        mk is not None,
        protocol,
        lpips_weights,
        device,
        inputs,
        progress,
    )


def write_result(res: EvalResult, out_csv: str | Path) -> tuple[Path, Path]:
    """Write the table to ``out_csv`` (NaN as an empty cell, +inf as ``inf``) and the record beside it as
    ``<stem>.json``, each atomically. Returns both paths."""
    from worldtree.infra.atomic import atomic_write_json, atomic_write_text

    out_csv = Path(out_csv)
    if out_csv.suffix.lower() != ".csv":
        raise UserError(f"--out {out_csv}: the table is written as CSV; give a file name ending in .csv")
    out_json = out_csv.with_suffix(".json")
    record = {**res.record, "csv": out_csv.name}
    atomic_write_text(out_csv, res.table.to_csv(index=False, na_rep="", float_format="%.10g"))
    atomic_write_json(out_json, record)
    res.record = record
    return out_csv, out_json
