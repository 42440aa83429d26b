"""Methods registered by name: a typed config with named presets, a description, and a builder.

A new method is one module that defines its config dataclass and a class implementing :class:`Method`, and
calls :func:`register_method` at import. Methods are found through the Python entry points of the group
:data:`ENTRY_POINT_GROUP` (``wtbench.methods``; as nerfstudio finds its methods): an installed package that
declares ``[project.entry-points."wtbench.methods"] NAME = "its.module"`` appears in ``wtbench run --list``
with nothing changed here. This package declares its own methods the same way; :data:`METHOD_MODULES` also
imports them when the installed metadata predates those entry points (an editable install not re-installed).

Every config dataclass has the fields of :class:`CommonConfig` (``seed``, ``steps``, ``downscale``), which
``wtbench run`` can override from the command line.
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Protocol

import torch

from methods.plugin import Grid, MethodOption, SharedRoot
from worldtree.budget import BudgetConfig
from worldtree.gaussian_frame import GaussianFrame, RenderMode
from worldtree.infra.config_ranges import in_range
from worldtree.infra.errors import UserError
from worldtree.plateau import PlateauRule
from worldtree.scene import Scene
from worldtree.trainer import TrainContext, TrainSummary

# This package's methods (also entry points in pyproject.toml): modules that register methods when imported.
METHOD_MODULES: tuple[str, ...] = ("methods.static3dgs", "methods.base", "methods.worldtree")
#: Entry-point group of methods: each entry point names a module that registers its methods when imported, or
#: a :class:`MethodSpec` object, which is registered.
ENTRY_POINT_GROUP = "wtbench.methods"

COMMON_FIELDS = ("seed", "steps", "downscale")
#: The quick presets train at full size up to this many pixels (frames x width x height): a 12-frame 480x270
#: capture (1.56 M) then trains at the size it is scored at in a few minutes on 2 cores (Base about 3 min at
#: 600 steps); longer videos (the demo's 40 frames at 320x180, 2.3 M) keep half size and their time.
QUICK_FULL_SIZE_PIXELS = 2_000_000


@dataclass
class CommonConfig:
    """Fields every method config has (and ``wtbench run`` may override)."""

    seed: int = 0
    """Seed of every random-number generator of the run."""
    steps: int = 30_000
    """Optimisation steps of the main training stage."""
    downscale: int = 1
    """Train on images shrunk by this integer factor (renders are still made at the test images' size)."""
    full_size_pixels: int = field(default=0, metadata=in_range(0, None, "a number of pixels; 0 turns it off"))
    """Train at full size instead (``downscale`` 1) when the training video holds at most this many pixels,
    frames x width x height (0: never): the quick presets' 2,000,000 train a 12-frame 480x270 capture at the
    size it is scored at, and keep half size for longer videos. A ``downscale`` given explicitly wins."""
    budget: BudgetConfig = field(default_factory=BudgetConfig)
    """Gaussian budget and contribution pruning (:mod:`worldtree.budget`; ``budget.enabled``)."""
    early_stop: PlateauRule = field(default_factory=PlateauRule)
    """Stop a fit when its loss plateaus (:mod:`worldtree.plateau`; ``early_stop.enabled``)."""

    def downscale_for(self, frames: int, width: int, height: int) -> int:
        """The training shrink for a video of ``frames`` images of ``width x height`` pixels (full size):
        1 when it holds at most ``full_size_pixels`` pixels, else ``downscale``."""
        if 0 < int(frames) * int(width) * int(height) <= self.full_size_pixels:
            return 1
        return self.downscale

    def with_exact_steps(self):
        """This config when the user asked for exactly ``steps`` main-stage steps (``--steps N``): a config
        whose step count grows with the video's length turns that off here (Base: ``steps_per_frame``).
        Default: unchanged."""
        return self

    def adaptive_default(self) -> bool:
        """Whether ``budget`` / ``early_stop`` with ``enabled=None`` are on (WorldTree: with ``--depth auto``)."""
        return False

    def budget_on(self) -> bool:
        """Whether the Gaussian budget and pruning apply."""
        return self.adaptive_default() if self.budget.enabled is None else bool(self.budget.enabled)

    def early_stop_on(self) -> bool:
        """Whether fits stop at a loss plateau."""
        return self.adaptive_default() if self.early_stop.enabled is None else bool(self.early_stop.enabled)

    def ignored_settings(self) -> dict[str, str]:
        """Settings (dotted ``--set`` keys) that a run of this config never reads, each with why and the fix:
        ``--set`` refuses them, so that a ``--set`` either changes the run or is an error (it would rename the
        run folder and change nothing). Subclasses add their own (``super()`` first)."""
        out: dict[str, str] = {}
        if not self.budget_on():
            out.update(settings_of("budget", self.budget, "the Gaussian budget is off; --set budget.enabled=true"))
        if not self.early_stop_on():
            out.update(settings_of("early_stop", self.early_stop, "early stop is off; --set early_stop.enabled=true"))
        return out


def at_training_size(cfg, root: str | Path, dropped_frames: int = 0):
    """``cfg`` with the shrink its ``downscale_for`` gives the training video of scene ``root`` less
    ``dropped_frames`` frames (``wtbench run``: none; leave-one-out: the held-out one); ``cfg`` itself for a
    config without ``downscale_for``. A caller whose user gave a downscale keeps it and does not call this."""
    if not hasattr(cfg, "downscale_for"):
        return cfg
    from worldtree.scene_schema import read_cameras

    doc = read_cameras(root)
    d = cfg.downscale_for(len(doc.frames) - int(dropped_frames), doc.width, doc.height)
    return cfg if d == cfg.downscale else replace(cfg, downscale=d)


def settings_of(prefix: str, obj: Any, why: str, skip: tuple[str, ...] = ("enabled",)) -> dict[str, str]:
    """``{"<prefix>.<field>": why}`` for every field of the dataclass ``obj`` except ``skip`` (its switch)."""
    return {f"{prefix}.{f.name}": why for f in fields(obj) if f.name not in skip}


class Method(Protocol):
    """What ``wtbench run`` needs from a method built for one scene."""

    def fit(self, ctx: TrainContext) -> TrainSummary:
        """Train (resuming from ``ctx.checkpoint_dir`` when it holds checkpoints)."""
        ...

    def render(
        self, K: torch.Tensor, w2c: torch.Tensor, width: int, height: int, time: int, test_view: bool = False
    ) -> torch.Tensor:
        """Image ``[height, width, 3]`` in [0, 1] of camera ``K [3,3]``, ``w2c [4,4]`` at time index ``time``.
        ``test_view``: the camera is the scene's held-out test camera (the runner says so; a method may
        use what it learnt about that camera, e.g. a refined pose)."""
        ...

    def save_model(self, folder: Path) -> None:
        """Write the final model (loadable) into ``folder``."""
        ...

    # Loading a finished run (benchmarks.api.load_run, `wtbench export`, `wtbench view`; docs/python_api.md). A
    # method without these still runs and is scored; only loading its runs is refused.
    def load_model(self, folder: Path) -> None:
        """The inverse of :meth:`save_model`: on a method built from the run's recorded config and scene, read
        ``folder`` so that :meth:`render` draws exactly what the run drew (test views from its refined poses)."""
        ...

    def gaussians_at(self, time: int) -> GaussianFrame:
        """Every Gaussian drawn at time index ``time`` (:class:`worldtree.gaussian_frame.GaussianFrame`: model
        world frame, activated opacities, log scales, SH DC colour, a dynamic flag, the scene->model Sim(3))."""
        ...

    def model_w2c(
        self, w2c: torch.Tensor, time: float, test_view: bool = False, frame: int | None = None
    ) -> torch.Tensor:
        """``[4, 4]`` pose in the model's world frame that :meth:`render` uses for the given ``w2c`` (scene
        frame): the refined test pose (``test_view``), training frame ``frame``'s own fitted pose, or else the
        camera as the method places one it did not train with at ``time`` (frames; a method that moves its
        cameras: the scene->model Sim(3), and the Base methods the training frames' residuals near ``time``)."""
        ...

    def render_mode(
        self, K: torch.Tensor, w2c: torch.Tensor, width: int, height: int, time: int,
        mode: RenderMode = "rgb", test_view: bool = False, frame: int | None = None,
    ) -> torch.Tensor:  # fmt: skip
        """:meth:`render` as ``mode`` (``rgb`` [H, W, 3] as :meth:`render`; ``depth`` [H, W] scene units, NaN
        where nothing is drawn; ``alpha`` [H, W]; ``dynamic`` [H, W, 3] the dynamic Gaussians alone), the
        camera placed by :meth:`model_w2c`."""
        ...

    def node_at(self, time: float) -> int | None:
        """The tree node that draws ``time`` (WorldTree; 1 = root), None for a method without a tree. A
        fractional ``time`` names the node that :meth:`render_between` draws it with."""
        ...

    # Leave-one-out (benchmarks.evaluation.leave_one_out): a time the method never trained on. Optional: for a
    # method without it the harness renders the nearer trained frame (:func:`render_between`).
    def render_between(
        self, K: torch.Tensor, w2c: torch.Tensor, width: int, height: int, time: float
    ) -> torch.Tensor:
        """Image ``[height, width, 3]`` in [0, 1] of camera ``K``/``w2c`` (scene frame, placed as
        :meth:`model_w2c` places a camera that is neither a test view nor a training frame) at a fractional
        ``time`` between the training frames ``floor(time)`` and ``floor(time) + 1`` (``2.5``: halfway between
        frames 2 and 3); an integer ``time`` is that frame, as :meth:`render` draws it. A method with motion
        draws its own motion there (Base: every Gaussian between its two positions); one that cannot interpolate
        draws the nearer trained frame, the later one at exactly halfway (:func:`nearer_frame`), as the harness
        does for a method without this."""
        ...

    def stats(self) -> dict[str, Any]:
        """Numbers for ``timing.json``: at least ``num_gaussians`` and ``backend``."""
        ...


def nearer_frame(time: float) -> int:
    """The training frame nearest to ``time``; exactly halfway between two frames, the later one."""
    return math.floor(time + 0.5)


def render_between(
    method: Method, K: torch.Tensor, w2c: torch.Tensor, width: int, height: int, time: float
) -> torch.Tensor:
    """``method.render_between(...)`` (:meth:`Method.render_between`), or for a method without it its
    :meth:`Method.render` at the :func:`nearer_frame`."""
    own = getattr(method, "render_between", None)
    if callable(own):
        return own(K, w2c, width, height, time)
    return method.render(K, w2c, width, height, nearer_frame(time))


def render_training_frame(
    method: Method, K: torch.Tensor, w2c: torch.Tensor, width: int, height: int, frame: int
) -> torch.Tensor:
    """``[height, width, 3]`` of training frame ``frame`` through the camera the method trained it with
    (:meth:`Method.render_mode` with ``frame``: a fitted pose where the method refines its cameras), or
    :meth:`Method.render` of the given camera for a method without ``render_mode``."""
    own = getattr(method, "render_mode", None)
    if callable(own):
        return own(K, w2c, width, height, frame, "rgb", frame=frame)
    return method.render(K, w2c, width, height, frame)


def node_at(method: Method, time: float) -> int | None:
    """``method.node_at(time)``, None for a method without it."""
    own = getattr(method, "node_at", None)
    return own(time) if callable(own) else None


@dataclass(frozen=True)
class MethodSpec:
    """A registered method."""

    name: str
    """Name used by ``--method``."""
    description: str
    """One line shown in listings."""
    config_cls: type
    """Config dataclass (with the :class:`CommonConfig` fields)."""
    presets: Mapping[str, Callable[[], Any]]
    """Preset name -> config factory; ``quick`` and ``paper`` at least."""
    build: Callable[[Any, Scene, torch.device], Method]
    """Entry point: ``build(config, scene, device) -> Method``."""
    options: tuple[MethodOption, ...] = ()
    """Config fields that `wtbench run` offers as options of their own (``--chain-length``), in run-folder-name
    order (:class:`methods.plugin.MethodOption`); ``--set`` reaches every field."""
    grids: Mapping[str, Grid] = field(default_factory=dict)
    """Named sweep grids of the method (``wtbench sweep --grid NAME``; :class:`methods.plugin.Grid`)."""
    shared_root: SharedRoot | None = None
    """The first stages another run may lend (``wtbench run --root-from``; :class:`methods.plugin.SharedRoot`);
    None: the method trains everything itself."""

    @property
    def ablations(self) -> tuple[str, ...]:
        """Names ``--ablate`` accepts, in display order: the config's ``ablation_names()`` (its ``ablate`` field
        holds those given); none for a config without them."""
        names = getattr(self.config_cls, "ablation_names", None)
        return tuple(names()) if names is not None else ()

    def config(self, preset: str) -> Any:
        """The config of ``preset``."""
        if preset not in self.presets:
            raise UserError(
                f"--preset {preset}: method {self.name!r} has presets {', '.join(sorted(self.presets))}"
            )
        return self.presets[preset]()


_METHODS: dict[str, MethodSpec] = {}


def register_method(spec: MethodSpec) -> MethodSpec:
    """Add ``spec`` to the registry (a second registration of the same name replaces the first)."""
    names = {f.name for f in fields(spec.config_cls)}
    missing = [f for f in COMMON_FIELDS if f not in names]
    if missing:
        raise TypeError(f"config of method {spec.name!r} lacks the common fields {missing}")
    for required in ("quick", "paper"):
        if required not in spec.presets:
            raise TypeError(f"method {spec.name!r} must define a {required!r} preset")
    if spec.ablations and "ablate" not in names:
        raise TypeError(f"config of method {spec.name!r} names ablations but has no 'ablate' field")
    for opt in spec.options:
        if opt.field not in names or opt.field in (*COMMON_FIELDS, "ablate"):
            raise TypeError(f"option {opt.field!r} of method {spec.name!r}: not a config field of its own")
    tags = [opt.tag for opt in spec.options]
    if "" in tags or len(set(tags)) != len(tags):
        raise TypeError(f"method {spec.name!r}: option tags must be distinct and non-empty: {tags}")
    _METHODS[spec.name] = spec
    return spec


_BROKEN: dict[str, str] = {}
"""Entry points whose loading failed: name -> ``"value: error"`` (shown when that method is asked for)."""
_LOADED = False


def _load_all() -> None:
    """Import this package's methods and load every entry point of :data:`ENTRY_POINT_GROUP` (once). A plug-in
    that fails to load is left out with a one-line warning, so that it breaks no other method."""
    global _LOADED
    if _LOADED:
        return
    import warnings
    from importlib.metadata import entry_points

    for mod in METHOD_MODULES:
        importlib.import_module(mod)
    _LOADED = True
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if ep.value in METHOD_MODULES:
            continue
        try:
            obj = ep.load()
        except Exception as e:  # any error of a third-party import
            _BROKEN[ep.name] = f"{ep.value}: {type(e).__name__}: {e}".splitlines()[0]
            warnings.warn(f"method plug-in {ep.name!r} not loaded ({_BROKEN[ep.name]})", stacklevel=2)
            continue
        if isinstance(obj, MethodSpec):
            register_method(obj)


def list_methods() -> list[MethodSpec]:
    """Every registered method, sorted by name."""
    _load_all()
    return [_METHODS[k] for k in sorted(_METHODS)]


def get_method(name: str) -> MethodSpec:
    """The method called ``name``; an unknown name is a :class:`UserError` listing the registered ones."""
    _load_all()
    if name not in _METHODS:
        if name in _BROKEN:
            raise UserError(f"--method {name}: its plug-in failed to load ({_BROKEN[name]}); fix or uninstall it")
        known = ", ".join(sorted(_METHODS)) or "(none)"
        raise UserError(f"--method {name!r} is not a registered method; choose one of: {known}")
    return _METHODS[name]
