"""Run folders: the layout of one method's run on one scene, its bookkeeping, and executing it end to end.

Layout (``RUNS_DIR/<scene>/<method>/<tag>/``, ``tag`` = preset plus overrides, e.g. ``quick`` or
``quick-steps200-seed1``, and ``-set<8 hex>`` when ``--set`` or imported priors change the config)::

    config.json     resolved typed config, preset, overrides, options, sets, imported priors, seed, scene,
                    tool version
    command.txt     the command line that made the run
    checkpoints/    periodic atomic checkpoints (model + optimiser + density-control state + RNG states);
                    root_from.json in a run grown on another run's root (--root-from,
                    benchmarks.runner.shared_root)
    model/          final model: gaussians.pt (GaussianSet.load), gaussians.ply, model.json
    renders/        the test camera at every test time, named like the ground truth (v001_tXXX.png)
    metrics.csv     per-frame scores and a 'mean' row (benchmarks.evaluation.evaluate), metrics.json beside it
    timing.json     wall time per stage and per session (an interrupted run's sessions add up: total_s),
                    iterations/s, peak memory, Gaussian count, device, backend
    tensorboard/    TensorBoard scalars (only with --tensorboard)
    DONE            written last; a finished run is skipped unless forced

Running the same request again resumes from the newest checkpoint, or skips a run whose DONE exists.
"""

from __future__ import annotations

import dataclasses
import json
import os
import resource
import shutil
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

import worldtree
from methods.config_overrides import apply_overrides, sets_digest, split_assignment
from worldtree.imageio import write_image
from worldtree.infra import thread_governor
from worldtree.infra.atomic import atomic_write_json, atomic_write_text, remove_stale_temporaries
from worldtree.infra.config_ranges import check_config_ranges
from worldtree.infra.errors import UserError
from worldtree.infra.output_paths import check_name, check_output_folder, check_replaceable, folder_name_of
from worldtree.infra.timing import StageClock
from worldtree.losses import SSIM_WINDOW

if TYPE_CHECKING:
    from methods.plugin import MethodOption

TUNABLE = ("steps", "seed", "downscale")
# The ablations of a run (`--ablate`, the method's `MethodSpec.ablations`), on the config field of that name.
ABLATE = "ablate"
# Files every run folder gets first (config.json, then command.txt): `--force` deletes only a folder holding them.
RUN_MARKERS = ("config.json", "command.txt")
# What a sweep writes into a run folder before its job starts the run (benchmarks.runner.sweep_executors).
SWEEP_FILES = ("job.json",)
# Imported-prior options of `wtbench run` -> the PriorsConfig field each sets (priors.<field>), and what the
# path must be ("dir", "file" or "any"; as `wtbench prep` reads them, docs/priors.md).
PRIOR_OPTIONS: dict[str, tuple[str, str]] = {
    "masks": ("masks_source", "dir"),
    "tracks": ("tracks_source", "file"),
    "depth_maps": ("depth_source", "any"),
    "flow": ("flow_source", "dir"),
}


@dataclass(frozen=True)
class RunFolder:
    """Paths of one run."""

    root: Path

    @property
    def config_json(self) -> Path:
        return self.root / "config.json"

    @property
    def command_txt(self) -> Path:
        return self.root / "command.txt"

    @property
    def checkpoints(self) -> Path:
        return self.root / "checkpoints"

    @property
    def model(self) -> Path:
        return self.root / "model"

    @property
    def renders(self) -> Path:
        return self.root / "renders"

    @property
    def metrics_csv(self) -> Path:
        return self.root / "metrics.csv"

    @property
    def metrics_json(self) -> Path:
        return self.root / "metrics.json"

    @property
    def timing_json(self) -> Path:
        return self.root / "timing.json"

    @property
    def timing_ledger(self) -> Path:
        """Stage and session times so far (:class:`worldtree.infra.timing.StageClock`), kept across resumes."""
        return self.checkpoints / "timing_sessions.json"

    @property
    def tensorboard(self) -> Path:
        return self.root / "tensorboard"

    @property
    def done(self) -> Path:
        return self.root / "DONE"

    def is_done(self) -> bool:
        return self.done.is_file()


