"""The loaded scene every method trains on: a monocular training video plus a held-out test camera.

One loader, :func:`load_scene`, reads the NVIDIA-LS layout written by ``nvls build`` (``docs/scene_format.md``)
through the typed document of :mod:`worldtree.scene_schema`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from worldtree.imageio import read_image, read_mask
from worldtree.infra.errors import SettingError, UserError
from worldtree.scene_schema import read_cameras, resolve_inside


@dataclass
class Scene:
    """A loaded scene. Images are ``uint8`` as read (:mod:`worldtree.pixels`: :func:`~worldtree.pixels.unit_float`
    gives float32 in [0, 1]; a hand-made scene may hold float images instead); poses are OpenCV world-to-camera.

    Attributes:
        name: scene folder name.
        root: scene folder.
        images: ``[T, H, W, 3]`` training frames.
        Ks: ``[T, 3, 3]`` intrinsics of each training frame (pixels, for the loaded size).
        w2cs: ``[T, 4, 4]`` world-to-camera pose of each training frame.
        frame_cameras: ``[T]`` rig camera id of each training frame.
        times: ``[T]`` time index of each training frame (0..T-1).
        test_images: ``[T_test, H, W, 3]`` test-camera images.
        test_K: ``[3, 3]`` test-camera intrinsics.
        test_w2c: ``[4, 4]`` test-camera pose (the rig is static, so one pose for all times).
        test_times: ``[T_test]`` time index of each test image.
        test_masks: ``[T_test, H, W]`` bool dynamic-region masks, or None.
        test_files: names of the test images (``v001_tXXX.png``), used to name renders.
        near, far: scene depth bounds in world units.
    """

    name: str
    root: Path
    images: torch.Tensor
    Ks: torch.Tensor
    w2cs: torch.Tensor
    frame_cameras: torch.Tensor
    times: torch.Tensor
    test_images: torch.Tensor
    test_K: torch.Tensor
    test_w2c: torch.Tensor
    test_times: torch.Tensor
    test_masks: torch.Tensor | None
    test_files: list[str]
    near: float
    far: float

    @property
    def num_frames(self) -> int:
        return int(self.images.shape[0])

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    def to(self, device: torch.device | str) -> Scene:
        """Copy of the scene with every tensor on ``device``."""
        kw = {}
        for k, v in self.__dict__.items():
            kw[k] = v.to(device) if isinstance(v, torch.Tensor) else v
        return Scene(**kw)


def _resize(img: np.ndarray, scale: int) -> np.ndarray:
    if scale == 1:
        return img
    h, w = img.shape[:2]
    return cv2.resize(img, (w // scale, h // scale), interpolation=cv2.INTER_AREA)


def _scaled_K(K: np.ndarray, scale: int) -> np.ndarray:
    # Pixel centres move with the resize: x' = (x + 0.5) / s - 0.5.
    K = K.astype(np.float64).copy()
    K[0, 0] /= scale
    K[1, 1] /= scale
    K[0, 2] = (K[0, 2] + 0.5) / scale - 0.5
    K[1, 2] = (K[1, 2] + 0.5) / scale - 0.5
    return K


def load_scene(root: str | Path, downscale: int = 1, load_masks: bool = True) -> Scene:
    """Load a scene folder written by ``nvls build``.

    Args:
        root: the scene folder (holding ``cameras.json``).
        downscale: integer factor to shrink images by (INTER_AREA); intrinsics follow.
        load_masks: read the test masks when present.
    """
    root = Path(root)
    if downscale < 1:
        raise SettingError("downscale", downscale, "must be an integer >= 1")
    doc = read_cameras(root)
    path = root / "cameras.json"

    def cam_arrays(cid: int) -> tuple[np.ndarray, np.ndarray]:
        c = doc.camera(cid, path)
        return _scaled_K(np.asarray(c.K, dtype=np.float64), downscale), np.asarray(c.w2c, np.float64)

    images, Ks, w2cs, fcams, times = [], [], [], [], []
    for fr in doc.frames:
        images.append(_resize(read_image(resolve_inside(root, fr.file, path)), downscale))
        K, w2c = cam_arrays(fr.camera)
        Ks.append(K)
        w2cs.append(w2c)
        fcams.append(fr.camera)
        times.append(fr.time)
    if not images:
        raise UserError(f"{path}: lists no training frames")

    test_imgs, test_masks, test_times, test_files = [], [], [], []
    have_masks = load_masks
    for fr in doc.test_frames:
        test_imgs.append(_resize(read_image(resolve_inside(root, fr.file, path)), downscale))
        test_times.append(fr.time)
        test_files.append(Path(fr.file).name)
        if have_masks and fr.mask:
            m = read_mask(resolve_inside(root, fr.mask, path))
            if downscale > 1:
                m = _resize(m.astype(np.uint8) * 255, downscale) > 127
            test_masks.append(m)
        else:
            have_masks = False
    tK, tw2c = cam_arrays(doc.test_camera) if test_imgs else (np.eye(3), np.eye(4))

    def f32(a) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(np.asarray(a), dtype=np.float32))

    def stack_images(lst: list[np.ndarray]) -> torch.Tensor:
        # Held as read (worldtree.pixels): a quarter of float32's memory; consumers convert per frame.
        return torch.from_numpy(np.stack(lst)) if lst else torch.zeros(0, 1, 1, 3, dtype=torch.uint8)

    return Scene(
        name=root.name,
        root=root,
        images=stack_images(images),
        Ks=f32(np.stack(Ks)),
        w2cs=f32(np.stack(w2cs)),
        frame_cameras=torch.tensor(fcams, dtype=torch.long),
        times=torch.tensor(times, dtype=torch.long),
        test_images=stack_images(test_imgs),
        test_K=f32(tK),
        test_w2c=f32(tw2c),
        test_times=torch.tensor(test_times, dtype=torch.long),
        test_masks=torch.from_numpy(np.stack(test_masks)) if have_masks and test_masks else None,
        test_files=test_files,
        near=doc.near,
        far=doc.far,
    )
