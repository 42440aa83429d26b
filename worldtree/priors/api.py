"""One interface to every 2D prior: :func:`compute_priors` (classical or imported, cached)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

import worldtree
from worldtree.infra.atomic import atomic_write_json
from worldtree.infra.errors import UserError
from worldtree.infra.hashing import sha256_file
from worldtree.infra.parallel import ordered_map, resolve_threads
from worldtree.pixels import as_uint8
from worldtree.priors import depth as depth_mod
from worldtree.priors import (
    depth_scale,
    dynamic_masks,
    dynamic_tracks,
    epipolar,
    flow,
    imported,
    object_flow,
    tracks,
)
from worldtree.priors.cache import CacheEntry, PriorCache, hash_key, inputs_fingerprint
from worldtree.priors.config import PriorsConfig, config_dict
from worldtree.priors.flow import FlowPair

ProgressFn = Callable[[str, int, int], None]
"""``progress(stage, done, total)``: called as work advances; stage is flow/depth/tracks/epipolar."""


@dataclass
class Priors:
    """All 2D priors of a video of T frames at H x W (numpy, float32 unless said).

    Attributes:
        depth: ``[T, H, W]`` depth along the camera z axis, scene units.
        depth_conf: ``[T, H, W]`` confidence in [0, 1]; 0 where filled or on dynamic-mask pixels.
        flow: ``{(i, j): FlowPair}`` flow from frame i to j ``[H, W, 2]`` pixels and its validity ``[H, W]``.
        tracks: ``[T, N, 2]`` point positions in pixels (x, y); placeholders where not visible.
        track_vis: ``[T, N]`` bool visibility.
        track_dynamic: ``[N]`` bool, the track lies on a dynamic pixel in >= ``epi.track_min_frames`` frames.
        epi_error: ``[T, H, W]`` epipolar (Sampson) error in pixels, max over flow pairs.
        epi_mask: ``[T, H, W]`` bool dynamic mask (EPI threshold, or the imported masks).
        sources: where each prior came from (``classical`` or ``imported:<path>``).
        mask_conf: ``[T, H, W]`` confidence in [0, 1] of the dynamic masks (the fused motion evidence; the
            mask itself for imported masks and plain EPI masks).
        motion_evidence: ``{cue: [T, H, W]}`` evidence of each motion cue (``worldtree.priors.motion_cues``),
            kept so the masks can be refined once a static model exists; empty when not fused.
        num_chained_tracks: how many of the last tracks were chained through flow inside the masks
            (``worldtree.priors.dynamic_tracks``; all dynamic).
        config: the settings used.
        cache_dir: the cache root, or None when nothing was cached.
        depth_metric: ``depth`` agrees with the cameras (classical, or imported and fitted to them).
        track_pieces: ``[N]`` chained pieces linked into each track (1 for the others); None without chaining.
        depth_fill: under ``depth_import.merge="fill"``, the imported depth refitted without a dynamic mask:
            ``mask [T, H, W] bool -> depth [T, H, W]`` (scene units), for masks refined later; None otherwise.
    """

    depth: np.ndarray
    depth_conf: np.ndarray
    flow: dict[tuple[int, int], FlowPair]
    tracks: np.ndarray
    track_vis: np.ndarray
    track_dynamic: np.ndarray
    epi_error: np.ndarray
    epi_mask: np.ndarray
    sources: dict[str, str]
    mask_conf: np.ndarray | None = None
    motion_evidence: dict[str, np.ndarray] = field(default_factory=dict)
    num_chained_tracks: int = 0
    config: PriorsConfig = field(default_factory=PriorsConfig)
    cache_dir: Path | None = None
    depth_metric: bool = False
    track_pieces: np.ndarray | None = None
    depth_fill: Callable[[np.ndarray], np.ndarray] | None = field(default=None, repr=False)

    def identical(self, other: Priors) -> bool:
        """Every array of the two (depth, confidences, flow pairs, tracks, masks, epipolar errors) equal bit for
        bit; the sources and settings are not compared."""
        arrays = ("depth", "depth_conf", "tracks", "track_vis", "track_dynamic", "epi_error", "epi_mask")
        same_flow = self.flow.keys() == other.flow.keys() and all(
            np.array_equal(f.flow, other.flow[k].flow) and np.array_equal(f.valid, other.flow[k].valid)
            for k, f in self.flow.items()
        )
        masks = (self.mask_conf is None) == (other.mask_conf is None) and (
            self.mask_conf is None or np.array_equal(self.mask_conf, other.mask_conf)
        )
        return (
            same_flow and masks and all(np.array_equal(getattr(self, n), getattr(other, n)) for n in arrays)
        )

    @property
    def num_frames(self) -> int:
        return int(self.depth.shape[0])

    def torch(self, device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
        """Dense per-frame priors as tensors on ``device`` (depth, depth_conf, tracks, ... ; not the flow)."""
        names = ("depth", "depth_conf", "tracks", "track_vis", "track_dynamic", "epi_error", "epi_mask")
        return {n: torch.from_numpy(np.ascontiguousarray(getattr(self, n))).to(device) for n in names}


def _scene_arrays(scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    imgs_u8 = as_uint8(scene.images.detach().cpu()).numpy()
    return imgs_u8, scene.Ks.detach().cpu().double().numpy(), scene.w2cs.detach().cpu().double().numpy()


def _path_digest(path: str) -> dict:
    p = Path(path)
    if p.is_file():
        return {"path": str(p), "sha256": sha256_file(p)}
    if p.is_dir():
        return {"path": str(p), "files": {q.name: sha256_file(q) for q in sorted(p.iterdir()) if q.is_file()}}
    return {"path": str(p), "missing": True}


def _tick(progress: ProgressFn | None, stage: str, done: int, total: int) -> None:
    if progress is not None:
        progress(stage, done, total)


# ------------------------------------------------------------------------------------------------ stages
def _flows(
    imgs, cfg: PriorsConfig, cache: PriorCache, fp: str, progress, init=None, fields=None
) -> tuple[dict, str, str]:
    """Flow pairs; ``init`` = (depth [T,H,W], Ks, w2cs, depth_key) starts DIS from the rigid flow;
    ``fields`` are the imported flows ({(i, j): [H,W,2]}) when ``cfg.flow_source`` is a folder."""
    T, H, W = imgs.shape[:3]
    pairs = [(i, j) for i, j in flow.flow_pairs(T, cfg.flow.offsets) if i < j]
    if cfg.flow_source != "classical":
        out = {}
        for (i, j), f in fields.items():
            # The FB check needs the reverse field; without it only landing inside and colour are checked.
            gi, gj = flow.to_gray_u8(imgs[i]), flow.to_gray_u8(imgs[j])
            out[(i, j)] = flow.FlowPair(f, flow.pair_validity(gi, gj, f, fields.get((j, i)), cfg.flow))
        key = hash_key("flow-imported", _path_digest(cfg.flow_source), fp, cfg.flow)
        src = f"imported:{cfg.flow_source}"
        missing = [(i, j) for i, j in pairs if (i, j) not in fields and (j, i) not in fields]
        if cfg.flow.import_missing == "classical" and missing:
            # A folder that holds neighbours only (DynamicNeRF's RAFT) leaves out the wider gaps, whose other
            # viewing directions are what tests motion along one pair's epipolar lines.
            dis, dis_key, _ = _classical_flows(imgs, cfg, cache, fp, progress, init, missing, complete=False)
            out.update(dis)
            key = hash_key(key, dis_key)
            gaps = sorted({j - i for i, j in missing})
            src += f" + classical DIS for the {len(missing)} pairs it lacks (gaps {', '.join(map(str, gaps))})"
        return out, key, src
    return _classical_flows(imgs, cfg, cache, fp, progress, init, pairs)


def _classical_flows(
    imgs, cfg: PriorsConfig, cache: PriorCache, fp: str, progress, init, pairs: list[tuple[int, int]],
    complete: bool = True,
) -> tuple[dict, str, str]:
    """OpenCV DIS flow of ``pairs`` (i < j; both directions), cached per pair under the key of the whole
    classical flow, so a subset reuses a full run's cache and the other way round; only the whole set
    (``complete``) marks the entry complete."""
    if not cfg.flow.init_from_depth:
        init = None
    settings = cfg.flow.dis_settings()
    key = hash_key("flow", fp, settings, None if init is None else init[3])
    meta = {"inputs": fp, "settings": config_dict(settings), "init_depth": None if init is None else init[3]}
    entry = cache.entry("flow", key, meta)
    grays = [flow.to_gray_u8(im) for im in imgs]
    out: dict[tuple[int, int], flow.FlowPair] = {}

    def compute(ij: tuple[int, int]) -> tuple[dict, bool]:
        i, j = ij
        got = entry.load(f"{i:05d}_{j:05d}") if entry is not None else None
        if got is not None:
            return got, False
        init_ij = init_ji = None
        if init is not None:
            dep, Ks, w2cs, _ = init
            init_ij = flow.rigid_flow(dep[i], Ks[i], w2cs[i], Ks[j], w2cs[j])
            init_ji = flow.rigid_flow(dep[j], Ks[j], w2cs[j], Ks[i], w2cs[i])
        fw, bw = flow.compute_pair(grays[i], grays[j], cfg.flow, init_ij, init_ji)
        # Stored as float16 (half the cache; step < 0.02 px under 32 px, < 0.07 px under 128 px); the
        # fresh result is rounded the same way so a cached rerun returns identical values.
        return {"fwd": fw.flow.astype(np.float16), "fwd_valid": fw.valid,
                "bwd": bw.flow.astype(np.float16), "bwd_valid": bw.valid}, True  # fmt: skip

    results = ordered_map(compute, pairs, resolve_threads(cfg.threads))
    for n, ((i, j), (got, fresh)) in enumerate(zip(pairs, results, strict=True)):
        if fresh and entry is not None:
            entry.save(f"{i:05d}_{j:05d}", **got)
        fw = flow.FlowPair(got["fwd"].astype(np.float32), got["fwd_valid"])
        bw = flow.FlowPair(got["bwd"].astype(np.float32), got["bwd_valid"])
        out[(i, j)], out[(j, i)] = fw, bw
        _tick(progress, "flow", n + 1, len(pairs))
    if entry is not None and complete:
        entry.mark_complete()
    return out, key, "classical"


def _classical_depth(imgs, Ks, w2cs, near, far, cfg: PriorsConfig, cache: PriorCache, fp: str, progress):
    d = cfg.depth
    near = d.near if d.near is not None else near
    far = d.far if d.far is not None else far
    if not (np.isfinite(near) and np.isfinite(far) and 0 < near < far):
        raise UserError(f"depth bounds near={near}, far={far} are invalid; fix cameras.json or pass near/far")
    key = hash_key("depth", fp, d, near, far)
    entry = cache.entry("depth", key, {"inputs": fp, "settings": config_dict(d), "near": near, "far": far})
    T = len(imgs)
    depth = np.empty(imgs.shape[:3], np.float32)
    conf = np.empty(imgs.shape[:3], np.float32)

    def compute(t: int) -> tuple[np.ndarray, np.ndarray, bool]:
        got = entry.load(f"{t:05d}") if entry is not None else None
        if got is not None:
            return got["depth"], got["conf"], False
        r = depth_mod.frame_depth(t, imgs, Ks, w2cs, near, far, d)
        return r.depth, r.conf, True

    # Saved from this thread in frame order, so an interrupted run leaves whole frames only.
    for t, (dep, cf, fresh) in enumerate(ordered_map(compute, range(T), resolve_threads(cfg.threads))):
        if fresh and entry is not None:
            entry.save(f"{t:05d}", depth=dep, conf=cf)
        depth[t], conf[t] = dep, cf
        _tick(progress, "depth", t + 1, T)
    if entry is not None:
        entry.mark_complete()
    return depth, conf, key


def _stored_size(scene) -> tuple[int, int] | None:
    """``(W, H)`` of the scene's stored images (cameras.json), which imported files without a size of
    their own refer to; None for a scene that was not loaded from a folder."""
    root = getattr(scene, "root", None)
    if root is None or not (Path(root) / "cameras.json").is_file():
        return None
    from worldtree.scene_schema import read_cameras

    doc = read_cameras(root)
    return doc.width, doc.height


def _with_notes(source: str, notes: list[str]) -> str:
    return f"{source} [{'; '.join(notes)}]" if notes else source


def _depth(imgs, Ks, w2cs, scene, cfg: PriorsConfig, cache, fp, progress, notes=None):
    """(depth [T,H,W], conf [T,H,W], source, key of the metric depth or None when it is not metric, the
    function ``dynamic mask [T,H,W] or None -> fitted imported depth [T,H,W]`` under ``merge="fill"``, or
    None; under ``fill_static="classical"`` the classical depth and confidence [T,H,W] the static pixels keep,
    else None)."""
    T, H, W = imgs.shape[:3]
    if cfg.depth_source == "classical":
        d, c, key = _classical_depth(imgs, Ks, w2cs, scene.near, scene.far, cfg, cache, fp, progress)
        return d, c, "classical", key, None, None
    di = cfg.depth_import
    if di.merge not in ("replace", "fill"):
        raise UserError(f"priors.depth_import.merge={di.merge!r}: choose replace or fill")
    if di.merge == "fill" and not di.fit_scale_shift:
        raise UserError(
            "priors.depth_import.merge=fill needs priors.depth_import.fit_scale_shift=true: "
            "the imported depth must be in the classical depth's scale to fill it"
        )
    raw = imported.read_depth(cfg.depth_source, T, H, W, di, notes=notes)
    ref = ref_conf = None
    key = None
    if di.fit_scale_shift:
        ref, ref_conf, ref_key = _classical_depth(
            imgs, Ks, w2cs, scene.near, scene.far, cfg, cache, fp, progress
        )
        key = hash_key("depth-imported", _path_digest(cfg.depth_source), di, ref_key)
    d = imported.imported_to_depth(raw, di, ref, ref_conf)
    fit = ""
    if di.fit_scale_shift:
        fit = ", scale/shift fitted to classical" if di.fit_shift else ", scale fitted to classical"
    src = f"imported:{cfg.depth_source} ({di.kind}{fit})"
    if di.merge == "fill":
        keep = ref_conf >= di.fill_min_conf
        depth = np.where(keep, ref, d).astype(np.float32)
        conf = np.where(keep, ref_conf, di.fill_conf).astype(np.float32)

        def fill(mask: np.ndarray | None) -> np.ndarray:
            # Dynamic pixels get the import once the masks are known, refitted without them.
            if mask is None or not di.fit_exclude_dynamic:
                return d
            return imported.imported_to_depth(
                raw, di, ref, ref_conf, exclude=_dilate(mask, di.fit_exclude_px)
            )

        note = "on dynamic pixels" if di.fill_static == "classical" else "where unconfident and on dynamic pixels"
        if di.fit_exclude_dynamic:
            note += " (refitted without them)"
        stereo = (ref, ref_conf) if di.fill_static == "classical" else None
        return depth, conf, f"classical, filled from {src} {note}", key, fill, stereo
    # Network depth carries no confidence of its own: trust it everywhere.
    return d, np.ones_like(d), src, key, None, None


def _scale_to_cameras(depth, source: str, flows, Ks, w2cs, cfg: PriorsConfig, flow_key: str):
    """Imported depth times the factor that makes it agree with the cameras (``fit_global_scale``):
    ``(depth [T,H,W], source, key)``; the key marks the depth as metric, None when the scale was not
    observable (no parallax), which leaves the depth as it was."""
    di = cfg.depth_import
    fit = depth_scale.fit_depth_scale(
        depth, flows, Ks, w2cs, di.scale_max_residual_px, di.scale_min_parallax_px
    )
    if not fit.observable:
        return depth, f"{source}, scale not observable ({fit.matches} flow matches with parallax)", None
    key = hash_key("depth-imported-scaled", _path_digest(cfg.depth_source), di, flow_key)
    note = f"{source}, x{fit.scale:.4g} to the cameras ({fit.matches} flow matches, spread {fit.spread:.3f})"
    return (depth * fit.scale).astype(np.float32), note, key


def _tracks(
    imgs, cfg: PriorsConfig, cache: PriorCache, fp: str, progress, init=None
) -> tuple[np.ndarray, np.ndarray, str]:
    """Classical tracks; ``init`` = (depth [T,H,W], Ks, w2cs, depth_key) seeds Lucas-Kanade's search."""
    T = imgs.shape[0]
    if not cfg.tracks.init_from_depth:
        init = None
    key = hash_key("tracks", fp, cfg.tracks, None if init is None else init[3])
    meta = {
        "inputs": fp,
        "settings": config_dict(cfg.tracks),
        "init_depth": None if init is None else init[3],
    }
    entry = cache.entry("tracks", key, meta)
    got = entry.load("all") if entry is not None and entry.complete else None
    if got is not None:
        _tick(progress, "tracks", T, T)
        return got["xy"], got["visible"], "classical"
    # Tracking carries state from frame to frame, so it restarts from frame 0 when interrupted (it is fast).
    predict = tracks.depth_predictor(*init[:3]) if init is not None else None
    tr = tracks.track_video(
        imgs, cfg.tracks, on_frame=lambda t: _tick(progress, "tracks", t + 1, T), predict=predict
    )
    if entry is not None:
        entry.save("all", xy=tr.xy, visible=tr.visible, seed_frame=tr.seed_frame)
        entry.mark_complete()
    return tr.xy, tr.visible, "classical"


