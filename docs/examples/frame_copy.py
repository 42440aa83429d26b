"""Example method (docs/adding_a_method.md): show the training frame of the same time (or a few frames earlier)."""

from dataclasses import dataclass

import torch

from methods.plugin import Grid, GridPoint, MethodOption
from methods.registry import CommonConfig, MethodSpec, register_method
from methods.stages import Stage, run_stages
from worldtree.infra.timing import StageClock
from worldtree.pixels import unit_float


@dataclass
class FrameCopyConfig(CommonConfig):
    steps: int = 1  # nothing is optimised; kept for the common fields
    lag: int = 0
    """Show the training frame this many frames earlier (0: the frame of the same time)."""


@dataclass
class FrameCopyState:
    scene: object  # worldtree.scene.Scene
    frames: torch.Tensor | None = None  # [T, H, W, 3] in [0, 1], filled in by stage "copy"


def stage_copy(state: FrameCopyState) -> None:
    state.frames = unit_float(state.scene.images)  # the scene holds its frames as uint8


STAGES = (Stage("copy", stage_copy),)


class FrameCopy:
    def __init__(self, cfg: FrameCopyConfig, scene, device: torch.device):
        self.cfg, self.state, self.clock = cfg, FrameCopyState(scene), StageClock()

    def fit(self, ctx):
        run_stages(STAGES, self.state, self.clock)  # each stage timed: stats()["stages_s"]

    def render(self, K, w2c, width, height, time, test_view=False) -> torch.Tensor:
        t = min(max(int(time) - self.cfg.lag, 0), self.state.frames.shape[0] - 1)
        img = self.state.frames[t].permute(2, 0, 1)[None]  # [1, 3, H, W]
        return torch.nn.functional.interpolate(img, size=(height, width), mode="area")[0].permute(1, 2, 0)

    def save_model(self, folder) -> None:
        pass  # nothing learnt to save

    def stats(self) -> dict:
        return {"num_gaussians": 0, "backend": "none", "stages_s": dict(self.clock.stages_s)}


register_method(
    MethodSpec(
        name="frame-copy",
        description="training frame of the same time (or lag frames earlier)",
        config_cls=FrameCopyConfig,
        presets={"quick": FrameCopyConfig, "paper": FrameCopyConfig},
        build=FrameCopy,
        options=(MethodOption("lag", "lag"),),  # `wtbench run --lag N`, run folder quick-lag<N>
        grids={"lags": Grid("lag 0..2", lambda: [GridPoint(f"lag {k}", {"lag": k}) for k in range(3)])},
    )
)
