"""The Python API of a finished run: load it, list its cameras and times, render any camera at any time, get the
Gaussians at a time (docs/python_api.md).

    from benchmarks.api import load_run

    run = load_run("runs/Synth/worldtree/quick")     # CUDA when present, else the CPU
    cam = run.cameras["test"]                        # or "train_000", ...; or (K, w2c, width, height)
    img = run.render(cam, time=5)                    # [H, W, 3] float32 in [0, 1], on the CPU
    depth = run.render(cam, time=5, mode="depth")    # [H, W] z-depth in the scene's units (NaN: empty)
    frame = run.gaussians_at(5)                      # worldtree.gaussian_frame.GaussianFrame
    run.node_at(5)                                   # the tree node drawing time 5 (None: no tree)

Loading rebuilds the method from the run's recorded ``config.json`` (method, resolved config, scene, downscale)
with ``MethodSpec.build(config, scene, device)`` and reads ``RUN/model`` with the method's ``load_model``: what
it renders is what the run rendered (``renders/`` are reproduced to the PNG's rounding on the same device).
Everything goes through the method protocol (:class:`methods.registry.Method`); nothing here reads a
method's internals.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from worldtree.gaussian_frame import RENDER_MODES, GaussianFrame, RenderMode
from worldtree.infra.errors import UserError

__all__ = ["Camera", "LoadedRun", "config_digest", "load_run"]

LOADING = ("load_model", "gaussians_at", "model_w2c", "render_mode", "node_at")
"""Members of :class:`methods.registry.Method` that loading a run needs."""


@dataclass(frozen=True)
class Camera:
    """A named camera of the run's scene, in the scene's given world frame (OpenCV, as ``cameras.json``)."""

    name: str
    """``train_000`` ... (one per training frame) or ``test``."""
    kind: Literal["train", "test"]
    K: torch.Tensor
    """``[3, 3]`` float32 intrinsics (pixels) at ``width`` x ``height``, the scene's stored size."""
    w2c: torch.Tensor
    """``[4, 4]`` float32 world-to-camera pose, scene frame."""
    width: int
    height: int
    time: int
    """The time it sees: a training frame's own time; the test camera's first test time (it sees every test
    time, :attr:`LoadedRun.test_times`)."""
    frame: int | None = None
    """The training frame's index (None for the test camera)."""