def _epi_errors(flows, Ks, w2cs, T, cfg: PriorsConfig, cache, flow_key: str, progress) -> np.ndarray:
    key = hash_key("epipolar", flow_key, cfg.epi, np.round(Ks, 9), np.round(w2cs, 9))
    entry: CacheEntry | None = cache.entry(
        "epipolar", key, {"flow_key": flow_key, "settings": config_dict(cfg.epi)}
    )
    got = entry.load("all") if entry is not None and entry.complete else None
    if got is not None:
        _tick(progress, "epipolar", T, T)
        return got["error"].astype(np.float32)
    use = cfg.epi.use_poses
    err = epipolar.epipolar_error_maps(
        flows, T, Ks if use else None, w2cs if use else None, cfg.epi,
        on_frame=lambda t: _tick(progress, "epipolar", t + 1, T), threads=resolve_threads(cfg.threads),
    )  # fmt: skip
    # Stored as float16; the fresh result is rounded the same way so that a cached rerun is identical.
    err = err.astype(np.float16).astype(np.float32)
    if entry is not None:
        entry.save("all", error=err.astype(np.float16))
        entry.mark_complete()
    return err


def _dilate(mask: np.ndarray, px: int) -> np.ndarray:
    """``mask`` [T,H,W] (bool) grown by ``px`` pixels in every frame."""
    if px <= 0:
        return mask.astype(bool)
    k = np.ones((2 * px + 1, 2 * px + 1), np.uint8)
    return np.stack([cv2.dilate(m.astype(np.uint8), k) > 0 for m in mask])


