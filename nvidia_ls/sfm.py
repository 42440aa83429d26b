"""Rig calibration by structure from motion (pycolmap) on the images of one time step.

The static rig sees the same scene from every camera at the same instant, so one time step is a static
multi-view capture: SIFT features, exhaustive matching, incremental mapping. Time steps are tried in turn
until one registers every camera.

Camera models: ``shared`` fits one SIMPLE_RADIAL camera (f, cx, cy, k) to all images (identical cameras,
much better constrained); ``per-camera`` fits one SIMPLE_RADIAL per image. Measured on the synthetic rig,
see docs/nvidia_ls.md.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nvidia_ls.layouts import RawCapture
from worldtree.imageio import write_image
from worldtree.infra.errors import UserError

CAMERA_MODELS = ("shared", "per-camera")


@dataclass
class SfmResult:
    """Calibrated rig in the SfM frame.

    Attributes:
        Ks: ``[N, 3, 3]`` OpenCV intrinsics (pixel centres at integer coordinates) at the raw image size.
        dists: ``[N, 5]`` OpenCV distortion ``(k1, k2, p1, p2, k3)``.
        w2cs: ``[N, 4, 4]`` world-to-camera (OpenCV), SfM frame.
        points: ``[P, 3]`` triangulated points (SfM frame).
        obs_point, obs_cam: ``[O]`` observations: point index and camera index (into ``Ks``) of each.
        time: the source time step that registered every camera.
        tried: the time steps tried, in order.
        reprojection_error: mean reprojection error (pixels).
        camera_model: "shared" or "per-camera".
    """

    Ks: np.ndarray
    dists: np.ndarray
    w2cs: np.ndarray
    points: np.ndarray
    obs_point: np.ndarray
    obs_cam: np.ndarray
    time: int
    tried: list[int]
    reprojection_error: float
    camera_model: str


def _camera_to_opencv(cam) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP camera -> OpenCV ``K`` and ``dist``. COLMAP puts pixel centres at +0.5, OpenCV at integers."""
    p = np.asarray(cam.params, np.float64)
    name = cam.model_name if hasattr(cam, "model_name") else str(cam.model)
    dist = np.zeros(5)
    if name in ("SIMPLE_RADIAL", "RADIAL", "SIMPLE_PINHOLE"):
        fx = fy = p[0]
        cx, cy = p[1], p[2]
        if name == "SIMPLE_RADIAL":
            dist[0] = p[3]
        elif name == "RADIAL":
            dist[0], dist[1] = p[3], p[4]
    elif name in ("PINHOLE", "OPENCV"):
        fx, fy, cx, cy = p[:4]
        if name == "OPENCV":
            dist[:4] = p[4:8]
    else:  # pragma: no cover - we only ask COLMAP for the models above
        raise UserError(f"SfM returned camera model {name}, which this tool does not convert")
    K = np.array([[fx, 0, cx - 0.5], [0, fy, cy - 0.5], [0, 0, 1.0]])
    return K, dist


def _run_once(images_dir: Path, work: Path, names: list[str], camera_model: str, threads: int, seed: int):
    import pycolmap

    pycolmap.logging.minloglevel = 2  # COLMAP's INFO lines would drown the progress display

    db = work / "database.db"
    if db.exists():
        db.unlink()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_RADIAL"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    extraction.use_gpu = False
    extraction.sift.max_num_features = 8192
    # Small rig images give few SIFT peaks at COLMAP's default threshold; a lower one keeps registration
    # well constrained (measured on the synthetic rig, docs/nvidia_ls.md).
    extraction.sift.peak_threshold = 0.004
    mode = pycolmap.CameraMode.SINGLE if camera_model == "shared" else pycolmap.CameraMode.PER_IMAGE
    pycolmap.extract_features(
        db,
        images_dir,
        image_names=names,
        camera_mode=mode,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )
    pycolmap.match_exhaustive(
        db, matching_options=cpu_matching(pycolmap, threads), device=pycolmap.Device.cpu
    )
    opts = narrow_baseline_mapping(pycolmap, threads, seed)
    opts.mapper.abs_pose_min_num_inliers = 20
    out = work / "sparse"
    out.mkdir(exist_ok=True)
    recs = pycolmap.incremental_mapping(db, images_dir, out, options=opts)
    if not recs:
        return None
    return max(recs.values(), key=lambda r: r.num_reg_images())


