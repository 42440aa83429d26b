"""Readers for priors computed elsewhere (the networks the paper uses), with validation.

- Depth: a folder with one file per frame (sorted by name) or one file holding ``[T, H, W]``; ``.npy``,
  ``.npz`` (key ``depth``/``disparity``/the only array) or 16-bit PNG (value / ``png_scale``). Depth or
  disparity; maps of another size but the same aspect ratio are resized. Optional per-frame scale/shift fit to
  the classical depth.
- Tracks: CoTracker's layout, positions ``[T, N, 2]`` (pixels) + visibility ``[T, N]`` (bool or probability,
  > 0.5 visible); a leading batch axis of 1 is accepted. ``.npz``/``.pt`` with keys ``tracks`` + ``visibility``
  (or ``pred_tracks`` + ``pred_visibility``) and optionally ``image_size`` [W, H] (the size the positions refer
  to; other working sizes of the same aspect are rescaled); ``.npy`` holding ``[T, N, 3]`` (x, y, visibility)
  or ``[T, N, 2]`` (all visible).
- Flow: a folder of ``<i>_<j>.flo`` (Middlebury) or ``<i>_<j>.npy`` ``[H, W, 2]``, flow from frame i to j;
  fields of another size but the same aspect ratio (e.g. the scene's full size under a run's --downscale) are
  resized and their vectors scaled by the size ratio.
- Masks: a folder of one mask image per frame (sorted by name), white = dynamic.

Every problem raises :class:`worldtree.infra.errors.UserError` naming the file and the fix.
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from worldtree.imageio import read_mask
from worldtree.infra.errors import SettingError, UserError
from worldtree.priors.config import DepthImportConfig

DEPTH_SUFFIXES = (".npy", ".npz", ".png")
FLO_MAGIC = 202021.25


# ------------------------------------------------------------------------------------------------ depth
def load_numpy(path: Path) -> np.ndarray | dict[str, np.ndarray]:
    """A ``.npy`` file as its array, a ``.npz`` file as ``{name: array}``, read whole and checked: a file
    that is not what its suffix says, is cut short or damaged, or holds non-real numbers (strings,
    complex, objects) is a one-line :class:`UserError` naming it."""
    import zipfile
    import zlib

    what = {".npy": "numpy.save", ".npz": "numpy.savez"}.get(path.suffix.lower())
    if what is None:
        raise UserError(f"{path}: unsupported suffix {path.suffix!r}; use .npy or .npz")
    try:
        obj = np.load(path, allow_pickle=False)
        if isinstance(obj, np.lib.npyio.NpzFile):
            with obj:
                obj = {k: obj[k] for k in obj.keys()}  # read every member now: damage shows here
    # zipfile raises NotImplementedError for an unknown compression method and RuntimeError for an
    # encrypted member: damaged or foreign files too, not bugs.
    except (
        ValueError,
        OSError,
        EOFError,
        KeyError,
        NotImplementedError,
        RuntimeError,
        zipfile.BadZipFile,
        zlib.error,
    ) as e:
        raise UserError(f"{path}: cannot read ({e}); re-export it with {what}") from e
    if isinstance(obj, dict) != (path.suffix.lower() == ".npz"):
        held = "several named arrays (.npz)" if isinstance(obj, dict) else "one array (.npy)"
        raise UserError(
            f"{path}: holds {held}, not what its suffix says; rename it or re-export it with {what}"
        )
    for name, arr in obj.items() if isinstance(obj, dict) else [("", obj)]:
        if not (
            np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer) or arr.dtype == bool
        ):
            where = f"array {name!r}" if name else "the array"
            raise UserError(f"{path}: {where} holds {arr.dtype} values; save real numbers (float or int)")
    return obj


def _load_array(path: Path, keys: tuple[str, ...]) -> np.ndarray:
    obj = load_numpy(path)
    if not isinstance(obj, dict):
        return obj
    names = list(obj)
    for k in keys:
        if k in names:
            return obj[k]
    if len(names) == 1:
        return obj[names[0]]
    raise UserError(f"{path}: holds arrays {names}; name the wanted one one of {list(keys)}")


def _read_depth_file(path: Path, png_scale: float) -> np.ndarray:
    if path.suffix.lower() == ".png":
        data = np.fromfile(str(path), dtype=np.uint8)
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
        if img is None:
            raise UserError(f"{path}: cannot decode PNG; replace the file")
        if img.dtype != np.uint16 or img.ndim != 2:
            raise UserError(f"{path}: depth PNG must be single-channel 16-bit, got {img.dtype} {img.shape}")
        return img.astype(np.float32) / float(png_scale)
    return np.asarray(_load_array(path, ("depth", "disparity", "disp", "pred")), dtype=np.float32)


def _fit_size(arr: np.ndarray, H: int, W: int, path: Path) -> np.ndarray:
    h, w = arr.shape
    if (h, w) == (H, W):
        return arr
    if abs(w / h - W / H) > 0.01 * (W / H):
        raise UserError(f"{path}: map is {w}x{h}, frames are {W}x{H} (other aspect ratio); export at {W}x{H}")
    return cv2.resize(arr, (W, H), interpolation=cv2.INTER_LINEAR if h < H else cv2.INTER_AREA)


def read_depth(
    source: str | Path,
    num_frames: int,
    height: int,
    width: int,
    cfg: DepthImportConfig,
    notes: list[str] | None = None,
) -> np.ndarray:
    """Imported maps as ``[T, H, W]`` float32, still in the file's space (depth or disparity), validated.

    Maps of another size (same aspect) are resized; the first such resize adds a line to ``notes``."""
    src = Path(source)
    if src.is_dir():
        files = sorted(p for p in src.iterdir() if p.is_file() and p.suffix.lower() in DEPTH_SUFFIXES)
        if len(files) != num_frames:
            raise UserError(
                f"{src}: {len(files)} depth files (.npy/.npz/.png), the scene has {num_frames} frames; "
                "provide one file per training frame"
            )
        maps, raw_sizes = [], []
        for p in files:
            a = np.squeeze(_read_depth_file(p, cfg.png_scale))
            if a.ndim != 2:
                raise UserError(f"{p}: depth map has shape {a.shape}; expected [H, W]")
            raw_sizes.append(a.shape)
            maps.append(_fit_size(a, height, width, p))
        arr = np.stack(maps)
    elif src.is_file():
        arr = np.squeeze(_read_depth_file(src, cfg.png_scale))
        if arr.ndim == 2 and num_frames == 1:
            arr = arr[None]
        if arr.ndim != 3 or arr.shape[0] != num_frames:
            raise UserError(f"{src}: shape {arr.shape}; expected [T={num_frames}, H, W]")
        raw_sizes = [a.shape for a in arr]
        arr = np.stack([_fit_size(a, height, width, src) for a in arr])
    else:
        raise SettingError(
            "PriorsConfig.depth_source", src, "no such file or folder; pass 'classical' or an existing path"
        )
    other = sorted({(w, h) for h, w in raw_sizes if (h, w) != (height, width)})
    if notes is not None and other:
        notes.append(f"depth resized {', '.join(f'{w}x{h}' for w, h in other)} -> {width}x{height}")
    if not np.all(np.isfinite(arr)):
        raise UserError(f"{src}: depth maps contain NaN or Inf; clean them before import")
    if (arr < 0).any():
        raise UserError(f"{src}: negative {cfg.kind} values; export non-negative {cfg.kind}")
    if not (arr > 0).any():
        raise UserError(f"{src}: every {cfg.kind} value is 0; the files look empty")
    return arr.astype(np.float32)


def fit_scale_shift(pred: np.ndarray, target: np.ndarray, weight: np.ndarray) -> tuple[float, float]:
    """Weighted least-squares ``a, b`` minimising ``sum w (a pred + b - target)^2``; (1, 0) if degenerate."""
    w = weight.astype(np.float64).ravel()
    x = pred.astype(np.float64).ravel()
    y = target.astype(np.float64).ravel()
    sw = w.sum()
    if sw <= 0:
        return 1.0, 0.0
    mx, my = (w * x).sum() / sw, (w * y).sum() / sw
    vx = (w * (x - mx) ** 2).sum()
    if vx < 1e-12 * max(sw, 1.0):
        return 1.0, 0.0
    a = (w * (x - mx) * (y - my)).sum() / vx
    return float(a), float(my - a * mx)


def fit_scale(pred: np.ndarray, target: np.ndarray, weight: np.ndarray) -> tuple[float, float]:
    """Weighted least-squares ``a`` minimising ``sum w (a pred - target)^2`` (a line through the origin),
    returned as ``(a, 0.0)``; (1, 0) if degenerate (no weight or every weighted ``pred`` 0)."""
    w = weight.astype(np.float64).ravel()
    x = pred.astype(np.float64).ravel()
    y = target.astype(np.float64).ravel()
    sxx = (w * x * x).sum()
    if not (w.sum() > 0 and sxx > 0):
        return 1.0, 0.0
    return float((w * x * y).sum() / sxx), 0.0


def fit_scale_shift_robust(
    pred: np.ndarray,
    target: np.ndarray,
    weight: np.ndarray,
    trim: float | None,
    rounds: int = 3,
    shift: bool = True,
) -> tuple[float, float]:
    """:func:`fit_scale_shift` (``shift=False``: :func:`fit_scale`, ``b = 0``), then ``rounds`` refits without
    the pixels whose residual exceeds ``trim`` robust standard deviations (1.4826 x the weighted median
    absolute residual); ``trim=None``: plain fit."""
    line = fit_scale_shift if shift else fit_scale
    a, b = line(pred, target, weight)
    if trim is None:
        return a, b
    x = pred.astype(np.float64).ravel()
    y = target.astype(np.float64).ravel()
    w = weight.astype(np.float64).ravel()
    use = w > 0
    for _ in range(rounds):
        r = np.abs(a * x + b - y)
        if use.sum() < 3:
            break
        sigma = 1.4826 * float(np.median(r[use]))
        # Floor: exact data has residuals at rounding level; never trim those.
        floor = 1e-9 * max(float(np.abs(y[use]).max()), 1e-12)
        keep = use & (r <= trim * max(sigma, floor))
        if keep.sum() < 3 or keep.sum() == use.sum():
            break
        use = keep
        a, b = line(x[use], y[use], w[use])
    return a, b


def balanced_weights(x: np.ndarray, weight: np.ndarray, bins: int) -> np.ndarray:
    """``weight`` [...] rescaled so that each of ``bins`` equal-width bins of the value ``x`` [...] (between its
    1st and 99th weighted-in percentiles) carries the same total weight; ``bins <= 1`` returns ``weight``.

    A scale-and-shift fit of relative depth is a line through (imported, reference) pairs; a frame is mostly
    one far wall, so an unweighted fit is pinned at one end and the slope, which sets every nearer depth (a
    moving object close to the camera is an extrapolation), comes from a few pixels. Equal weight per value
    range spreads the leverage over the whole depth range seen."""
    w = np.asarray(weight, np.float64)
    use = w > 0
    if bins <= 1 or use.sum() < 2 * bins:
        return w
    lo, hi = np.percentile(x[use], [1.0, 99.0])
    if not hi > lo:
        return w
    idx = np.clip(((x - lo) / (hi - lo) * bins).astype(np.int64), 0, bins - 1)
    mass = np.bincount(idx[use], weights=w[use], minlength=bins)
    # Empty bins get no weight (nothing to spread); the others share the total mass equally.
    share = np.where(mass > 0, w.sum() / max(int((mass > 0).sum()), 1) / np.maximum(mass, 1e-300), 0.0)
    return w * share[idx]


def imported_to_depth(
    raw: np.ndarray,
    cfg: DepthImportConfig,
    ref_depth: np.ndarray | None = None,
    ref_conf: np.ndarray | None = None,
    min_depth: float = 1e-3,
    exclude: np.ndarray | None = None,
) -> np.ndarray:
    """Turn imported maps ``[T,H,W]`` into depth ``[T,H,W]``.

    With ``fit_scale_shift`` each frame is fitted to ``ref_depth`` (a scale and shift, or under
    ``cfg.fit_shift=False`` a scale alone; weights ``ref_conf``, rebalanced over the
    imported values' range by ``cfg.fit_balance_bins``) in the file's own space (disparity against
    1/ref_depth, depth against ref_depth) before any inversion; pixels where ``exclude`` [T,H,W] (bool) is set
    take no part in the fit (moving objects: the reference is the static world's depth, wrong there).
    Disparity 0 means infinitely far and is clamped to the largest finite depth of the frame.
    """
    out = np.empty_like(raw, dtype=np.float32)
    for t in range(raw.shape[0]):
        x = raw[t].astype(np.float64)
        if cfg.fit_scale_shift:
            if ref_depth is None:
                raise ValueError("fit_scale_shift needs the classical depth")
            target = 1.0 / np.maximum(ref_depth[t], 1e-9) if cfg.kind == "disparity" else ref_depth[t]
            w = (ref_conf[t] if ref_conf is not None else np.ones_like(x)) * (x > 0)
            if exclude is not None:
                w = w * ~exclude[t]
            w = balanced_weights(x, w, cfg.fit_balance_bins)
            a, b = fit_scale_shift_robust(x, target, w, cfg.fit_trim, shift=cfg.fit_shift)
            x = a * x + b
        if cfg.kind == "disparity":
            pos = x > 1e-9
            d = np.where(pos, 1.0 / np.where(pos, x, 1.0), np.nan)
            far = np.nanmax(d) if pos.any() else 1.0 / min_depth
            x = np.where(pos, d, far)
        out[t] = np.maximum(x, min_depth)
    return out


# ------------------------------------------------------------------------------------------------ tracks
def _load_tracks_obj(path: Path):
    suffix = path.suffix.lower()
    if suffix == ".pt":
        import torch

        try:
            obj = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as e:  # torch raises many types for a corrupt or unsafe file
            raise UserError(
                f"{path}: cannot load with torch.load(weights_only=True) ({e}); save plain tensors"
            ) from e
        if isinstance(obj, (tuple, list)) and len(obj) == 2:
            obj = {"tracks": obj[0], "visibility": obj[1]}
        try:
            if isinstance(obj, dict):
                out = {
                    str(k): np.asarray(v.detach().cpu().numpy() if hasattr(v, "detach") else v)
                    for k, v in obj.items()
                }
            else:
                out = {"": np.asarray(obj.detach().cpu().numpy() if hasattr(obj, "detach") else obj)}
        except (TypeError, ValueError, RuntimeError) as e:  # e.g. ragged lists, bfloat16 tensors
            raise UserError(f"{path}: holds values that are not arrays ({e}); save plain tensors") from e
        for name, arr in out.items():
            if not (np.issubdtype(arr.dtype, np.number) and not np.iscomplexobj(arr)) and arr.dtype != bool:
                where = f"entry {name!r}" if name else "the tensor"
                raise UserError(f"{path}: {where} holds {arr.dtype} values; save real-valued tensors")
        return out if isinstance(obj, dict) else out[""]
    if suffix in (".npz", ".npy"):
        return load_numpy(path)
    raise SettingError(
        "PriorsConfig.tracks_source", path, f"unsupported suffix {path.suffix!r}; use .npy, .npz or .pt"
    )


def _tracks_image_size(value, path: Path) -> tuple[int, int] | None:
    """``image_size`` entry of a tracks file as ``(W0, H0)``, or None when absent."""
    if value is None:
        return None
    size = np.asarray(value).reshape(-1)
    if size.size != 2 or not np.all(np.isfinite(size)) or np.any(size < 1) or np.any(size != np.round(size)):
        raise UserError(f"{path}: image_size {size.tolist()}; expected [W, H] in whole pixels")
    return int(size[0]), int(size[1])


def read_tracks(
    source: str | Path,
    num_frames: int,
    height: int,
    width: int,
    default_size: tuple[int, int] | None = None,
    notes: list[str] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """CoTracker-layout tracks: (``xy`` [T,N,2] float32 pixels, ``visible`` [T,N] bool), validated.

    Points outside the image (CoTracker predicts them) are marked not visible. A dict file (.npz/.pt) may
    name the size its positions refer to, ``image_size`` = [W0, H0]; a file without it refers to
    ``default_size`` ``(W0, H0)`` (``compute_priors`` passes the scene's stored size), or to ``width x height``
    when that is None too. When the size differs from ``width x height`` (e.g. the run's --downscale)
    positions are rescaled as ``(x + 0.5) * width / W0 - 0.5`` (y likewise) and a line is added to ``notes``.
    """
    path = Path(source)
    if not path.is_file():
        raise SettingError(
            "PriorsConfig.tracks_source", path,
            "no such file; pass 'classical' or an existing .npy/.npz/.pt file"
        )
    obj = _load_tracks_obj(path)
    if isinstance(obj, dict):
        tk = next((k for k in ("tracks", "pred_tracks") if k in obj), None)
        vk = next((k for k in ("visibility", "pred_visibility", "visibles") if k in obj), None)
        if tk is None or vk is None:
            raise UserError(
                f"{path}: keys {sorted(obj)}; expected 'tracks' and 'visibility' (or pred_tracks/pred_visibility)"
            )
        xy, vis = np.asarray(obj[tk]), np.asarray(obj[vk])
        src_size = _tracks_image_size(obj.get("image_size"), path)
    else:
        arr = np.asarray(obj)
        if arr.ndim == 4 and arr.shape[0] == 1:
            arr = arr[0]
        if arr.ndim != 3 or arr.shape[-1] not in (2, 3):
            raise UserError(
                f"{path}: array shape {arr.shape}; expected [T, N, 2] or [T, N, 3] (x, y, visibility)"
            )
        xy = arr[..., :2]
        vis = arr[..., 2] if arr.shape[-1] == 3 else np.ones(arr.shape[:2])
        src_size = None
    if src_size is None:
        src_size = default_size
    if xy.ndim == 4 and xy.shape[0] == 1:
        xy = xy[0]  # CoTracker's batch axis
    if vis.ndim == 4 and vis.shape[0] == 1:
        vis = vis[0]
    if vis.ndim == 3 and vis.shape[-1] == 1:
        vis = vis[..., 0]
    if vis.ndim == 3 and vis.shape[0] == 1:
        vis = vis[0]
    if xy.ndim != 3 or xy.shape[-1] != 2:
        raise UserError(f"{path}: track positions have shape {xy.shape}; expected [T, N, 2]")
    if vis.shape != xy.shape[:2]:
        raise UserError(
            f"{path}: visibility shape {vis.shape} does not match positions {xy.shape[:2]} ([T, N])"
        )
    if xy.shape[0] != num_frames:
        raise UserError(
            f"{path}: tracks span {xy.shape[0]} frames, the scene has {num_frames}; track the same video"
        )
    xy = xy.astype(np.float32)
    if not np.all(np.isfinite(xy)):
        raise UserError(f"{path}: track positions contain NaN or Inf; clean them before import")
    if src_size is not None and src_size != (width, height):
        w0, h0 = src_size
        if abs(w0 / h0 - width / height) > 0.01 * (width / height):
            raise UserError(
                f"{path}: image_size {w0}x{h0} has another aspect ratio than the {width}x{height} frames; "
                "track the scene's own images (SCENE/images)"
            )
        # Pixel centres at integers (OpenCV): the pixel edge -0.5 stays at -0.5 under the resize.
        xy = np.stack(
            [(xy[..., 0] + 0.5) * (width / w0) - 0.5, (xy[..., 1] + 0.5) * (height / h0) - 0.5], -1
        ).astype(np.float32)
        if notes is not None:
            notes.append(f"tracks rescaled {w0}x{h0} -> {width}x{height}")
    if vis.dtype == bool:
        visible = vis.copy()
    else:
        v = vis.astype(np.float64)
        if not np.all(np.isfinite(v)) or v.min() < 0 or v.max() > 1:
            raise UserError(f"{path}: visibility must be bool or probabilities in [0, 1]")
        visible = v > 0.5
    span = max(height, width)
    if np.abs(xy).max(initial=0.0) > 10 * span:
        raise UserError(
            f"{path}: positions reach {np.abs(xy).max():.0f} px for {width}x{height} frames; "
            "are they normalised or for another resolution? export pixel coordinates of these frames"
        )
    inside = (
        (xy[..., 0] >= -0.5)
        & (xy[..., 0] <= width - 0.5)
        & (xy[..., 1] >= -0.5)
        & (xy[..., 1] <= height - 0.5)
    )
    return xy, visible & inside


# ------------------------------------------------------------------------------------------------ flow
def read_flo(path: str | Path) -> np.ndarray:
    """Read a Middlebury ``.flo`` file: ``[H, W, 2]`` float32."""
    path = Path(path)
    raw = path.read_bytes()
    if len(raw) < 12 or np.frombuffer(raw[:4], "<f4")[0] != FLO_MAGIC:
        raise UserError(f"{path}: not a .flo file (bad magic number); write Middlebury .flo or .npy")
    w, h = (int(v) for v in np.frombuffer(raw[4:12], "<i4"))
    if w <= 0 or h <= 0 or len(raw) != 12 + 8 * w * h:
        raise UserError(
            f"{path}: header says {w}x{h} but the file holds {len(raw) - 12} data bytes; re-export it"
        )
    return np.frombuffer(raw[12:], "<f4").reshape(h, w, 2).copy()


def write_flo(path: str | Path, flow: np.ndarray) -> None:
    """Write ``[H, W, 2]`` flow as Middlebury ``.flo`` (used by tests and exports)."""
    from worldtree.infra.atomic import atomic_write_bytes

    h, w = flow.shape[:2]
    head = np.array([FLO_MAGIC], "<f4").tobytes() + np.array([w, h], "<i4").tobytes()
    atomic_write_bytes(path, head + np.ascontiguousarray(flow, "<f4").tobytes())


def resize_flow(flow: np.ndarray, height: int, width: int) -> np.ndarray:
    """Flow ``[h, w, 2]`` (pixels at ``w x h``) resampled to ``[height, width, 2]`` in pixels of the new size.

    Both grids share the image's edges (pixel centres at integers, ``x' = (x + 0.5) width / w - 0.5``), so a
    displacement scales by ``width / w`` along x and ``height / h`` along y; the field itself is resampled
    bilinearly when enlarged and by area averaging when shrunk.
    """
    h, w = flow.shape[:2]
    if (h, w) == (height, width):
        return flow.astype(np.float32, copy=True)
    interp = cv2.INTER_AREA if (width < w and height < h) else cv2.INTER_LINEAR
    out = cv2.resize(np.ascontiguousarray(flow, np.float32), (width, height), interpolation=interp)
    out[..., 0] *= width / w
    out[..., 1] *= height / h
    return out


_PAIR = re.compile(r"^(\d+)[_-](\d+)$")


def read_flows(
    source: str | Path, num_frames: int, height: int, width: int, notes: list[str] | None = None
) -> dict[tuple[int, int], np.ndarray]:
    """Flow fields ``{(i, j): [H, W, 2]}`` from a folder of ``<i>_<j>.flo`` / ``<i>_<j>.npy``, validated.

    Fields of another size with the frames' aspect ratio are resized by :func:`resize_flow`; each distinct
    resize adds a line to ``notes`` (recorded in the priors' sources)."""
    src = Path(source)
    if not src.is_dir():
        raise SettingError(
            "PriorsConfig.flow_source", src,
            "not a folder; pass 'classical' or a folder of <i>_<j>.flo/.npy files"
        )
    out: dict[tuple[int, int], np.ndarray] = {}
    for p in sorted(src.iterdir()):
        if p.suffix.lower() not in (".flo", ".npy"):
            continue
        m = _PAIR.match(p.stem)
        if not m:
            raise UserError(f"{p}: flow files must be named <i>_<j>{p.suffix} (frame indices); rename it")
        i, j = int(m.group(1)), int(m.group(2))
        if not (0 <= i < num_frames and 0 <= j < num_frames) or i == j:
            raise UserError(f"{p}: frame pair ({i}, {j}) is outside 0..{num_frames - 1} or repeats a frame")
        f = read_flo(p) if p.suffix.lower() == ".flo" else np.asarray(_load_array(p, ("flow",)), np.float32)
        if f.ndim == 3 and f.shape[0] == 2 and f.shape[-1] != 2:
            f = np.moveaxis(f, 0, -1)  # [2, H, W] as written by torch code
        if f.ndim != 3 or f.shape[-1] != 2 or min(f.shape[:2]) < 1:
            raise UserError(f"{p}: flow shape {f.shape}; expected [{height}, {width}, 2] for these frames")
        if not np.all(np.isfinite(f)):
            raise UserError(f"{p}: flow contains NaN or Inf; clean it before import")
        h, w = f.shape[:2]
        if (h, w) != (height, width):
            if abs(w / h - width / height) > 0.01 * (width / height):
                raise UserError(
                    f"{p}: flow shape {f.shape} has another aspect ratio than the {width}x{height} frames; "
                    f"expected [{height}, {width}, 2] (or any size of the same aspect)"
                )
            f = resize_flow(f, height, width)
            note = f"flow resized {w}x{h} -> {width}x{height} (vectors scaled)"
            if notes is not None and note not in notes:
                notes.append(note)
        out[(i, j)] = f.astype(np.float32)
    if not out:
        raise SettingError("PriorsConfig.flow_source", src, "no <i>_<j>.flo/.npy files found")
    return out


# ------------------------------------------------------------------------------------------------ masks
def read_masks(source: str | Path, num_frames: int, height: int, width: int) -> np.ndarray:
    """Dynamic masks ``[T, H, W]`` bool from a folder of one image per frame (sorted by name)."""
    src = Path(source)
    if not src.is_dir():
        raise SettingError(
            "PriorsConfig.masks_source", src,
            "not a folder; pass a folder with one mask image per training frame"
        )
    files = sorted(p for p in src.iterdir() if p.is_file() and p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    if len(files) != num_frames:
        raise UserError(
            f"{src}: {len(files)} mask images, the scene has {num_frames} frames; one mask per frame"
        )
    masks = []
    for p in files:
        m = read_mask(p)
        if m.shape != (height, width):
            if abs(m.shape[1] / m.shape[0] - width / height) > 0.01 * width / height:
                raise UserError(f"{p}: mask is {m.shape[1]}x{m.shape[0]}, frames are {width}x{height}")
            m = cv2.resize(m.astype(np.uint8) * 255, (width, height), interpolation=cv2.INTER_NEAREST) > 127
        masks.append(m)
    return np.stack(masks)