def _refill_dynamic(
    depth, conf, mask, imgs, cfg: PriorsConfig, refill: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Zero the confidence on dynamic pixels and (``refill``) replace their depth by the edge-aware fill.

    Multi-view stereo assumes a static world, so its matches on moving objects are noise; the fill is a
    smooth guess from the surrounding static surfaces (confidence 0 says so). Without ``refill`` the sweep's
    value stays, unconfident.
    """
    if not refill:
        return depth.astype(np.float32), np.where(mask, 0.0, conf).astype(np.float32)
    depth, conf = depth.copy(), conf.copy()

    def fill(t: int) -> np.ndarray | None:
        w = np.where(mask[t], 0.0, conf[t]).astype(np.float32)
        if not (w > 0).any():
            return None
        return depth_mod.edge_aware_fill(
            1.0 / np.maximum(depth[t], 1e-9), w, imgs[t], cfg.depth.fill_lambda, cfg.depth.fill_sigma
        )

    frames = np.flatnonzero(mask.reshape(len(mask), -1).any(1)).tolist()
    for t, inv in zip(frames, ordered_map(fill, frames, resolve_threads(cfg.threads)), strict=True):
        if inv is None:
            continue
        depth[t] = np.where(mask[t], 1.0 / np.maximum(inv, 1e-9), depth[t])
        conf[t] = np.where(mask[t], 0.0, conf[t])
    return depth.astype(np.float32), conf.astype(np.float32)


def add_chained_tracks(
    xy, vis, dynamic, flows, mask, cfg: PriorsConfig, images=None, depth=None, Ks=None, w2cs=None, stats=None
):
    """Append the tracks chained through flow inside ``mask`` [T, H, W] to ``xy`` [T, N, 2] / ``vis`` [T, N]
    / ``dynamic`` [N]; the tracks already on the masks are kept. Returns ``(xy, vis, dynamic, added, pieces)``
    with ``pieces`` [N + added] the track pieces linked into each track (1 for the tracks given).

    ``images`` [T, H, W, 3], metric ``depth`` [T, H, W], ``Ks`` [T, 3, 3] and ``w2cs`` [T, 4, 4] (numpy) let the
    linking of track pieces compare appearance and remove the camera's motion; ``stats`` (a dict) receives
    the linking counts (and, with ``motion.object_flow``, the object matches' counts).

    With ``cfg.motion.object_flow`` and ``images``, the chaining's flow pairs are first recomputed inside
    ``mask`` from each object's template-matched displacement (:mod:`worldtree.priors.object_flow`); ``flows``
    itself is not changed."""
    if cfg.motion.object_flow and images is not None:
        flows = object_flow.object_flows(
            flows,
            mask,
            images,
            cfg.motion,
            cfg.flow,
            depth,
            Ks,
            w2cs,
            stats,
            threads=resolve_threads(cfg.threads),
        )
    ch = dynamic_tracks.chain_dynamic_tracks(flows, mask, cfg.motion, images, depth, Ks, w2cs, stats)
    pieces = np.ones(vis.shape[1], np.int64)
    if ch.num_tracks == 0:
        return xy, vis, dynamic, 0, pieces
    xy = np.concatenate([xy, ch.xy.astype(xy.dtype)], 1)
    vis = np.concatenate([vis, ch.visible], 1)
    dynamic = np.concatenate([dynamic, np.ones(ch.num_tracks, bool)])
    return xy, vis, dynamic, ch.num_tracks, np.concatenate([pieces, ch.pieces])


# ------------------------------------------------------------------------------------------------ entry point
def compute_priors(
    scene,
    cfg: PriorsConfig | None = None,
    cache_dir: str | Path | None = None,
    progress: ProgressFn | None = None,
) -> Priors:
    """Compute (or load from the cache) every prior of ``scene`` (a :class:`worldtree.scene.Scene`).

    Args:
        scene: training frames ``images`` [T,H,W,3] in [0,1], ``Ks`` [T,3,3], ``w2cs`` [T,4,4], near/far.
        cfg: settings and sources; defaults to classical priors with default settings.
        cache_dir: cache root; None computes everything and stores nothing.
        progress: optional ``progress(stage, done, total)`` callback.

    Returns:
        :class:`Priors`. A ``priors.json`` record (sources, keys, settings, version, shapes) is written to the
        cache root when there is one.
    """
    # OpenCV splits some filters (the fast global smoother) into stripes by its thread count, and the
    # results depend on the split in the last bits: single-threaded OpenCV inside, with the frames spread
    # over a pool instead (PriorsConfig.threads), gives the same priors on any machine.
    old_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        return _compute_priors(scene, cfg, cache_dir, progress)
    finally:
        cv2.setNumThreads(old_threads)


def _compute_priors(scene, cfg: PriorsConfig | None, cache_dir, progress: ProgressFn | None) -> Priors:
    cfg = cfg or PriorsConfig()
    imgs, Ks, w2cs = _scene_arrays(scene)
    T, H, W = imgs.shape[:3]
    if T < 2:
        raise UserError(f"scene {scene.name}: {T} training frame(s); priors need at least 2")
    cache = PriorCache(cache_dir)
    fp = inputs_fingerprint(imgs, Ks, w2cs)

    # Read imported tracks, masks and flow first, so a bad file fails before any long computation. Each
    # follows the working size (a run's --downscale); the resizes are recorded in the sources.
    resized: dict[str, list[str]] = {"tracks": [], "flow": [], "depth": []}
    imported_tracks = None
    if cfg.tracks_source != "classical":
        imported_tracks = imported.read_tracks(
            cfg.tracks_source, T, H, W, default_size=_stored_size(scene), notes=resized["tracks"]
        )
    mask = None
    if cfg.masks_source is not None:
        mask = imported.read_masks(cfg.masks_source, T, H, W)
    fields = None
    if cfg.flow_source != "classical":
        fields = imported.read_flows(cfg.flow_source, T, H, W, notes=resized["flow"])
    # Depth first: metric depth and the poses predict where static pixels go, which guides flow and tracks.
    depth, depth_conf, depth_src, depth_key, fill, stereo = _depth(
        imgs, Ks, w2cs, scene, cfg, cache, fp, progress, notes=resized["depth"]
    )
    init = (depth, Ks, w2cs, depth_key) if depth_key is not None else None
    flows, flow_key, flow_src = _flows(imgs, cfg, cache, fp, progress, init, fields)
    flow_src = _with_notes(flow_src, resized["flow"])
    if depth_key is None and cfg.depth_source != "classical" and cfg.depth_import.fit_global_scale:
        depth, depth_src, depth_key = _scale_to_cameras(depth, depth_src, flows, Ks, w2cs, cfg, flow_key)
        init = (depth, Ks, w2cs, depth_key) if depth_key is not None else None
    depth_src = _with_notes(depth_src, resized["depth"])
    if imported_tracks is not None:
        xy, vis = imported_tracks
        tracks_src = _with_notes(f"imported:{cfg.tracks_source}", resized["tracks"])
    else:
        xy, vis, tracks_src = _tracks(imgs, cfg, cache, fp, progress, init)
    err = _epi_errors(flows, Ks, w2cs, T, cfg, cache, flow_key, progress)
    evidence: dict[str, np.ndarray] = {}
    if mask is not None:
        mask_src = f"imported:{cfg.masks_source}"
        mask_conf = mask.astype(np.float32)
    elif cfg.motion.enabled:
        # Motion discovery: epipolar and depth-consistency cues fused (the residual cue joins after the
        # static warm-up, in the methods). Depth is metric only when classical or fitted. Under
        # fill_static="classical" the depth-consistency cue tests the flow against stereo: the import, an
        # extrapolation where stereo is unsure of static content, marked such strips as moving on Balloon1.
        metric = (depth if stereo is None else stereo[0]) if depth_key is not None else None
        evidence = dynamic_masks.prior_evidence(
            err, flows, metric, Ks, w2cs, cfg.motion, cfg.epi, threads=resolve_threads(cfg.threads)
        )
        fused = dynamic_masks.fuse(evidence, flows, cfg.motion, cfg.epi)
        mask, mask_conf = fused.mask, fused.confidence
        mask_src = f"motion cues ({', '.join(evidence)})"
    else:
        mask = epipolar.epi_masks(err, cfg.epi)
        mask_conf = mask.astype(np.float32)
        mask_src = f"epipolar (threshold {cfg.epi.threshold_px} px)"
    dynamic = epipolar.label_dynamic_tracks(xy, vis, mask, cfg.epi.track_min_frames)
    if depth_src == "classical":
        # An imported mask outlines whole objects: the fill would put each at the depth behind it
        # (`DepthConfig.fill_imported_masks`).
        refill = cfg.masks_source is None or cfg.depth.fill_imported_masks
        depth, depth_conf = _refill_dynamic(depth, depth_conf, mask, imgs, cfg, refill)
    elif fill is not None:
        # Stereo on moving objects is noise even where it looks confident: the network depth replaces it.
        if stereo is not None:
            # The import guided the flow and the tracks on the moving objects before the masks were known;
            # the static pixels now keep the stereo depth and confidence (fill_static="classical").
            depth, depth_conf = stereo
        depth = np.where(mask, fill(mask), depth).astype(np.float32)
        depth_conf = np.where(mask, cfg.depth_import.fill_conf, depth_conf).astype(np.float32)
    n_chained, pieces = 0, None
    links: dict[str, int] = {}
    if cfg.motion.enabled and imported_tracks is None:
        # After the refill: the camera's share of a moving point's motion is taken at the depth of the
        # surfaces around it, not at the stereo noise on the object.
        metric = depth if depth_key is not None else None
        xy, vis, dynamic, n_chained, pieces = add_chained_tracks(
            xy, vis, dynamic, flows, mask, cfg, imgs, metric, Ks, w2cs, links
        )

    sources = {"flow": flow_src, "depth": depth_src, "tracks": tracks_src, "masks": mask_src}
    pri = Priors(depth, depth_conf, flows, xy, vis, dynamic, err, mask, sources, mask_conf, evidence, n_chained,
                 cfg, Path(cache_dir) if cache_dir is not None else None, depth_key is not None,
                 pieces, fill)  # fmt: skip
    if cache_dir is not None:
        atomic_write_json(
            Path(cache_dir) / "priors.json",
            {
                "version": worldtree.__version__,
                "scene": scene.name,
                "inputs": fp,
                "frames": T,
                "size": [W, H],
                "sources": sources,
                "resized": {k: v for k, v in resized.items() if v},
                "config": config_dict(cfg),
                "num_tracks": int(xy.shape[1]),
                "num_dynamic_tracks": int(dynamic.sum()),
                "num_chained_tracks": n_chained,
                "chained_track_links": links,
                "dynamic_pixel_fraction": float(mask.mean()),
            },
        )
    return pri
