"""Cameras of a monocular clip by incremental SfM (pycolmap), with features on moving objects left out.

1. **Moving-pixel masks** (:func:`moving_masks`): the motion cues of :mod:`worldtree.priors` without poses.
   DIS optical flow between neighbouring frames (forward-backward checked), a fundamental matrix per pair
   fitted to the flow with LMedS, the Sampson distance of every pixel's flow to it (the epipolar error), fused
   over the pairs and carried along the flow to the neighbours (temporal agreement), thresholded and cleaned
   (:mod:`worldtree.priors.dynamic_masks`). A moving object's flow leaves the static epipolar geometry, so its
   pixels stand out; motion along the epipolar lines stays unseen (the limit of every epipolar test).
2. **SfM** (:func:`clip_sfm`): SIFT extracted with the masks as COLMAP feature masks (``ImageReaderOptions
   .mask_path``: no keypoint where the mask is 0), sequential matching (each frame against its next
   ``SEQUENTIAL_OVERLAP`` frames, plus quadratic gaps), incremental mapping with one shared SIMPLE_RADIAL camera
   held at COLMAP's guess (focal 1.2 x the longer side, principal point at the centre, k1 = 0), then two global
   bundle adjustments (Cauchy loss) with every pose and point: the focal alone, then focal and k1.

Everything is written under a work folder the caller gives (inside the scene's temporary folder), so nothing
outside the output folder is created.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from nvidia_ls.sfm import _camera_to_opencv, cpu_matching, narrow_baseline_mapping
from nvidia_ls.writer import save_image
from worldtree.infra.errors import UserError

MASK_WORK_SIDE = 320
"""The masks are computed on frames shrunk to at most this many pixels on the longer side (flow is the cost).
On the generated 480x270 clips SfM came out closer to the truth at 320 than at 480 (max rotation error 0.22-0.86
against 0.38-0.95 deg over 5 seeds); on the real train clip at 320 the masks miss most of the slow train (0.4 %
of the pixels masked against 6 % at 480), with the same 80 of 80 frames registered and the same focal."""
MASK_DILATE_FRAC = 0.01
"""Masks grow by this fraction of the longer image side: SIFT's support reaches past an object's border."""
MAX_MASKED_FRAC = 0.5
"""A frame whose mask covers more than this is taken as a failed estimate (not a moving object) and unmasked."""
SEQUENTIAL_OVERLAP = 10
"""Sequential matching: each frame is matched with this many following frames (plus quadratic gaps)."""


@dataclass
class ClipCameras:
    """SfM of a clip, in the SfM frame.

    Attributes:
        registered: ``[T]`` bool, frame registered.
        K: ``[3, 3]`` shared OpenCV intrinsics (pixel centres at integers) at the frames' size.
        dist: ``[5]`` OpenCV distortion ``(k1, 0, 0, 0, 0)``.
        w2cs: ``[T, 4, 4]`` world-to-camera (OpenCV) of every frame; identity where not registered.
        points: ``[P, 3]`` triangulated points.
        obs_point, obs_frame: ``[O]`` observations: point index and frame index of each.
        reprojection_error: mean reprojection error (pixels).
        focal_guess: the initial focal length (pixels) bundle adjustment started from.
    """

    registered: np.ndarray
    K: np.ndarray
    dist: np.ndarray
    w2cs: np.ndarray
    points: np.ndarray
    obs_point: np.ndarray
    obs_frame: np.ndarray
    reprojection_error: float
    focal_guess: float


def moving_masks(frames: np.ndarray, tick: Callable[[int, int], None] | None = None) -> np.ndarray:
    """``[T, H, W]`` bool, true on pixels that move against the static scene, from ``frames`` [T, H, W, 3] uint8.

    Computed at :data:`MASK_WORK_SIDE`, brought back to the frames' size, dilated by :data:`MASK_DILATE_FRAC`; a
    frame masked over :data:`MAX_MASKED_FRAC` is left unmasked (see the module docstring)."""
    from worldtree.priors.config import EpiConfig, FlowConfig, MotionConfig
    from worldtree.priors.dynamic_masks import fuse, prior_evidence
    from worldtree.priors.epipolar import epipolar_error_maps
    from worldtree.priors.flow import compute_flows

    T, H, W = frames.shape[:3]
    s = min(1.0, MASK_WORK_SIDE / max(H, W))
    w, h = max(16, round(W * s)), max(16, round(H * s))
    small = (
        np.stack([cv2.resize(f, (w, h), interpolation=cv2.INTER_AREA) for f in frames]) if s < 1 else frames
    )
    # Neighbouring frames only: a video's next frame is close, so the flow holds; the gap-3 pairs of the
    # priors add little here and double the cost.
    pairs_done = [0]

    def on_pair(_i: int, _j: int) -> None:
        pairs_done[0] += 1
        if tick:
            tick(pairs_done[0], T - 1)

    flows = compute_flows(small, FlowConfig(offsets=(1,)), on_pair=on_pair)
    epi = EpiConfig(use_poses=False)  # no poses yet: F from the flow itself (LMedS)
    motion = MotionConfig()
    err = epipolar_error_maps(flows, T, None, None, epi)
    ev = prior_evidence(err, flows, None, np.zeros((T, 3, 3)), np.zeros((T, 4, 4)), motion, epi)
    masks = fuse(ev, flows, motion, epi).mask
    r = max(1, round(MASK_DILATE_FRAC * max(H, W)))
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    out = np.zeros((T, H, W), bool)
    for t in range(T):
        m = masks[t].astype(np.uint8)
        if (w, h) != (W, H):
            m = cv2.resize(m, (W, H), interpolation=cv2.INTER_NEAREST)
        m = cv2.dilate(m, disk) > 0
        out[t] = m if m.mean() <= MAX_MASKED_FRAC else False
    return out


def clip_sfm(
    frames: np.ndarray,
    masks: np.ndarray | None,
    work: Path,
    threads: int = 1,
    seed: int = 0,
    stage: Callable[[str, int, int], None] | None = None,
) -> ClipCameras | None:
    """Incremental SfM over ``frames`` [T, H, W, 3] uint8 (in clip order), ``masks`` [T, H, W] bool (true =
    moving: no feature there) or None; scratch files under ``work``. ``stage(name, done, total)`` reports
    progress. None when SfM registers no frame at all (the caller words the error for the clip)."""
    import pycolmap

    pycolmap.logging.minloglevel = 2  # COLMAP's INFO lines would drown the progress display
    say = stage or (lambda _n, _d, _t: None)
    T, H, W = frames.shape[:3]
    images, mask_dir = work / "images", work / "masks"
    names = [f"{t:05d}.png" for t in range(T)]
    for t, name in enumerate(names):
        save_image(images / name, frames[t])
        if masks is not None:
            # COLMAP reads the mask of image NAME as NAME.png; features are kept where it is non-zero.
            save_image(mask_dir / f"{name}.png", ~masks[t])
        say("sfm: writing frames", t + 1, T)
    db = work / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_RADIAL"
    if masks is not None:
        reader.mask_path = str(mask_dir)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    extraction.use_gpu = False
    extraction.sift.max_num_features = 8192
    # Small frames give few SIFT peaks at COLMAP's default threshold (the rig measurement, docs/nvidia_ls.md).
    extraction.sift.peak_threshold = 0.004
    say("sfm: features", 0, T)
    pycolmap.extract_features(
        db, images, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
        extraction_options=extraction, device=pycolmap.Device.cpu,
    )  # fmt: skip
    say("sfm: matching", 0, T)
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = SEQUENTIAL_OVERLAP
    pairing.quadratic_overlap = True
    pycolmap.match_sequential(
        db,
        matching_options=cpu_matching(pycolmap, threads),
        pairing_options=pairing,
        device=pycolmap.Device.cpu,
    )

    # A hand-held clip moves a little per frame, as the rig's cameras are a few degrees apart.
    opts = narrow_baseline_mapping(pycolmap, threads, seed)
    # The intrinsics stay at COLMAP's guess while the frames register, and are refined at the end. Refined from
    # the first pair on (COLMAP's default), a short-baseline pair lets focal and k1 run off (focal x5 on the
    # generated clip) and no third frame registers; fixed, every frame registers, and the final bundle
    # adjustments bring the focal within 2.5 % of the truth (docs/nvidia_ls.md, "Your own video").
    opts.ba_refine_focal_length = False
    opts.ba_refine_extra_params = False
    rec = _map_and_refine(pycolmap, db, images, work / "sparse", opts, T, say)
    if rec is None:
        return None  # no initial pair: nothing registered (the caller's error names the clip)
    return _cameras(rec, names, W, H)


def _map_and_refine(pycolmap, db: Path, images: Path, out: Path, opts, T: int, say):
    """Incremental mapping with the camera held fixed, then global bundle adjustments that refine its focal (then
    focal and k1) with every pose and point. The model with the most registered frames, or None."""
    registered = [0]

    def next_image() -> None:
        registered[0] += 1
        say("sfm: mapping", min(registered[0], T), T)

    out.mkdir(parents=True, exist_ok=True)
    say("sfm: mapping", 0, T)
    recs = pycolmap.incremental_mapping(db, images, out, options=opts, next_image_callback=next_image)
    rec = max(recs.values(), key=lambda r: r.num_reg_images()) if recs else None
    if rec is None or rec.num_reg_images() == 0:
        return None
    # The focal first, k1 held at 0; then both. Freed together from a guess 39 % long, they settled in a wrong
    # model on 2 of 6 generated clips (40-75 deg off, focal 3-26 % off, k1 up to -2).
    for step, extra in enumerate((False, True)):
        say("sfm: refining the camera", step, 2)
        ba = pycolmap.BundleAdjustmentOptions()
        ba.refine_focal_length = True
        ba.refine_extra_params = extra
        ba.print_summary = False
        # A few wrong matches (a moving object the masks missed) must not pull the focal length.
        ba.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
        # The adjuster itself, not pycolmap.bundle_adjustment: that wrapper turns COLMAP's INFO log back on.
        config = pycolmap.BundleAdjustmentConfig()
        for image_id, img in rec.images.items():
            if img.has_pose:
                config.add_image(image_id)
        config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
        pycolmap.create_default_bundle_adjuster(ba, config, rec).solve()
    return rec


def _cameras(rec, names: list[str], W: int, H: int) -> ClipCameras:
    T = len(names)
    index = {n: t for t, n in enumerate(names)}
    registered = np.zeros(T, bool)
    w2cs = np.tile(np.eye(4), (T, 1, 1))
    frame_of_image: dict[int, int] = {}
    K = dist = None
    for img in rec.images.values():
        if not img.has_pose:
            continue
        t = index[img.name]
        registered[t] = True
        w2cs[t, :3, :4] = np.asarray(img.cam_from_world().matrix(), np.float64)
        frame_of_image[img.image_id] = t
        if K is None:
            K, dist = _camera_to_opencv(rec.cameras[img.camera_id])
    pts, obs_p, obs_f = [], [], []
    for k, p3d in enumerate(rec.points3D.values()):
        pts.append(np.asarray(p3d.xyz, np.float64))
        for el in p3d.track.elements:
            if el.image_id in frame_of_image:
                obs_p.append(k)
                obs_f.append(frame_of_image[el.image_id])
    return ClipCameras(
        registered=registered, K=K, dist=dist, w2cs=w2cs, points=np.asarray(pts, np.float64).reshape(-1, 3),
        obs_point=np.asarray(obs_p, np.int64), obs_frame=np.asarray(obs_f, np.int64),
        reprojection_error=float(rec.compute_mean_reprojection_error()), focal_guess=1.2 * max(W, H),
    )  # fmt: skip


def frame_bounds(
    points: np.ndarray, obs_point: np.ndarray, obs_frame: np.ndarray, w2cs: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """``(bounds [T, 2], depths [O])``: per frame, near/far = 0.9 x the 1st and 1.1 x the 99th percentile of
    the depths of the SfM points it observes (the whole model's where it sees fewer than 5), as ``nvls build``
    does; ``depths`` are the z of every observation ``obs_point``/``obs_frame`` in its frame's camera."""
    cam = np.einsum("nij,nj->ni", w2cs[obs_frame, :3, :3], points[obs_point]) + w2cs[obs_frame, :3, 3]
    depths = cam[:, 2]
    front = depths[depths > 0]
    if front.size == 0:
        raise UserError("SfM triangulated no point in front of the cameras")
    bounds = np.zeros((len(w2cs), 2))
    for t in range(len(w2cs)):
        d = depths[(obs_frame == t) & (depths > 0)]
        d = d if d.size >= 5 else front
        bounds[t] = [0.9 * np.percentile(d, 1), 1.1 * np.percentile(d, 99)]
    return bounds, depths
