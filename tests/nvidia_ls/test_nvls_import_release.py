"""`nvls import` of the paper's NVIDIA-LS release layout (``images/``, ``poses_bounds.npy``,
``gt_images/v001_tXXX.png``, ``sam_results/masks/v001_tXXX.png``): a generated rig capture written in that
layout comes back with the generator's frames, cameras, ping-pong camera order, test views and test masks."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.fixtures.planar_scene import PlanarScene, PlanarSceneConfig
from nvidia_ls import llff
from nvidia_ls.importer import ImportConfig, import_scene
from nvidia_ls.manifest import verify_scene
from worldtree.imageio import write_image
from worldtree.scene import load_scene

T, N_RIG = 7, 3
CFG = PlanarSceneConfig(width=64, height=40, num_frames=T, num_cameras=N_RIG, supersample=1, baseline=0.3)


def _test_camera(scene: PlanarScene) -> np.ndarray:
    """The held-out test camera (id 1): left of the rig, looking at the same point."""
    return scene._rig_pose(-1)


def _write_release(scene: PlanarScene, root, rows: str) -> dict[str, np.ndarray]:
    """Write the release layout under ``root``; ``rows`` = "rig" (one pose row per rig camera, test camera
    first) or "frames" (one row per training frame, plus the test camera as row 0). Returns the exact arrays."""
    fr = scene.frames()
    H, W = CFG.height, CFG.width
    rgb = np.round(fr["rgb"] * 255).astype(np.uint8)
    for t in range(T):
        write_image(root / "images" / f"{t:05d}.png", rgb[t])
    w_test = _test_camera(scene)
    test = [scene.render(scene.K, w_test, t) for t in range(T)]
    test_rgb = np.stack([np.round(r["rgb"] * 255).astype(np.uint8) for r in test])
    test_mask = np.stack([r["mask"] for r in test])
    for t in range(T):
        write_image(root / "gt_images" / f"v001_t{t:03d}.png", test_rgb[t])
        write_image(root / "sam_results" / "masks" / f"v001_t{t:03d}.png", test_mask[t])
    poses = [w_test] + (list(scene.rig_w2c) if rows == "rig" else list(fr["w2cs"]))
    n = len(poses)
    pb = llff.opencv_to_llff(
        np.stack(poses), np.tile(scene.K, (n, 1, 1)), H, W, np.tile([[0.5, 8.0]], (n, 1))
    )
    np.save(root / "poses_bounds.npy", pb)
    return {"rgb": rgb, "w2cs": fr["w2cs"], "cameras": fr["cameras"], "test_rgb": test_rgb,
            "test_mask": test_mask, "test_w2c": w_test}  # fmt: skip


@pytest.mark.parametrize("rows", ["rig", "frames"])
def test_release_layout_round_trip(tmp_path, rows):
    scene = PlanarScene(CFG)
    src = tmp_path / "Release"
    gt = _write_release(scene, src, rows)
    # Layout detected from gt_images/v001_* and sam_results/; the file's own frame to compare cameras as is.
    out = import_scene(src, tmp_path / "scenes", ImportConfig(normalize="none"), log=lambda m: None)
    assert verify_scene(out) == []
    sc = load_scene(out)
    np.testing.assert_array_equal(sc.images.numpy(), gt["rgb"])
    np.testing.assert_allclose(sc.w2cs.numpy(), gt["w2cs"], atol=1e-5)
    np.testing.assert_allclose(sc.Ks.numpy(), np.tile(scene.K, (T, 1, 1)), rtol=1e-6, atol=1e-4)
    np.testing.assert_allclose(sc.test_w2c.numpy(), gt["test_w2c"], atol=1e-5)
    np.testing.assert_array_equal(sc.test_images.numpy(), gt["test_rgb"])
    assert sc.test_masks is not None
    np.testing.assert_array_equal(sc.test_masks.numpy(), gt["test_mask"])
    assert sc.test_times.tolist() == list(range(T))
    if rows == "rig":
        # One row per rig camera: the frames visit cameras 2..N+1 in ping-pong order, like the generator.
        assert sc.frame_cameras.tolist() == gt["cameras"].tolist() == [2, 3, 4, 3, 2, 3, 4]
