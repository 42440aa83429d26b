"""`nvls import CLIP.mp4` / `nvls import FRAMES_DIR`: SfM recovers a known camera path; bad input is one line.

The clip is generated (benchmarks.fixtures.video_clip): the textured room of `nvls synth` with its two moving
objects, one camera gliding along a smooth 3D arc, 24 frames at 480x270. The estimated cameras are compared with
the true ones after a similarity (Umeyama) fitted to the camera centres.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from benchmarks.fixtures.video_clip import ClipConfig, render_clip, write_frames, write_video
from nvidia_ls.gt_priors import camera_centres, umeyama
from nvidia_ls.importer import ImportConfig, import_scene
from nvidia_ls.manifest import verify_scene
from nvidia_ls.video_frames import VideoConfig, read_clip
from worldtree.infra.errors import UserError
from worldtree.scene import load_scene


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    root = tmp_path_factory.mktemp("clip")
    gen = render_clip(ClipConfig())
    return gen, write_video(root / "walk.mp4", gen.frames), write_frames(root / "walk_frames", gen.frames)


def path_errors(scene, true_w2cs: np.ndarray) -> tuple[float, float]:
    """(max rotation error in degrees, max centre error as a fraction of the true path's extent) of the scene's
    training cameras after the similarity that best maps their centres onto the true ones."""
    doc = json.loads((scene / "cameras.json").read_text())
    by_id = {c["id"]: np.asarray(c["w2c"], float) for c in doc["cameras"]}
    est = np.stack([by_id[f["camera"]] for f in doc["frames"]])
    true = true_w2cs[[f["source_time"] for f in doc["frames"]]]
    c_est, c_true = camera_centres(est), camera_centres(true)
    s, R, t = umeyama(c_est, c_true)
    moved = c_est @ R.T * s + t
    extent = max(np.linalg.norm(a - b) for a in c_true for b in c_true)
    rot = []
    for e, g in zip(est, true, strict=True):
        # Camera-to-world rotation of the estimate, carried into the true world: R @ Rc2w_est.
        d = g[:3, :3] @ (R @ e[:3, :3].T)
        rot.append(math.degrees(math.acos(np.clip((np.trace(d) - 1) / 2, -1, 1))))
    return max(rot), float(np.linalg.norm(moved - c_true, axis=1).max() / extent)


def test_video_recovers_the_camera_path(clip, tmp_path):
    gen, video, _ = clip
    out = tmp_path / "scenes"
    notes: list[str] = []
    scene = import_scene(video, out, ImportConfig(), log=notes.append)
    assert scene == out / "walk" and sorted(p.name for p in out.iterdir()) == ["walk"]  # nothing else written
    man = json.loads((scene / "manifest.json").read_text())
    assert man["poses"]["registered"] == 24 and man["source_times"] == list(range(24)), notes
    rot, centre = path_errors(scene, gen.w2cs)
    assert rot < 1.0 and centre < 0.02, (rot, centre)
    focal = man["poses"]["intrinsics"][0][0]
    assert abs(focal / gen.K[0, 0] - 1) < 0.05, focal  # estimated from COLMAP's guess, 39 % too long
    # The moving objects' features were left out: the masks cover the objects' pixels in most frames.
    assert man["poses"]["feature_masks"]["frames_masked"] >= 20
    assert verify_scene(scene) == []
    loaded = load_scene(scene)
    assert loaded.num_frames == 24 and loaded.test_images.shape[0] == 0
    assert not (scene / ".sfm").exists() and (scene / "preview.png").is_file()


def test_frames_folder_recovers_the_path(clip, tmp_path):
    gen, _, frames = clip
    scene = import_scene(frames, tmp_path / "scenes", ImportConfig(name="frames"))
    man = json.loads((scene / "manifest.json").read_text())
    assert man["source"]["layout"] == "frames" and man["source"]["source_frames"] == 24
    assert man["source_times"] == list(range(24))
    rot, centre = path_errors(scene, gen.w2cs)
    assert rot < 1.0 and centre < 0.02, (rot, centre)
    doc = json.loads((scene / "cameras.json").read_text())
    assert doc["test_frames"] == [] and 0 < doc["near"] < doc["far"]


def test_stride_and_max_frames_pick_the_source_frames(clip):
    _, video, frames = clip
    for source in (video, frames):
        got = read_clip(source, VideoConfig(stride=3, max_frames=5), size=(160, 90))
        assert got.source_index == [0, 3, 6, 9, 12] and got.truncated and got.frames.shape == (5, 90, 160, 3)
    with pytest.raises(UserError, match="another aspect"):
        read_clip(frames, VideoConfig(), size=(100, 100))


def _one_line(source, out, match: str, **video) -> str:
    with pytest.raises(UserError, match=match) as e:
        import_scene(source, out, ImportConfig(video=VideoConfig(**video)))
    msg = str(e.value)
    assert "\n" not in msg and str(source) in msg
    assert not out.exists()  # the -o folder the import made is gone with the rest
    return msg


def test_bad_input_is_one_line_naming_the_clip(tmp_path):
    out = tmp_path / "out"
    _one_line(tmp_path / "missing.mp4", out, "no such file")
    bad = tmp_path / "broken.mp4"
    bad.write_bytes(b"\x00\x00\x00\x18ftypmp42 not a video at all" * 10)
    _one_line(bad, out, "cannot open|no frame could be decoded")
    # Noise frames share no feature: SfM registers (almost) nothing, and the error says what to try.
    rng = np.random.default_rng(0)
    noise = write_frames(tmp_path / "noise", rng.integers(0, 256, (6, 90, 160, 3), dtype=np.uint8))
    msg = _one_line(noise, out, "SfM registered", mask_moving=False)
    assert "--video-stride" in msg


def test_cli_imports_a_clip_and_refuses_scene_options(clip, tmp_path):
    from typer.testing import CliRunner

    from nvidia_ls.cli import app

    _, video, _ = clip
    r = CliRunner().invoke(app, ["import", str(video), "-o", str(tmp_path), "--test-row", "0"])
    assert r.exit_code != 0 and "--test-row" in str(r.exception)
    assert not (tmp_path / "walk").exists()
