"""The Base method through `wtbench run`'s executor on the tiny analytic scene (smoke schedule)."""

from __future__ import annotations

import dataclasses
import json

import pytest
import torch

import methods.base  # noqa: F401  (registers "base")
from benchmarks.runner.runs import RunRequest, execute
from methods.registry import get_method
from worldtree.dynamic import DynamicGaussians
from worldtree.gaussians import GaussianSet
from worldtree.motion.scaffold import Scaffold


def run(scene, tmp_path, preset: str, ablate: tuple[str, ...] = ()):
    opts = {"ablate": list(ablate)} if ablate else {}
    return execute(
        RunRequest(
            scene=scene,
            method="base",
            runs_dir=tmp_path / "runs",
            preset=preset,
            options=opts,
            progress=False,
        )
    )


@pytest.fixture(scope="module")
def smoke_runs(tiny_scene, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("base_runs")
    torch.set_num_threads(1)
    return {
        "smoke": run(tiny_scene, tmp, "smoke"),
        "noba": run(tiny_scene, tmp, "smoke", ("ba",)),
        "nosw": run(tiny_scene, tmp, "smoke", ("sw",)),
    }


def test_run_layout_model_and_timings(smoke_runs, tiny_scene):
    res = smoke_runs["smoke"]
    folder = res.folder
    assert folder.is_done()
    renders = sorted(p.name for p in folder.renders.iterdir())
    assert renders == [f"v001_t{t:03d}.png" for t in range(6)]
    for k in ("psnr", "ssim", "mpsnr"):
        assert k in res.mean and res.mean[k] == res.mean[k]  # present and not NaN
    timing = json.loads(folder.timing_json.read_text())
    stages = timing["method_stats"]["stages_s"]
    # The stages in the order they ran; the budget's 'prune' only when the budget is on (off for Base smoke).
    order = ["priors", "ba", "sw", "motion", "scaffold", "photometric", "test_pose"]
    assert timing["method_stats"]["stages"] == order and set(stages) == set(order)
    assert all(v >= 0 for v in stages.values())
    assert timing["deterministic"] is True  # a CPU run trains with torch's deterministic kernels
    # Loadable model files.
    m = folder.model
    static = GaussianSet.load(m / "static_gaussians.pt")
    dyn = DynamicGaussians.load(m / "dynamic_gaussians.pt")
    extra = torch.load(m / "scaffold_cameras.pt", weights_only=True)
    scf = Scaffold.from_state(extra["scaffold"])
    assert len(static) == timing["method_stats"]["num_static"]
    assert len(dyn) == timing["method_stats"]["num_dynamic"]
    assert scf.T == 6 and extra["w2cs"].shape == (6, 4, 4)
    assert set(extra["test_poses"]) == set(range(6))
    cfg = json.loads(folder.config_json.read_text())
    assert cfg["preset"] == "smoke" and cfg["config"]["ablate"] == []


def test_ablations_are_recorded_and_change_the_result(smoke_runs):
    base = json.loads(smoke_runs["smoke"].folder.timing_json.read_text())["method_stats"]
    no_ba = json.loads(smoke_runs["noba"].folder.timing_json.read_text())["method_stats"]
    no_sw = json.loads(smoke_runs["nosw"].folder.timing_json.read_text())["method_stats"]
    assert no_ba["ablate"] == ["ba"] and base["ablate"] == [] and no_sw["ablate"] == ["sw"]
    # Without BA the cameras are the given ones, untouched: reprojection stats stay at zero.
    assert no_ba["ba"]["reproj_px_after"] == 0.0 and base["ba"]["reproj_px_after"] > 0.0
    assert no_sw["sw_steps"] == 0 and base["sw_steps"] == 20
    assert smoke_runs["smoke"].mean["psnr"] != smoke_runs["noba"].mean["psnr"]
    assert smoke_runs["smoke"].mean["psnr"] != smoke_runs["nosw"].mean["psnr"]


def test_rerun_resumes_and_skips(smoke_runs, tiny_scene):
    folder = smoke_runs["smoke"].folder
    again = run(tiny_scene, folder.root.parent.parent.parent.parent, "smoke")
    assert again.skipped


def test_presets_and_config_fields():
    spec = get_method("base")
    for name in ("quick", "paper", "smoke"):
        cfg = spec.config(name)
        assert cfg.seed == 0
    paper, quick = spec.config("paper"), spec.config("quick")
    assert (paper.steps, paper.ba.steps, paper.sw.steps) == (4000, 2000, 6000)
    assert paper.photometric.camera_start_step == 1500
    assert (paper.test_pose.first_steps, paper.test_pose.next_steps) == (300, 30)
    assert quick.steps < paper.steps and quick.sw.steps < paper.sw.steps
    # One spelling of an ablation: a stage switched off in its own settings is recorded as its ablation.
    off = dataclasses.replace(quick, ba=dataclasses.replace(quick.ba, enabled=False))
    assert off.ablate == ("ba",) and off.ba.enabled
    assert dataclasses.replace(off, ablate=("ba",)) == off


def test_second_fit_resumes_from_the_checkpoints(tiny_scene, tmp_path, monkeypatch):
    import methods.base as base_module
    from methods.base import STAGE_LEDGER, BaseMethod, smoke_config
    from worldtree.checkpoint import seed_everything
    from worldtree.infra.device import pick_device
    from worldtree.scene import load_scene
    from worldtree.trainer import TrainContext

    scene = load_scene(tiny_scene)
    ctx = TrainContext(checkpoint_dir=tmp_path / "ckpt", progress=False)
    seed_everything(0)
    first = BaseMethod(smoke_config(), scene, pick_device("cpu"))
    s1 = first.fit(ctx)
    img1 = first.render(scene.test_K, scene.test_w2c, scene.width, scene.height, 2, test_view=True)
    assert (tmp_path / "ckpt" / "ba.pt").is_file() and (tmp_path / "ckpt" / "scaffold.pt").is_file()
    assert first.state.scaffold.M > 0
    assert len(first.state.fit.ssim_targets) == 0  # the finished fit keeps no per-frame SSIM statistics

    def no_refit(*args, **kwargs):
        raise AssertionError("the resumed run fitted the scaffold again instead of reading scaffold.pt")

    monkeypatch.setattr(base_module, "fit_scaffold", no_refit)
    seed_everything(0)
    second = BaseMethod(smoke_config(), scene, pick_device("cpu"))
    s2 = second.fit(ctx)
    assert second.state.info["scaffold_fit"] == first.state.info["scaffold_fit"]
    assert (s1.start_step, s1.end_step) == (0, 20) and (s2.start_step, s2.end_step) == (20, 20)
    torch.testing.assert_close(second.state.fit.cameras(), first.state.fit.cameras())
    img2 = second.render(scene.test_K, scene.test_w2c, scene.width, scene.height, 2, test_view=True)
    torch.testing.assert_close(img2, img1)
    # The resumed method's stage times count both sessions (the second only reloads the checkpoints), read
    # from the checkpoint folder's ledger, which holds both sessions.
    t1, t2 = first.stats()["stages_s"], second.stats()["stages_s"]
    assert set(t2) == set(t1) and all(t2[k] >= t1[k] for k in t1), (t1, t2)
    ledger = json.loads((tmp_path / "ckpt" / STAGE_LEDGER).read_text())
    assert len(ledger["sessions_s"]) == 2 and ledger["stages_s"] == pytest.approx(t2)


def test_prior_use_follows_ablations_and_weights():
    """``method_stats.prior_use``: a stage an ablation or a zero weight switches off is not listed; the weights
    are the config's."""
    import dataclasses as dc

    from methods.base import BaseConfig, prior_use

    classical = {"depth": "classical", "flow": "classical", "masks": "classical", "tracks": "classical"}
    cfg = BaseConfig()
    use = prior_use(cfg, classical)
    assert set(use) == {"depth", "masks", "tracks", "flow"}
    assert set(use["depth"]["used_in"]) == {"ba", "sw", "scaffold", "photometric"}
    assert str(cfg.ba.lambda_depth) in use["depth"]["used_in"]["ba"]
    assert "trajectory depth" in use["depth"]["used_in"]["scaffold"]  # classical depth on moving pixels
    assert "motion" in use["masks"]["used_in"]
    off = prior_use(
        dc.replace(cfg, ablate=("ba", "sw"), photometric=dc.replace(cfg.photometric, lambda_track=0.0)), classical
    )
    assert "ba" not in off["depth"]["used_in"] and "ba" not in off["tracks"]["used_in"]
    assert "sw" not in off["depth"]["used_in"] and "sw" not in off["masks"]["used_in"]
    assert "photometric" not in off["tracks"]["used_in"]
    imported = prior_use(cfg, {**classical, "depth": "imported:/x (disparity)"})
    assert imported["depth"]["source"] == "imported:/x (disparity)"
    assert "trajectory depth" not in imported["depth"]["used_in"]["scaffold"]


def test_steps_per_frame_raises_the_photometric_steps(tiny_scene, tmp_path):
    # 6 frames at 5 steps per frame: 30 steps, above the smoke preset's 20.
    torch.set_num_threads(1)
    res = execute(
        RunRequest(scene=tiny_scene, method="base", runs_dir=tmp_path / "runs", preset="smoke",
                   sets=["steps_per_frame=5"], progress=False)
    )  # fmt: skip
    ad = json.loads(res.folder.timing_json.read_text())["method_stats"]["adaptive"]
    assert ad["steps_max"] == ad["steps_taken"] == 30


@pytest.mark.parametrize(
    ("preset", "frames", "steps"),
    [("quick", 12, 600), ("quick", 40, 600), ("quick", 41, 615), ("quick", 160, 2400), ("paper", 160, 4000)],
)
def test_photometric_steps_keep_the_visits_per_frame(preset, frames, steps):
    # The quick preset's 600 steps on 40 frames are 15 visits a frame; longer videos keep that rate, shorter
    # ones keep 600. The paper preset's schedule is fixed.
    cfg = get_method("base").config(preset)
    assert cfg.photometric_steps(frames) == steps
    assert dataclasses.replace(cfg, steps_per_frame=0.0).photometric_steps(frames) == cfg.steps


def test_two_threads_train_the_same_model_as_one(smoke_runs, tiny_scene, tmp_path):
    """The thread governor changes torch's thread count with the machine's load during a run
    (worldtree.infra.thread_governor), which is only sound if the count does not change what is trained."""
    torch.set_num_threads(2)
    try:
        two = run(tiny_scene, tmp_path, "smoke")
    finally:
        torch.set_num_threads(1)
    one = smoke_runs["smoke"]
    assert json.loads(two.folder.timing_json.read_text())["torch_threads"] == 2
    for name in ("static_gaussians.pt", "dynamic_gaussians.pt"):
        a = torch.load(one.folder.model / name, weights_only=True)
        b = torch.load(two.folder.model / name, weights_only=True)
        assert a.keys() == b.keys()
        for k in a:
            if isinstance(a[k], torch.Tensor):
                assert torch.equal(a[k], b[k]), (name, k)
    assert two.mean == one.mean
