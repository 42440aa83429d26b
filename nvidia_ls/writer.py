"""File names and the ``cameras.json`` document of a built scene (layout: docs/scene_format.md)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from worldtree.scene_schema import CameraEntry, CamerasDoc, FrameEntry


def frame_file(index: int) -> str:
    """Relative path of training frame ``index``."""
    return f"images/{index:05d}.png"


def test_file(time: int) -> str:
    """Relative path of the test image at kept time ``time``."""
    return f"gt_images/v001_t{time:03d}.png"


def mask_file(time: int) -> str:
    """Relative path of the test mask at kept time ``time``."""
    return f"masks/v001_t{time:03d}.png"


def cameras_document(
    *,
    width: int,
    height: int,
    cameras: list[int],
    test_camera: int,
    Ks: np.ndarray,
    w2cs: np.ndarray,
    bounds: np.ndarray,
    frame_cameras: list[int],
    source_times: list[int],
    has_masks: bool,
    world_transform: dict,
) -> dict:
    """The ``cameras.json`` content (:class:`worldtree.scene_schema.CamerasDoc`, the one schema readers check).

    Args:
        width, height: stored image size.
        cameras: rig camera ids, in the order of ``Ks``/``w2cs``/``bounds``.
        test_camera: id of the held-out camera.
        Ks: ``[N, 3, 3]`` intrinsics for the stored size; w2cs: ``[N, 4, 4]`` OpenCV world-to-camera.
        bounds: ``[N, 2]`` near/far per camera (world units).
        frame_cameras: camera id of each training frame; source_times: raw time index of each kept time.
        has_masks: whether test masks are written.
        world_transform: ``{"scale", "R", "t", "note"}`` from the SfM frame to the stored world.
    """
    cams = [
        CameraEntry(
            id=int(cid),
            K=np.asarray(Ks[i]).tolist(),
            w2c=np.asarray(w2cs[i]).tolist(),
            dist=[0.0, 0.0, 0.0, 0.0, 0.0],
            near=float(bounds[i, 0]),
            far=float(bounds[i, 1]),
        )
        for i, cid in enumerate(cameras)
    ]
    frames = [
        FrameEntry(index=i, file=frame_file(i), camera=int(c), time=i, source_time=int(source_times[i]))
        for i, c in enumerate(frame_cameras)
    ]
    test_frames = [
        FrameEntry(
            index=t,
            file=test_file(t),
            mask=mask_file(t) if has_masks else None,
            camera=int(test_camera),
            time=t,
            source_time=int(s),
        )
        for t, s in enumerate(source_times)
    ]
    doc = CamerasDoc(
        width=int(width),
        height=int(height),
        test_camera=int(test_camera),
        cameras=cams,
        frames=frames,
        test_frames=test_frames,
        near=float(bounds[:, 0].min()),
        far=float(bounds[:, 1].max()),
        world_transform=world_transform,
    )
    return doc.to_json()


def save_image(path: str | Path, image: np.ndarray) -> None:
    """Write RGB uint8 ``[H, W, 3]`` or a bool/uint8 mask ``[H, W]`` (0/255) as PNG/JPG, without fsync.

    Only for files inside a folder made by :func:`worldtree.infra.atomic.atomic_dir`: the folder rename is what
    makes the output atomic, and skipping a per-file fsync makes writing thousands of frames much faster.
    """
    path = Path(path)
    arr = np.asarray(image)
    if arr.dtype == bool:
        arr = arr.astype(np.uint8) * 255
    if arr.ndim == 3:
        arr = cv2.cvtColor(arr, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(path.suffix, arr)
    if not ok:
        raise ValueError(f"cannot encode {path.suffix} image")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(buf.tobytes())