def run_tag(
    preset: str,
    overrides: dict[str, Any],
    options: dict[str, Any] | None = None,
    sets: list[str] | None = None,
    method_options: Sequence[MethodOption] = (),
) -> str:
    """Folder name of a configuration: the preset, then ``-<field><value>`` per override in a fixed order,
    then ``-no<name>`` per ablation, then the method's options (``method_options``, its
    ``MethodSpec.options``) in their declared order, each ``-<tag><value>`` (a flag: ``-<tag>``; e.g.
    ``quick-steps200-noba-nosac-depth3``), then ``-set<8 hex>`` when ``sets`` (``KEY=VALUE`` strings,
    imported priors included) are given: :func:`methods.config_overrides.sets_digest`, the same for the
    same settings in any order. An option in ``options`` that ``method_options`` does not declare is a
    ValueError (:func:`resolve_config` refuses it first, naming its flag)."""
    parts = [preset] + [f"{k}{overrides[k]}" for k in TUNABLE if k in overrides]
    opts = dict(options or {})
    parts += [f"no{a}" for a in sorted(set(opts.pop(ABLATE, None) or ()))]
    for opt in method_options:
        value = opts.pop(opt.field, None)
        if value is True:
            parts.append(opt.tag)
        elif value is not None and value is not False:
            parts.append(f"{opt.tag}{value}")
    if opts:
        raise ValueError(f"options {sorted(opts)} are not among the method's options")
    if sets:
        parts.append("set" + sets_digest(sets))
    return "-".join(parts)