def config_digest(record: dict[str, Any]) -> str:
    """sha256 (hex) of a run's resolved config (``config.json``'s ``config``) as canonical JSON."""
    text = json.dumps(record.get("config"), sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()


@dataclass
class LoadedRun:
    """A finished run loaded by :func:`load_run`. Tensors it returns are on the CPU."""

    folder: Path
    """The run folder."""
    record: dict[str, Any]
    """Its ``config.json`` (method, preset, resolved config, scene, tool version)."""
    config: Any
    """The method's typed config, rebuilt from ``record``."""
    method: Any
    """The loaded method (:class:`methods.registry.Method`)."""
    device: torch.device
    scene_dir: Path
    cameras: dict[str, Camera]
    """Every training frame's camera (``train_000``...) and the test camera (``test``), by name."""
    times: list[int]
    """The time indices the model covers (its training frames), ascending."""
    test_times: list[int] = field(default_factory=list)
    """The times the test camera was rendered at (``renders/``)."""
    test_files: list[str] = field(default_factory=list)
    """The test images' names, one per test time."""

    @property
    def method_name(self) -> str:
        return str(self.record["method"])

    @property
    def digest(self) -> str:
        """:func:`config_digest` of the run."""
        return config_digest(self.record)

    def _time(self, time: int) -> int:
        t = int(time)
        if t not in self.times:
            raise UserError(f"time {time}: {self.folder} covers times {self.times[0]}..{self.times[-1]}")
        return t

    def _camera(
        self, camera: Camera | str | Sequence[Any]
    ) -> tuple[torch.Tensor, torch.Tensor, int, int, Camera | None]:
        if isinstance(camera, str):
            if camera not in self.cameras:
                raise UserError(
                    f"camera {camera!r}: {self.folder} has cameras train_000.., test (LoadedRun.cameras)"
                )
            camera = self.cameras[camera]
        if isinstance(camera, Camera):
            return camera.K, camera.w2c, camera.width, camera.height, camera
        try:
            K, w2c, width, height = camera
        except (TypeError, ValueError) as e:
            raise TypeError(
                "camera: give a Camera, a camera name or (K [3,3], w2c [4,4], width, height)"
            ) from e
        K = torch.as_tensor(np.asarray(K, np.float32))
        w2c = torch.as_tensor(np.asarray(w2c, np.float32))
        if K.shape != (3, 3) or w2c.shape != (4, 4):
            raise ValueError(
                f"camera: K {tuple(K.shape)} and w2c {tuple(w2c.shape)}; expected [3, 3] and [4, 4]"
            )
        return K, w2c, int(width), int(height), None

    @torch.no_grad()
    def render(
        self, camera: Camera | str | Sequence[Any], time: int | None = None, mode: RenderMode = "rgb"
    ) -> torch.Tensor:
        """Render ``camera`` (a :class:`Camera`, its name, or ``(K [3,3], w2c [4,4], width, height)`` in the
        scene's frame) at ``time`` (default: the camera's own) as ``mode``: ``rgb`` ``[H, W, 3]`` in [0, 1],
        ``depth`` ``[H, W]`` z-depth in scene units (NaN where less than half opaque), ``alpha`` ``[H, W]``,
        ``dynamic`` ``[H, W, 3]`` the dynamic Gaussians alone on black.

        The test camera is drawn from the pose the run refined for that time (as ``renders/``), a training
        camera from its frame's fitted pose (Base and WorldTree: also a ``w2c`` equal to a training frame's
        given pose), any other camera through the run's scene->model Sim(3)."""
        if mode not in RENDER_MODES:
            raise UserError(f"mode {mode!r}: choose one of {', '.join(RENDER_MODES)}")
        K, w2c, width, height, cam = self._camera(camera)
        if time is None:
            if cam is None:
                raise TypeError(
                    "render((K, w2c, width, height), time): give the time for a camera of your own"
                )
            time = cam.time
        t = self._time(time)
        test_view = cam is not None and cam.kind == "test"
        frame = cam.frame if cam is not None else None
        img = self.method.render_mode(K, w2c, width, height, t, mode, test_view=test_view, frame=frame)
        return img.detach().float().cpu()

    @torch.no_grad()
    def model_w2c(self, camera: Camera | str | Sequence[Any], time: int | None = None) -> torch.Tensor:
        """``[4, 4]`` pose (CPU) in the model's world frame that :meth:`render` draws ``camera`` from."""
        _, w2c, _, _, cam = self._camera(camera)
        t = self._time(cam.time if time is None and cam is not None else time)
        test_view = cam is not None and cam.kind == "test"
        return self.method.model_w2c(w2c, t, test_view, cam.frame if cam is not None else None).detach().cpu()

    @torch.no_grad()
    def gaussians_at(self, time: int) -> GaussianFrame:
        """Every Gaussian drawn at ``time`` (:class:`worldtree.gaussian_frame.GaussianFrame`, on the CPU, model
        frame; ``frame.scene_to_model`` maps the scene's cameras into it)."""
        return self.method.gaussians_at(self._time(time)).to("cpu")

    def node_at(self, time: int) -> int | None:
        """The tree node that draws ``time`` (WorldTree; 1 = root), None for a method without a tree."""
        return self.method.node_at(self._time(time))

    def saved_test_render(self, time: int) -> np.ndarray:
        """The run's own test render at test time ``time`` (``renders/<name>.png``): uint8 ``[H, W, 3]``."""
        from worldtree.imageio import read_image

        if int(time) not in self.test_times:
            raise UserError(f"time {time}: {self.folder} has test renders at times {self.test_times}")
        name = Path(self.test_files[self.test_times.index(int(time))]).stem + ".png"
        path = self.folder / "renders" / name
        if not path.is_file():
            raise UserError(f"{path}: missing; finish the run with `wtbench run` first")
        return read_image(path)


def _read_record(folder: Path) -> dict[str, Any]:
    path = folder / "config.json"
    if not folder.is_dir():
        raise UserError(
            f"{folder}: no such run folder; give a folder written by `wtbench run` (RUNS/SCENE/METHOD/TAG)"
        )
    if not path.is_file():
        raise UserError(
            f"{folder}: no config.json, so not a run folder; give a folder written by `wtbench run`"
        )
    try:
        record = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise UserError(
            f"{path}: unreadable ({type(e).__name__}); re-run the run with `wtbench run --force`"
        ) from e
    if not isinstance(record, dict) or not all(k in record for k in ("method", "config", "scene")):
        raise UserError(f"{path}: lacks method/config/scene; re-run the run with `wtbench run --force`")
    if not (folder / "model" / "model.json").is_file():
        raise UserError(
            f"{folder}: no saved model (model/model.json); the run has not finished: run its command.txt again"
        )
    return record


def _rebuild_config(spec, record: dict[str, Any], path: Path) -> Any:
    from worldtree.infra.config_json import from_dict

    try:
        return from_dict(spec.config_cls, record["config"])
    except UserError as e:
        raise UserError(f"{path}: {e}") from e
    except (TypeError, ValueError, KeyError) as e:
        raise UserError(
            f"{path}: its config does not fit method {spec.name!r} of this version ({e}); load it with the "
            f"version that made it ({record.get('version', '?')})"
        ) from e


def _cameras(scene_dir: Path) -> tuple[dict[str, Camera], list[int], list[int], list[str]]:
    from worldtree.scene_schema import read_cameras

    doc = read_cameras(scene_dir)
    path = scene_dir / "cameras.json"

    def mats(cid: int) -> tuple[torch.Tensor, torch.Tensor]:
        c = doc.camera(cid, path)
        return torch.tensor(c.K, dtype=torch.float32), torch.tensor(c.w2c, dtype=torch.float32)

    cams: dict[str, Camera] = {}
    digits = max(3, len(str(len(doc.frames) - 1)))
    for i, fr in enumerate(doc.frames):
        K, w2c = mats(fr.camera)
        name = f"train_{i:0{digits}d}"
        cams[name] = Camera(name, "train", K, w2c, doc.width, doc.height, int(fr.time), i)
    test_times = [int(f.time) for f in doc.test_frames]
    if doc.test_frames:
        K, w2c = mats(doc.test_camera)
        cams["test"] = Camera("test", "test", K, w2c, doc.width, doc.height, test_times[0])
    times = sorted({int(f.time) for f in doc.frames})
    return cams, times, test_times, [Path(f.file).name for f in doc.test_frames]


def load_run(
    run_dir: str | Path, device: str | torch.device | None = None, scene: str | Path | None = None
) -> LoadedRun:
    """Load the finished run in ``run_dir`` (a folder written by ``wtbench run``).

    Args:
        run_dir: the run folder (``config.json``, ``model/``, ``renders/``).
        device: ``"cpu"``, ``"cuda"``, ``"cuda:N"``; None / ``"auto"``: CUDA when present, else the CPU.
        scene: the scene folder, when it has moved since the run (default: the one ``config.json`` names).

    A missing or unfinished run, a moved scene, or a method that cannot be loaded is a :class:`UserError`
    naming the path and the fix.
    """
    from methods.registry import get_method
    from worldtree.checkpoint import seed_everything
    from worldtree.infra.device import pick_device
    from worldtree.scene import load_scene

    folder = Path(run_dir)
    record = _read_record(folder)
    cfg_path = folder / "config.json"
    try:
        spec = get_method(str(record["method"]))
    except UserError as e:
        raise UserError(f"{cfg_path}: {e}") from e
    config = _rebuild_config(spec, record, cfg_path)
    scene_dir = Path(scene) if scene is not None else Path(record["scene"])
    if not (scene_dir / "cameras.json").is_file():
        how = (
            "give the scene folder that holds it" if scene is not None else "pass scene=... (the scene moved)"
        )
        raise UserError(f"{scene_dir / 'cameras.json'}: missing; {how}")
    dev = device if isinstance(device, torch.device) else pick_device(device)
    seed_everything(int(getattr(config, "seed", 0)))  # as the run: a method may draw its initial points
    loaded_scene = load_scene(scene_dir, downscale=int(getattr(config, "downscale", 1)), load_masks=False)
    method = spec.build(config, loaded_scene, dev)
    missing = [m for m in LOADING if not callable(getattr(method, m, None))]
    if missing:
        raise UserError(
            f"{cfg_path}: method {spec.name!r} cannot be loaded (it lacks {', '.join(missing)}); "
            "see docs/adding_a_method.md"
        )
    method.load_model(folder / "model")
    cams, times, test_times, test_files = _cameras(scene_dir)
    return LoadedRun(folder, record, config, method, dev, scene_dir, cams, times, test_times, test_files)