def cpu_matching(pycolmap, threads: int):
    """pycolmap's feature-matching options on the CPU with ``threads`` threads."""
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    matching.use_gpu = False
    return matching


def narrow_baseline_mapping(pycolmap, threads: int, seed: int):
    """pycolmap's incremental-mapping options for captures whose neighbouring views are a few degrees apart (a
    rig, a hand-held clip): one model, seeded, and smaller triangulation angles than COLMAP's defaults for
    wide-baseline photo collections (16 deg to start, 1.5 deg to keep a point), which discard most points."""
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = threads
    opts.random_seed = seed
    opts.multiple_models = False
    opts.mapper.init_min_tri_angle = 4.0
    opts.mapper.filter_min_tri_angle = 0.5
    opts.triangulation.min_angle = 0.5
    return opts


def run_sfm(
    raw: RawCapture,
    candidates: list[int],
    camera_model: str = "shared",
    threads: int = 2,
    seed: int = 0,
    log: Callable[[str], None] | None = None,
) -> SfmResult:
    """Calibrate the rig from the first candidate time step at which every camera registers.

    Args:
        raw: the capture.
        candidates: source time steps to try, in order.
        camera_model: "shared" or "per-camera".
        threads: CPU threads for pycolmap.
        seed: mapper random seed.
        log: optional callable for progress lines.

    Raises:
        UserError: when no candidate registers every camera.
    """
    if camera_model not in CAMERA_MODELS:
        raise UserError(f"--camera-model {camera_model!r}: choose one of {', '.join(CAMERA_MODELS)}")
    names = [f"cam{c:02d}.png" for c in raw.cameras]
    tried, best = [], (0, None)
    with tempfile.TemporaryDirectory(prefix="nvls_sfm_") as tmp:
        work = Path(tmp)
        for t in candidates:
            tried.append(t)
            images_dir = work / f"t{t:05d}"
            for c, name in zip(raw.cameras, names, strict=True):
                write_image(images_dir / name, raw.read(c, t))
            rec = _run_once(images_dir, work, names, camera_model, threads, seed)
            n_reg = 0 if rec is None else rec.num_reg_images()
            if log:
                log(f"SfM at time step {t}: {n_reg}/{len(names)} cameras registered")
            if n_reg > best[0]:
                best = (n_reg, t)
            if n_reg == len(names):
                return _result(rec, raw, names, t, tried, camera_model)
    raise UserError(
        f"SfM registered at most {best[0]} of {len(names)} cameras at the time steps tried ({tried}); "
        "pass --poses poses_bounds.npy, or raise --sfm-tries, or check the images (texture, overlap)"
    )


def _result(rec, raw: RawCapture, names: list[str], t: int, tried: list[int], camera_model: str) -> SfmResult:
    by_name = {img.name: img for img in rec.images.values()}
    Ks, dists, w2cs, img_index = [], [], [], {}
    for i, name in enumerate(names):
        img = by_name[name]
        K, dist = _camera_to_opencv(rec.cameras[img.camera_id])
        w2c = np.eye(4)
        w2c[:3, :4] = np.asarray(img.cam_from_world().matrix(), np.float64)
        Ks.append(K)
        dists.append(dist)
        w2cs.append(w2c)
        img_index[img.image_id] = i
    pts, obs_p, obs_c = [], [], []
    for k, (_, p3d) in enumerate(rec.points3D.items()):
        pts.append(np.asarray(p3d.xyz, np.float64))
        for el in p3d.track.elements:
            obs_p.append(k)
            obs_c.append(img_index[el.image_id])
    return SfmResult(
        Ks=np.stack(Ks),
        dists=np.stack(dists),
        w2cs=np.stack(w2cs),
        points=np.asarray(pts).reshape(-1, 3),
        obs_point=np.asarray(obs_p, np.int64),
        obs_cam=np.asarray(obs_c, np.int64),
        time=t,
        tried=tried,
        reprojection_error=float(rec.compute_mean_reprojection_error()),
        camera_model=camera_model,
    )


def sfm_candidates(times: list[int], tries: int) -> list[int]:
    """Time steps to try: the first, then ``tries - 1`` more spread evenly over the sequence."""
    if tries < 1:
        raise UserError(f"--sfm-tries {tries}: must be at least 1")
    if len(times) <= tries:
        return list(times)
    idx = np.unique(np.round(np.linspace(0, len(times) - 1, tries)).astype(np.int64))
    return [times[i] for i in idx]