def peak_rss_mib() -> float:
    """Peak resident memory of this process so far, MiB (Linux reports kilobytes, macOS bytes)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / (1024.0 * 1024.0) if sys.platform == "darwin" else rss / 1024.0


@dataclass(frozen=True)
class TestView:
    """The test camera at the size of the ground-truth images."""

    K: torch.Tensor  # [3, 3] pixels
    w2c: torch.Tensor  # [4, 4] OpenCV world-to-camera
    width: int
    height: int
    times: list[int]
    files: list[str]


def native_test_view(root: Path) -> TestView:
    """The test camera of scene ``root`` at the stored (not down-scaled) image size, from ``cameras.json``."""
    from worldtree.scene_schema import read_cameras

    doc = read_cameras(root)
    path = root / "cameras.json"
    if not doc.test_frames:
        # A scene without test views (your own video, `nvls import CLIP`): the run trains and saves its model;
        # nothing is rendered at a test camera and the evaluation records "no ground truth".
        return TestView(torch.eye(3), torch.eye(4), doc.width, doc.height, [], [])
    cam = doc.camera(doc.test_camera, path)
    return TestView(
        K=torch.tensor(cam.K, dtype=torch.float32),
        w2c=torch.tensor(cam.w2c, dtype=torch.float32),
        width=doc.width,
        height=doc.height,
        times=[f.time for f in doc.test_frames],
        files=[Path(f.file).name for f in doc.test_frames],
    )


@dataclass
class RunRequest:
    """Everything ``wtbench run`` was asked to do."""

    scene: Path
    """Scene folder (written by ``nvls build``)."""
    method: str
    """Registered method name."""
    runs_dir: Path = Path("runs")
    """Root of all run folders."""
    preset: str = "paper"
    """Config preset of the method."""
    device: str = "auto"
    """auto, cpu, cuda or cuda:N."""
    overrides: dict[str, int] = field(default_factory=dict)
    """Overridden common config fields (steps, seed, downscale)."""
    options: dict[str, Any] = field(default_factory=dict)
    """Method options: ``ablate`` (a list of the method's ``MethodSpec.ablations``) and the fields of its
    ``MethodSpec.options`` (e.g. ``{"ablate": ["ba"], "depth": 3}``), set on the config fields of the same
    name; a method that does not declare one refuses it."""
    lpips_weights: Path | None = None
    """Folder with the LPIPS weight files (None: the evaluator's default search)."""
    tensorboard: bool = False
    """Write TensorBoard scalars into the run folder."""
    force: bool = False
    """Delete an existing run folder (finished or not) and start again."""
    sets: list[str] = field(default_factory=list)
    """``KEY=VALUE`` assignments to any config field (``--set``, :mod:`methods.config_overrides`), applied
    after overrides and options; recorded verbatim in config.json."""
    priors: dict[str, str] = field(default_factory=dict)
    """Imported priors: ``PRIOR_OPTIONS`` name (masks, tracks, depth_maps, flow) -> path; each sets its
    ``priors.<...>_source`` field (a method without ``priors`` refuses them)."""
    tag: str | None = None
    """Run-folder name; default: preset plus overrides."""
    root_from: Path | None = None
    """A run folder whose first stages this run takes instead of training them (``--root-from``;
    :mod:`benchmarks.runner.shared_root`)."""
    progress: bool = True
    """Show training progress."""
    command: str = ""
    """Command line, recorded in command.txt."""


@dataclass
class RunResult:
    folder: RunFolder
    skipped: bool
    mean: dict[str, float]


def _config_record(spec, cfg, req: RunRequest) -> dict[str, Any]:
    return {
        "method": spec.name,
        "preset": req.preset,
        "overrides": dict(req.overrides),
        "options": dict(req.options),
        # The method's own vocabulary for table labels (reporting reads it here and knows no method).
        "labels": {"options": [[o.field, o.tag] for o in spec.options], "ablations": list(spec.ablations)},
        "sets": list(req.sets),
        "imported_priors": dict(req.priors),
        "config": dataclasses.asdict(cfg),
        "seed": cfg.seed,
        "scene": str(req.scene.resolve()),
        "device": req.device,
        "version": worldtree.__version__,
    }


def _check_same_config(folder: RunFolder, record: dict[str, Any]) -> None:
    try:
        old = json.loads(folder.config_json.read_text())
    except json.JSONDecodeError as e:
        raise UserError(f"{folder.config_json}: damaged; re-run with --force to start this run again") from e
    # Round-trip through JSON so tuples compare equal to the lists read back.
    new = json.loads(json.dumps(record, default=str))
    for key in ("method", "config", "scene"):
        if old.get(key) != new.get(key):
            raise UserError(
                f"{folder.root} holds a run with a different {key}; use --force to replace it, "
                "or --tag/-o to run elsewhere"
            )


def execute(req: RunRequest) -> RunResult:
    """Train, render, score and record one run (resuming or skipping as described in the module doc).

    Everything that can be checked is checked before the run folder is touched (method, scene, config,
    device, the output folder's writability), so a rejected request leaves nothing behind. The run folder
    is then locked (:class:`worldtree.infra.folder_lock.FolderLock`, held until this function returns) before
    anything is written or deleted in it: a second writer, ``--force`` included, fails at once naming the
    holder's PID and host.
    """
    from methods.registry import get_method
    from worldtree.checkpoint import seed_everything
    from worldtree.infra.determinism import deterministic_for
    from worldtree.infra.device import pick_device
    from worldtree.infra.folder_lock import FolderLock
    from worldtree.scene import load_scene
    from worldtree.trainer import check_tensorboard

    spec = get_method(req.method)
    if req.tensorboard:
        check_tensorboard()
    root = Path(req.scene)
    if not root.is_dir():
        raise UserError(f"--scene {root}: no such folder; give a scene folder written by `nvls build`")
    view = native_test_view(root)
    cfg, sets = resolve_config(spec, req)
    cfg = training_size(cfg, root, req)
    _check_downscale(cfg.downscale, view, root, req)
    folder = _run_folder(req, spec, sets)
    device = pick_device(req.device)
    check_output_folder(req.runs_dir, "--out")
    check_run_folder(folder, req.force)
    lent = None
    if req.root_from is not None and not (folder.is_done() and not req.force):
        from benchmarks.runner.shared_root import check_root_from

        lent = check_root_from(req.root_from, folder.root, spec, _config_record(spec, cfg, req), device.type)
    timer = StageClock()  # the run's clock, from the start of this session

    def build_method():
        if device.type == "cpu":
            # The C++ rasterizer's one-time build is timed apart, so that the method's stages time the method.
            from worldtree.render.cpu_kernel import prepare

            with timer.stage("kernel_build"):
                prepare()
        seed_everything(cfg.seed)  # before building: a method may draw its initial points
        deterministic_for(device)
        with timer.stage("load"):
            scene = load_scene(root, downscale=cfg.downscale)
        if min(scene.height, scene.width) < SSIM_WINDOW:
            raise UserError(
                f"--scene {root}: training images of {scene.width}x{scene.height} (downscale {cfg.downscale}) "
                f"are smaller than the {SSIM_WINDOW}x{SSIM_WINDOW} SSIM window; use a smaller --downscale "
                "or rebuild the scene larger"
            )
        with timer.stage("init"):
            return spec.build(cfg, scene, device)

    # A finished run is skipped without loading its scene; any other request loads the scene and builds the
    # method first, so that their errors (a damaged scene, too few frames) come before the folder exists.
    method = None if (folder.is_done() and not req.force) else build_method()
    with FolderLock(folder.root, "run folder"):
        return _execute_locked(req, spec, cfg, folder, root, view, device, timer, method, build_method, lent)


def training_size(cfg, root: Path, req: RunRequest):
    """``cfg`` with the shrink it trains at on scene ``root``: its ``downscale_for`` the scene's training video
    (the quick presets train a short video at full size), unless ``--downscale`` or ``--set downscale`` gave
    one."""
    from methods.registry import at_training_size

    given = "downscale" in req.overrides or any(split_assignment(i)[0] == "downscale" for i in req.sets)
    return cfg if given else at_training_size(cfg, root)


def _check_downscale(downscale: int, view: TestView, root: Path, req: RunRequest) -> None:
    """Refuse a shrink that leaves training images smaller than the SSIM window, before the scene is loaded
    (at load it is an OpenCV assertion, or work is done first): the images shrink by integer division."""
    w, h = view.width // downscale, view.height // downscale
    if min(w, h) < SSIM_WINDOW:
        given = f"--downscale {downscale}" if "downscale" in req.overrides else f"--set downscale={downscale}"
        if (
            not any(split_assignment(i)[0] == "downscale" for i in req.sets)
            and "downscale" not in req.overrides
        ):
            given = f"the preset's downscale {downscale}"
        raise UserError(
            f"{given}: the {view.width}x{view.height} images of {root} would shrink to {w}x{h}, smaller than the "
            f"{SSIM_WINDOW}x{SSIM_WINDOW} SSIM window; use a downscale of at most "
            f"{max(1, min(view.width, view.height) // SSIM_WINDOW)}"
        )


def _kernel_target(device: torch.device) -> str | None:
    """The C++ rasterizer build the run used on the CPU (native, avx2 or portable), None elsewhere or without it."""
    if device.type != "cpu":
        return None
    from worldtree.render.cpu_kernel import loaded_target

    return loaded_target()


def _execute_locked(req, spec, cfg, folder, root, view, device, timer, method, build_method, lent) -> RunResult:
    """The part of :func:`execute` that runs with the run folder locked. ``method`` is the built method, or
    None when the run looked finished before locking (``build_method()`` builds it if it no longer is);
    ``lent``: the checked root of ``--root-from`` (None without)."""
    from methods.shared_root import lend_root, root_from_record
    from worldtree.trainer import TrainContext

    record = _config_record(spec, cfg, req)
    if req.force and folder.root.exists():
        check_run_folder(folder, force=True)  # again under the lock: what is deleted is what was checked
        shutil.rmtree(folder.root)
    if folder.root.is_dir():  # what a kill -9 left mid-write; under the lock no live writer owns it
        remove_stale_temporaries(folder.root)
    if folder.config_json.is_file():
        _check_same_config(folder, record)
        if folder.is_done():
            print(f"already finished: {folder.root} (use --force to run it again)", file=sys.stderr)
            return RunResult(folder, skipped=True, mean=_read_mean(folder))
        print(f"resuming: {folder.root}", file=sys.stderr)
    folder.root.mkdir(parents=True, exist_ok=True)
    atomic_write_json(folder.config_json, record)
    atomic_write_text(folder.command_txt, req.command + "\n")
    timer.attach(folder.timing_ledger)  # earlier sessions of this run, if it was interrupted
    if lent is not None:
        linked = lend_root(lent, folder.checkpoints, spec.shared_root.checkpoints)
        if linked:
            print(f"root from {lent.source}: {', '.join(linked)}", file=sys.stderr)

    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    if method is None:
        method = build_method()
    with timer.stage("train"):
        ctx = TrainContext(
            checkpoint_dir=folder.checkpoints,
            tensorboard_dir=folder.tensorboard if req.tensorboard else None,
            progress=req.progress,
            resume=True,
        )
        summary = method.fit(ctx)
    with timer.stage("save_model"):
        method.save_model(folder.model)
    with timer.stage("render"):
        _render_test(method, view, folder)
    with timer.stage("eval"):
        mean = _evaluate(folder, root, req, device)

    stats = method.stats()
    timing = {
        **_flushed(timer).record(),
        "train": _train_record(summary),
        "peak_rss_mib": peak_rss_mib(),
        "cuda_peak_allocated_mib": (
            torch.cuda.max_memory_allocated(device) / 2**20 if device.type == "cuda" else None
        ),
        "num_gaussians": stats.get("num_gaussians"),
        "backend": stats.get("backend"),
        "rasterizer_target": _kernel_target(device),
        "device": str(device),
        "torch_threads": torch.get_num_threads(),
        "deterministic": torch.are_deterministic_algorithms_enabled(),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
        "gomp_spincount": os.environ.get("GOMP_SPINCOUNT"),
        "thread_governor": thread_governor.record(),
        "method_stats": stats,
        "root_from": root_from_record(folder.checkpoints),
    }
    atomic_write_json(folder.timing_json, timing)
    atomic_write_json(
        folder.done, {"finished": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "mean": mean}
    )
    return RunResult(folder, skipped=False, mean=mean)


def config_record_of(req: RunRequest) -> dict[str, Any]:
    """The config.json record :func:`execute` would write for ``req`` (nothing is written)."""
    from methods.registry import get_method

    spec = get_method(req.method)
    cfg, _ = resolve_config(spec, req)
    return _config_record(spec, training_size(cfg, Path(req.scene), req), req)


def run_folder_of(req: RunRequest) -> RunFolder:
    """The folder :func:`execute` writes for ``req`` (its config resolved the same way; nothing is written)."""
    from methods.registry import get_method

    spec = get_method(req.method)
    _, sets = resolve_config(spec, req)
    return _run_folder(req, spec, sets)


def _run_folder(req: RunRequest, spec, sets: list[str]) -> RunFolder:
    """``RUNS_DIR/<scene>/<method>/<tag>`` of ``req``, each part checked to be one folder name (a ``--tag``
    or scene name holding ``/``, ``..`` or a newline would put the run, and what ``--force`` deletes,
    outside RUNS_DIR)."""
    scene = check_name(folder_name_of(req.scene), f"--scene {req.scene}: the folder name")
    if req.tag is not None:
        tag = check_name(req.tag, "--tag")
    else:
        tag = run_tag(req.preset, req.overrides, req.options, sets, spec.options)
        tag = check_name(tag, "the run folder name")
    return RunFolder(Path(req.runs_dir) / scene / spec.name / tag)


def check_run_folder(folder: RunFolder, force: bool) -> None:
    """Refuse a run folder path that holds something other than a run: with ``force`` (which deletes it)
    anything but a folder holding ``RUN_MARKERS`` (or nothing but ``SWEEP_FILES``); without, a file or link,
    or a folder holding other files but no config.json, which the run would write into."""
    root = folder.root
    if force:
        check_replaceable(root, "--force", "run folder", RUN_MARKERS, also_own=SWEEP_FILES)
        return
    if root.is_symlink() or (root.exists() and not root.is_dir()):
        raise UserError(f"{root}: is a file or link, not a run folder; choose another --tag or -o")
    own = {p.name for p in root.iterdir()} <= set(SWEEP_FILES) if root.is_dir() else True
    if not own and not folder.config_json.is_file():
        raise UserError(
            f"{root}: holds files but no config.json, so it is not a run folder; choose another --tag or -o"
        )


def _train_record(summary) -> dict[str, Any] | None:
    """The main training loop's figures (a method's ``fit`` returns its trainer's summary; None: no loop)."""
    if summary is None:
        return None
    return {
        "steps": summary.end_step,
        "resumed_from_step": summary.start_step,
        "steps_this_session": summary.steps_run,
        "wall_s_this_session": summary.wall_s,
        "wall_s_all_sessions": summary.total_wall_s,
        "it_per_s": summary.it_per_s,
        "final_loss": summary.final_loss,
    }


def _flushed(timer: StageClock) -> StageClock:
    timer.flush()  # this session's wall time up to now, written to the ledger
    return timer


def resolve_config(spec, req: RunRequest) -> tuple[Any, list[str]]:
    """The config of ``req``: ``spec``'s preset, then the overrides, the method options, and last the
    ``--set`` assignments with the imported priors (as ``priors.<field>=<absolute path>``). Returns the config
    and every assignment applied (they name the run folder). A ``--set`` key also given by its own option
    (``--steps``, ``--depth``, ``--masks``...) is refused rather than silently preferring one; ``--steps N``
    asks for exactly N (the config's ``with_exact_steps``; a ``--set`` applied after it still wins)."""
    cfg = spec.config(req.preset)
    for k in req.overrides:
        if k not in TUNABLE:
            raise UserError(f"override {k!r} is not one of {', '.join(TUNABLE)}")
    cfg = dataclasses.replace(cfg, **req.overrides, **method_option_fields(spec, req.options))
    if "steps" in req.overrides:
        cfg = cfg.with_exact_steps()  # --steps N means N, on a video of any length
    prior_sets = _prior_sets(cfg, spec.name, req.priors)
    flags = {k: option_flag(k) for k in (*req.overrides, *req.options)}
    flags |= {f"priors.{PRIOR_OPTIONS[k][0]}": option_flag(k) for k in req.priors}
    for item in req.sets:
        key, _ = split_assignment(item)
        if key in flags:
            raise UserError(f"--set {item}: {key} is also given by {flags[key]}; keep one of them")
    sets = list(req.sets) + prior_sets
    cfg = apply_overrides(cfg, sets)
    for k in ("steps", "downscale"):  # given by --steps/--downscale or by --set
        v = getattr(cfg, k)
        if v < 1:
            raise UserError(f"{f'--{k} {v}' if k in req.overrides else f'--set {k}={v}'}: must be at least 1")
    # Every setting within its declared range (worldtree.infra.config_ranges), named as it was given.
    given = {split_assignment(item)[0]: f"--set {item}" for item in req.sets}
    given |= {k: f"{option_flag(k)} {v}" for k, v in (*req.overrides.items(), *req.options.items())}
    check_config_ranges(cfg, given)
    return cfg, sets


def resolve_prior_paths(priors: dict[str, Any]) -> dict[str, str]:
    """``{option: path}`` (``PRIOR_OPTIONS`` names; None values dropped) with each path made absolute; a
    missing path, or a file where a folder is needed (or the reverse), is a :class:`UserError` naming the
    option."""
    out: dict[str, str] = {}
    for name, value in priors.items():
        if value is None:
            continue
        if name not in PRIOR_OPTIONS:
            raise UserError(f"prior {name!r} is not one of {', '.join(PRIOR_OPTIONS)}")
        flag = option_flag(name)
        path = Path(value).expanduser().resolve()
        kind = PRIOR_OPTIONS[name][1]
        if not path.exists():
            raise UserError(f"{flag} {value}: no such file or folder; see docs/priors.md for the layout")
        if kind == "dir" and not path.is_dir():
            raise UserError(f"{flag} {value}: not a folder; give the folder holding the files")
        if kind == "file" and not path.is_file():
            raise UserError(f"{flag} {value}: not a file; give one .npy/.npz/.pt file")
        out[name] = str(path)
    return out


def option_flag(name: str) -> str:
    """The command-line option of a request field: ``depth_maps`` -> ``--depth-maps``."""
    return "--" + name.replace("_", "-")


def _prior_sets(cfg, method: str, priors: dict[str, Any]) -> list[str]:
    """The imported priors as ``priors.<field>=<absolute path>`` assignments, in ``PRIOR_OPTIONS`` order."""
    given = [k for k, v in priors.items() if v is not None]
    if given and "priors" not in {f.name for f in dataclasses.fields(cfg)}:
        raise UserError(
            f"{option_flag(given[0])}: method {method!r} uses no 2D priors; drop it or use one of the methods "
            f"that do ({', '.join(_methods_with_field('priors')) or 'none'})"
        )
    paths = resolve_prior_paths(priors)
    return [f"priors.{PRIOR_OPTIONS[k][0]}={paths[k]}" for k in PRIOR_OPTIONS if k in paths]


def method_option_fields(spec, options: dict[str, Any]) -> dict[str, Any]:
    """``options`` as config fields of ``spec``'s method: ``ablate`` (a tuple) when it declares ablations, and
    the fields of its ``MethodSpec.options``; an option it does not declare is a :class:`UserError` naming the
    flag and the methods that have it."""
    out: dict[str, Any] = {}
    for k, v in options.items():
        if k not in method_option_names(spec):
            others = [s.name for s in _list_methods() if k in method_option_names(s)]
            where = f"use it with --method {' or '.join(others)}" if others else "no method has it"
            raise UserError(f"{option_flag(k)}: method {spec.name!r} has no such option; drop it or {where}")
        out[k] = tuple(v) if k == ABLATE else v
    return out


def method_option_names(spec) -> set[str]:
    """The ``RunRequest.options`` keys ``spec``'s method accepts: ``ablate`` (when it has ablations) and the
    fields of its ``MethodSpec.options``."""
    return {o.field for o in spec.options} | ({ABLATE} if spec.ablations else set())


def _list_methods():
    from methods.registry import list_methods

    return list_methods()


def _methods_with_field(name: str) -> list[str]:
    """Names of the registered methods whose config has a top-level field ``name``."""
    return [s.name for s in _list_methods() if name in {f.name for f in dataclasses.fields(s.config_cls)}]


def _render_test(method, view: TestView, folder: RunFolder) -> None:
    """Render the test camera at every test time into ``renders/`` (existing renders of the final model are
    kept, so an interrupted rendering stage resumes)."""
    folder.renders.mkdir(parents=True, exist_ok=True)
    for t, name in zip(view.times, view.files, strict=True):
        out = folder.renders / (Path(name).stem + ".png")  # lossless, whatever the ground truth's format
        if out.is_file():
            continue
        img = method.render(view.K, view.w2c, view.width, view.height, t, test_view=True)
        if not torch.isfinite(img).all():
            raise UserError(
                f"render of test time {t} contains NaN/Inf: the model diverged; lower the learning rates or "
                "loss weights you changed (--set ...) and re-run with --force"
            )
        arr = (img.detach().clamp(0, 1).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)
        write_image(out, arr)


NO_GROUND_TRUTH = "no ground truth"
"""What ``metrics.json`` (``protocol.name``) and the tables say of a run on a scene without test views."""


def _evaluate(folder: RunFolder, root: Path, req: RunRequest, device: torch.device) -> dict[str, float]:
    from benchmarks.evaluation.evaluate import evaluate_folder

    gt = root / "gt_images"
    if not (gt.is_dir() and any(gt.iterdir())):
        # No metrics.csv: there is nothing to score. The record says why, for the tables and the report.
        atomic_write_json(
            folder.metrics_json,
            {"protocol": {"name": NO_GROUND_TRUTH}, "ground_truth": False,
             "note": f"{root}: the scene has no test views (e.g. imported from a video), so nothing is scored"},
        )  # fmt: skip
        print(
            f"{NO_GROUND_TRUTH}: {root} has no test views; the model is saved, nothing scored",
            file=sys.stderr,
        )
        return {}

    mask_dir = root / "masks"
    has_masks = mask_dir.is_dir() and any(mask_dir.iterdir())
    res = evaluate_folder(
        folder.renders,
        root / "gt_images",
        mask_dir=mask_dir if has_masks else None,
        protocol="worldtree",
        out_csv=folder.metrics_csv,
        lpips_weights=req.lpips_weights,
        device=str(device),
    )
    if not folder.metrics_json.is_file():
        atomic_write_json(folder.metrics_json, res.record)
    return _finite_means(res.mean)


def _finite_means(row) -> dict[str, float]:
    """The finite numbers of the table's mean row (LPIPS is empty when its weights are missing)."""
    out = {}
    for k, v in row.items():
        if k == "frame":
            continue
        try:
            fv = float(v)
        except (TypeError, ValueError):
            continue
        if np.isfinite(fv):
            out[str(k)] = fv
    return out


def _read_mean(folder: RunFolder) -> dict[str, float]:
    try:
        return dict(json.loads(folder.done.read_text()).get("mean", {}))
    except (OSError, json.JSONDecodeError):
        return {}
