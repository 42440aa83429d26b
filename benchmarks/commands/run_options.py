"""The options `wtbench run` and `wtbench sweep` share, declared once, and the typed object they fill in.

Each shared option is one ``typer.Option`` here that both commands use as a parameter default; the values
end up in one :class:`RunOptions`, which builds the :class:`benchmarks.runner.runs.RunRequest` of a run and its
canonical command line (``command.txt``), for a single run and for every run of a sweep alike.
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import typer

from worldtree.infra.cli_runner import one_line_warning

__all__ = ["RunOptions", "one_line_warning"]

# Help of the imported-prior options, worded as `wtbench prep`'s options for the same files.
PRIOR_HELP = {
    "masks": "Folder of dynamic masks (one per frame) replacing EPI masks; sets priors.masks_source.",
    "tracks": "CoTracker .npy/.npz/.pt file of tracks to import; sets priors.tracks_source.",
    "depth_maps": "Depth file/folder to import (prep's --depth PATH); sets priors.depth_source.",
    "flow": "Folder of <i>_<j>.flo/.npy flow to import; sets priors.flow_source.",
}

OUT = typer.Option(Path("runs"), "--out", "-o", help="Root folder of the run folders.")
PRESET = typer.Option("paper", "--preset", help="Config preset: quick (CPU minutes), paper (or smoke).")
DEVICE = typer.Option("auto", "--device", help="auto, cpu, cuda or cuda:N.")
STEPS = typer.Option(None, "--steps", help="Override the number of (root) training steps.")
SEED = typer.Option(None, "--seed", help="Override the random seed.")
LPIPS_WEIGHTS = typer.Option(
    None, "--lpips-weights", help="Folder holding alexnet-owt-7be5be79.pth and alex.pth."
)
SET = typer.Option(
    None,
    "--set",
    metavar="KEY=VALUE",
    help="Change any config field, e.g. photometric.lambda_depth=0.1 or priors.epi.threshold_px=1.0 "
    "(dotted path, value parsed by the field's type); repeatable. See docs/running.md.",
)
MASKS = typer.Option(None, "--masks", help=PRIOR_HELP["masks"])
TRACKS = typer.Option(None, "--tracks", help=PRIOR_HELP["tracks"])
DEPTH_MAPS = typer.Option(None, "--depth-maps", help=PRIOR_HELP["depth_maps"])
FLOW = typer.Option(None, "--flow", help=PRIOR_HELP["flow"])


@dataclass
class RunOptions:
    """What a `wtbench run` (or each run of a sweep) is asked for, besides its scene and method options."""

    method: str
    runs_dir: Path = Path("runs")
    preset: str = "paper"
    device: str = "auto"
    overrides: dict[str, Any] = field(default_factory=dict)
    """``steps`` / ``seed`` / ``downscale`` given on the command line."""
    sets: list[str] = field(default_factory=list)
    """``--set KEY=VALUE`` items, as given."""
    priors: dict[str, Path] = field(default_factory=dict)
    """Imported priors (``benchmarks.runner.runs.PRIOR_OPTIONS`` name -> absolute path)."""
    lpips_weights: Path | None = None
    tensorboard: bool = False
    tag: str | None = None
    root_from: Path | None = None
    """``--root-from``: a run folder lending this run its first stages (a sweep sets it per run)."""

    @classmethod
    def from_cli(cls, method: str, masks, tracks, depth_maps, flow, steps=None, seed=None, downscale=None,
                 sets=None, **kw: Any) -> RunOptions:  # fmt: skip
        """The object of a command's parameters: prior paths resolved, overrides that were given kept."""
        from benchmarks.runner.runs import resolve_prior_paths

        given = (("steps", steps), ("seed", seed), ("downscale", downscale))
        priors = resolve_prior_paths({"masks": masks, "tracks": tracks, "depth_maps": depth_maps, "flow": flow})
        return cls(method, overrides={k: v for k, v in given if v is not None}, sets=list(sets or []),
                   priors=priors, **kw)  # fmt: skip

    def request(self, scene: Path, options: dict | None = None, overrides: dict | None = None,
                root_from: Path | None = None, **kw: Any):  # fmt: skip
        """The :class:`~benchmarks.runner.runs.RunRequest` of ``scene`` with the method ``options`` and extra
        ``overrides`` (a sweep's grid point), grown on ``root_from``'s root (default: this object's);
        ``kw``: its other fields (``force``, ``progress``...)."""
        from benchmarks.runner.runs import RunRequest

        ovr = {**self.overrides, **(overrides or {})}
        opts = dict(options or {})
        lender = root_from if root_from is not None else self.root_from
        return RunRequest(
            scene=scene, method=self.method, runs_dir=self.runs_dir, preset=self.preset, device=self.device,
            overrides=ovr, options=opts, sets=list(self.sets), priors=dict(self.priors),
            lpips_weights=self.lpips_weights, tensorboard=self.tensorboard, tag=self.tag, root_from=lender,
            command=self.command_line(scene, opts, ovr, lender), **kw,
        )  # fmt: skip

    def command_line(self, scene: Path, options: dict, overrides: dict, root_from: Path | None = None) -> str:
        """The command in canonical form (every resolved option), so that it can be pasted to repeat the run
        however it was invoked (shell, script, sweep, or in-process)."""
        from benchmarks.runner.runs import option_flag

        parts = ["wtbench", "run", "--method", self.method, "--scene", str(scene), "-o", str(self.runs_dir)]
        parts += ["--preset", self.preset, "--device", self.device]
        for k, v in overrides.items():
            parts += [f"--{k}", str(v)]
        for k, v in options.items():  # a list repeats its option; True is a flag given
            flag = option_flag(k)
            if isinstance(v, list | tuple):
                for item in v:
                    parts += [flag, str(item)]
            elif v is True:
                parts.append(flag)
            else:
                parts += [flag, str(v)]
        for item in self.sets:
            parts += ["--set", item]
        for k, v in self.priors.items():
            parts += [option_flag(k), str(v)]
        if self.lpips_weights is not None:
            parts += ["--lpips-weights", str(self.lpips_weights)]
        if self.tensorboard:
            parts.append("--tensorboard")
        if self.tag is not None:
            parts += ["--tag", self.tag]
        if root_from is not None:
            parts += ["--root-from", str(root_from)]
        return shlex.join(parts)
