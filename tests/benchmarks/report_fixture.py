"""A tiny generated sweep for the report tests: two scenes, three configurations, one unfinished run and a
failure recorded in a sweep report; one run has a video.

Scenes come from tests/methods/scene_fixture.py; each finished run's "renders" are the ground truth plus
noise of a per-configuration strength, scored by the real harness (:func:`benchmarks.evaluation.evaluate.evaluate_folder`),
so metrics.csv/metrics.json hold real per-frame scores and checksums. Folders, config.json and timing.json
come from runs_fixture.write_run.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np

from benchmarks.evaluation.evaluate import evaluate_folder
from benchmarks.reporting.video import compose_frames, write_video
from worldtree.imageio import read_image, write_image


def _load(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


_here = Path(__file__).parent
rf = _load("wt_tests_runs_fixture_report", _here / "runs_fixture.py")
sf = _load("wt_tests_scene_fixture_report", _here.parent / "methods" / "scene_fixture.py")

SCENES = ("SceneA", "SceneB")
#: (method, tag, ablate, noise std in grey levels, train seconds); one row of the table each. The third is
#: slower and worse than the second, so it is off the Pareto front.
CONFIGS = (
    ("static", "quick", None, 30.0, 5.0),
    ("worldtree", "quick", None, 6.0, 40.0),
    ("worldtree", "quick-nosac", ["sac"], 12.0, 50.0),
)
FRAMES = 4
#: Image size of the fixture's scenes (scene_fixture's default).
WIDTH, HEIGHT = 64, 36


#: What runs with imported priors record (``nvls import`` folders, many ``--set`` overrides): with these,
#: every configuration name of the fixture is 150 characters or more (``write_sweep(long_names=True)``).
LONG_SETS = (
    "priors.depth_import.fit_scale_shift=true",
    "priors.depth_import.kind=disparity",
    "priors.depth_import.merge=fill",
)
LONG_PRIORS = {"depth_maps": "/data/priors/balloon1_dav2"}


def _imported_priors(folder: Path, k: int) -> None:
    """Add the ``--set`` overrides and imported prior folders of :data:`LONG_SETS`/:data:`LONG_PRIORS` to a
    run's config.json; ``k`` makes one override differ per configuration (the tail of the name)."""
    path = folder / "config.json"
    record = json.loads(path.read_text())
    record["sets"] = [*LONG_SETS, f"train.tv_weight=0.{k + 1}"]
    record["imported_priors"] = dict(LONG_PRIORS)
    path.write_text(json.dumps(record))


def write_sweep(root: Path, long_names: bool = False) -> tuple[Path, Path]:
    """Write scenes under ``root/scenes`` and runs under ``root/runs``; return (runs_dir, scenes_dir).
    ``long_names``: the runs record imported priors and ``--set`` overrides, so that their configuration
    names are 150 characters or more (as real runs with imported priors have)."""
    runs, scenes = root / "runs", root / "scenes"
    rng = np.random.default_rng(0)
    for s in SCENES:
        scene = sf.write_tiny_scene(scenes / s, frames=FRAMES)
        for k, (method, tag, ablate, noise, train_s) in enumerate(CONFIGS):
            folder = rf.write_run(
                runs, s, method, tag, {}, config={"ablate": ablate} if ablate else None, train_s=train_s,
                scene_dir=scene,
            )  # fmt: skip
            if long_names:
                _imported_priors(folder.root, k)
            folder.renders.mkdir()
            for gt in sorted((scene / "gt_images").iterdir()):
                img = read_image(gt).astype(np.float64) + rng.normal(0.0, noise, (36, 64, 3))
                write_image(folder.renders / gt.name, np.clip(img + 0.5, 0, 255).astype(np.uint8))
            evaluate_folder(
                folder.renders, scene / "gt_images", scene / "masks", lpips_weights=False,
                out_csv=folder.metrics_csv,
            )  # fmt: skip
    # One run has its video (`wtbench video`'s render | ground truth | mask mp4).
    video_run = runs / SCENES[0] / CONFIGS[1][0] / CONFIGS[1][1]
    write_video(compose_frames(video_run)[0], video_run / "test_view.mp4")
    # A run of a fourth configuration that has not finished: listed with its state, not in the table.
    unfinished = rf.write_run(runs, "SceneA", "base", "quick", {}, done=False, scene_dir=scenes / "SceneA")
    if long_names:
        _imported_priors(unfinished.root, len(CONFIGS))
    report = {
        "grid": "paper-ablation",
        "runs": [
            {"scene": "SceneB", "label": "BA- SW- TPT- SAC-", "status": "failed", "error": "out of memory"}
        ],
    }
    (runs / "sweep-paper-ablation.json").write_text(json.dumps(report))
    return runs, scenes
