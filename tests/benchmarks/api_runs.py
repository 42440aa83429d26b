"""Finished tiny runs for the Python API and export tests: a static run with view-dependent colour (SH degree 1),
a Base run and a WorldTree run with one split, each made by `wtbench run`'s executor on the CPU with the
cheapest settings that still give each method's model its parts (dynamic Gaussians, a scaffold, tree nodes)."""

from __future__ import annotations

from pathlib import Path

from benchmarks.runner.runs import RunRequest, execute

# 14 frames: the WorldTree run splits its root once ([0, 5] and [6, 13]; a child needs 12 / 2 frames or more).
FRAMES = 14
# The smoke preset's stages shortened further (what is tested is saving and loading, not the fit).
SHORT = [
    "ba.steps=5",
    "sw.steps=5",
    "scaffold_fit.steps=3",
    "test_pose.first_steps=2",
    "test_pose.next_steps=1",
]


def make_runs(tmp: Path, write_tiny_scene) -> dict[str, Path]:
    """``{"scene": SCENE, "static": RUN, "base": RUN, "worldtree": RUN}`` under ``tmp``."""
    scene = write_tiny_scene(tmp / "tiny14", frames=FRAMES)
    common = {"scene": scene, "runs_dir": tmp / "runs", "device": "cpu", "progress": False}
    static = execute(
        RunRequest(
            method="static", preset="quick", overrides={"steps": 8, "downscale": 1},
            sets=["init_num_points=300", "sh_degree=1", "sh_increase_every=1"], **common,
        )
    )  # fmt: skip
    base = execute(RunRequest(method="base", preset="smoke", overrides={"steps": 8}, sets=SHORT, **common))
    tree = execute(
        RunRequest(
            method="worldtree", preset="smoke", overrides={"steps": 8}, options={"depth": 1, "sequential": True},
            sets=[*SHORT, "layer_steps=4"], **common,
        )
    )  # fmt: skip
    return {
        "scene": scene,
        "static": static.folder.root,
        "base": base.folder.root,
        "worldtree": tree.folder.root,
    }
