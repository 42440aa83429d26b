"""`wtbench run --set` / `--masks ...` and `wtbench sweep --set`: the settings reach the method's config, name
the run folder, are recorded, and bad input is refused with one line naming the option."""

from __future__ import annotations

import dataclasses
import json
import shlex
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
from typer.testing import CliRunner

import benchmarks.runner.runs
from benchmarks.cli import app
from benchmarks.commands.run_options import RunOptions
from benchmarks.commands.sweep import sweep
from benchmarks.runner.runs import RunRequest, resolve_config, run_tag
from methods.registry import get_method
from worldtree.infra.errors import UserError


def test_set_reaches_config_names_folder_and_repeats(scene, tmp_path, small_quick):
    runner = CliRunner()
    sets = ["lambda_dssim=0.35", "strategy.reset_every=7", "init_num_points=150"]
    args = ["run", "--method", "static", "--scene", str(scene), "-o", str(tmp_path), "--preset", "quick"]
    args += ["--steps", "2", "--device", "cpu"]
    for s in sets:
        args += ["--set", s]
    first = runner.invoke(app, args, catch_exceptions=False)
    assert first.exit_code == 0, first.output
    # Hidden names are the run folder's lock file beside it (worldtree.infra.folder_lock).
    folders = [p for p in (tmp_path / "tiny" / "static").iterdir() if not p.name.startswith(".")]
    assert [f.name for f in folders] == [run_tag("quick", {"steps": 2}, None, sets)]
    assert len(folders[0].name) == len("quick-steps2-set") + 8
    folder = folders[0]
    record = json.loads((folder / "config.json").read_text())
    assert record["sets"] == sets and record["imported_priors"] == {}
    cfg = record["config"]
    assert cfg["lambda_dssim"] == 0.35 and cfg["strategy"]["reset_every"] == 7
    assert cfg["init_num_points"] == 150 and cfg["steps"] == 2
    # Fields not set keep the (patched) preset's values.
    assert cfg["checkpoint_every"] == 2 and cfg["strategy"]["refine_every"] == 100
    # command.txt repeats the run: pasted back, it lands in the same folder, which is finished.
    command = (folder / "command.txt").read_text().strip()
    assert command.count("--set ") == 3 and "--set init_num_points=150" in command
    argv = shlex.split(command)
    assert argv[:2] == ["wtbench", "run"]
    again = runner.invoke(app, argv[1:], catch_exceptions=False)
    assert again.exit_code == 0 and "already finished" in again.output
    # The same settings in another order are the same run, too.
    reordered = args[: -2 * len(sets)] + [a for s in reversed(sets) for a in ("--set", s)]
    third = runner.invoke(app, reordered, catch_exceptions=False)
    assert "already finished" in third.output
    # Without --set the run goes to another folder (not run here: only its name is compared).
    assert run_tag("quick", {"steps": 2}) != folder.name


def test_masks_on_static_is_refused(scene, tmp_path):
    masks = tmp_path / "masks"
    masks.mkdir()
    args = ["run", "--method", "static", "--scene", str(scene), "-o", str(tmp_path / "runs")]
    res = CliRunner().invoke(app, args + ["--preset", "quick", "--masks", str(masks)])
    assert isinstance(res.exception, UserError)
    msg = str(res.exception)
    assert msg.startswith("--masks:") and "'static' uses no 2D priors" in msg
    assert not (tmp_path / "runs").exists(), "nothing is written before the check"


def test_prior_options_set_absolute_sources(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "m").mkdir()
    (tmp_path / "flow").mkdir()
    (tmp_path / "tracks.npy").write_bytes(b"")
    (tmp_path / "depth").mkdir()
    spec = get_method("base")
    req = RunRequest(
        scene=Path("."), method="base", preset="smoke",
        priors={"masks": "m", "tracks": "tracks.npy", "depth_maps": "depth", "flow": "flow"},
    )  # fmt: skip
    cfg, sets = resolve_config(spec, req)
    assert cfg.priors.masks_source == str(tmp_path / "m")
    assert cfg.priors.tracks_source == str(tmp_path / "tracks.npy")
    assert cfg.priors.depth_source == str(tmp_path / "depth")
    assert cfg.priors.flow_source == str(tmp_path / "flow")
    assert f"priors.masks_source={tmp_path / 'm'}" in sets and len(sets) == 4
    # --masks DIR and --set priors.masks_source=DIR are the same settings, so the same folder.
    no_masks = {k: v for k, v in req.priors.items() if k != "masks"}
    alt = dataclasses.replace(req, priors=no_masks, sets=[f"priors.masks_source={tmp_path / 'm'}"])
    cfg2, sets2 = resolve_config(spec, alt)
    assert cfg2 == cfg and run_tag("smoke", {}, None, sets2) == run_tag("smoke", {}, None, sets)

    with pytest.raises(UserError, match=r"^--masks nosuch: no such file or folder"):
        resolve_config(spec, dataclasses.replace(req, priors={"masks": "nosuch"}))
    with pytest.raises(UserError, match=r"^--tracks m: not a file"):
        resolve_config(spec, dataclasses.replace(req, priors={"tracks": "m"}))
    with pytest.raises(UserError, match=r"^--flow tracks.npy: not a folder"):
        resolve_config(spec, dataclasses.replace(req, priors={"flow": "tracks.npy"}))
    with pytest.raises(UserError, match=r"also given by --masks"):
        resolve_config(spec, dataclasses.replace(req, sets=["priors.masks_source=/x"]))
    both = RunRequest(
        scene=Path("."), method="base", preset="smoke", overrides={"steps": 4}, sets=["steps=3"]
    )
    with pytest.raises(UserError, match=r"--set steps=3: steps is also given by --steps"):
        resolve_config(spec, both)
    with pytest.raises(UserError, match=r"--set downscale=0: must be at least 1"):
        resolve_config(spec, RunRequest(scene=Path("."), method="base", preset="smoke", sets=["downscale=0"]))


def test_bad_set_key_is_one_line_error(tmp_path, scene):
    out = subprocess.run(
        [sys.executable, "-m", "benchmarks.cli", "run", "--method", "static", "--scene", str(scene),
         "-o", str(tmp_path / "runs"), "--preset", "quick", "--set", "lambda_dsim=0.1"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: --set lambda_dsim:"), out.stderr
    assert "did you mean 'lambda_dssim'" in lines[0] and "init_num_points" in lines[0]
    assert not (tmp_path / "runs").exists()


def test_sweep_passes_sets_and_priors_to_every_run(tmp_path, monkeypatch):
    scene = tmp_path / "scenes" / "a"
    scene.mkdir(parents=True)
    (scene / "cameras.json").write_text("{}")
    masks = tmp_path / "masks"
    masks.mkdir()
    seen: list[RunRequest] = []

    def fake_execute(req):
        seen.append(req)
        return SimpleNamespace(skipped=False, folder=SimpleNamespace(root=tmp_path), mean={})

    monkeypatch.setattr(benchmarks.runner.runs, "execute", fake_execute)
    sets = ["priors.epi.threshold_px=1.0", "photometric.lambda_depth=0.2"]

    def opts(method, **kw):
        return RunOptions(method, runs_dir=tmp_path / "runs", preset="quick", device="cpu", **kw)

    sweep([scene], "split", opts("worldtree", sets=sets, priors={"masks": str(masks)}))
    assert [r.options for r in seen] == [{"split": s} for s in ("binary", "gradient", "flow")]
    assert all(r.sets == sets and r.priors == {"masks": str(masks)} for r in seen)
    assert all("--set priors.epi.threshold_px=1.0" in r.command for r in seen)
    assert all(f"--masks {masks}" in r.command for r in seen)
    report = json.loads((tmp_path / "runs" / "sweep-split.json").read_text())
    assert report["config"]["sets"] == sets and report["config"]["imported_priors"] == {"masks": str(masks)}

    # Refused once, before any run: a bad key, a key the grid varies, priors on a method without them.
    seen.clear()
    with pytest.raises(UserError, match="has no field 'nosuch'"):
        sweep([scene], "split", opts("worldtree", sets=["nosuch=1"]))
    with pytest.raises(UserError, match="the split grid sets split itself"):
        sweep([scene], "split", opts("worldtree", sets=["split=flow"]))
    with pytest.raises(UserError, match="'static' uses no 2D priors"):
        sweep([scene], "seeds", opts("static", priors={"masks": str(masks)}))
    assert seen == []


def test_run_and_sweep_share_one_declaration_of_their_common_options():
    import typer.main

    cli = typer.main.get_command(app)

    def params(name):
        return {o: p for p in cli.commands[name].params for o in p.opts}

    run, sw = params("run"), params("sweep")
    shared = ["--out", "--preset", "--device", "--steps", "--seed", "--lpips-weights", "--set", "--masks",
              "--tracks", "--depth-maps", "--flow"]  # fmt: skip
    for flag in shared:
        assert (run[flag].help, run[flag].default) == (sw[flag].help, sw[flag].default), flag
    # A sweep's run records the command `wtbench run` would record for the same request.
    from benchmarks.commands.run_options import RunOptions

    opts = RunOptions("worldtree", preset="quick", sets=["steps=3"], overrides={"seed": 1})
    req = opts.request(Path("scenes/S"), {"ablate": ["ba"], "sequential": True})
    assert shlex.split(req.command) == [
        "wtbench", "run", "--method", "worldtree", "--scene", "scenes/S", "-o", "runs", "--preset", "quick",
        "--device", "auto", "--seed", "1", "--ablate", "ba", "--sequential", "--set", "steps=3",
    ]  # fmt: skip


def test_quick_presets_train_a_short_video_at_full_size(scene):
    """The quick presets train at full size when frames x width x height is at most ``full_size_pixels``
    (2,000,000: the 12-frame 480x270 protocol yes; the demo's 40 frames at 320x180 and the 160-frame NVIDIA-LS
    video no); ``--downscale`` or ``--set downscale`` wins; 0 turns it off."""
    from benchmarks.runner.runs import training_size

    for name in ("static", "base", "worldtree"):
        quick = get_method(name).presets["quick"]()
        assert quick.downscale == 2
        assert quick.downscale_for(12, 480, 270) == 1
        assert quick.downscale_for(40, 320, 180) == 2
        assert quick.downscale_for(160, 480, 270) == 2
        assert dataclasses.replace(quick, full_size_pixels=0).downscale_for(1, 2, 2) == 2
    spec = get_method("base")
    req = RunRequest(scene=scene, method="base", preset="quick")
    cfg, _ = resolve_config(spec, req)
    assert training_size(cfg, scene, req).downscale == 1  # 6 frames of 64x36
    for given in (dataclasses.replace(req, overrides={"downscale": 2}), dataclasses.replace(req, sets=["downscale=2"])):
        cfg, _ = resolve_config(spec, given)
        assert training_size(cfg, scene, given).downscale == 2
    off = dataclasses.replace(req, sets=["full_size_pixels=0"])
    cfg, _ = resolve_config(spec, off)
    assert training_size(cfg, scene, off).downscale == 2


def test_explicit_steps_are_exact_on_a_long_video():
    # The quick preset raises its steps on long videos (steps_per_frame); --steps N asks for N steps, so it turns
    # that off, unless --set gives steps_per_frame as well.
    spec = get_method("base")
    req = RunRequest(scene=Path("."), method="base", preset="quick")
    assert resolve_config(spec, req)[0].photometric_steps(160) == 2400
    cfg, _ = resolve_config(spec, dataclasses.replace(req, overrides={"steps": 100}))
    assert cfg.steps_per_frame == 0.0 and cfg.photometric_steps(160) == 100
    cfg, _ = resolve_config(spec, dataclasses.replace(req, overrides={"steps": 100}, sets=["steps_per_frame=2"]))
    assert cfg.photometric_steps(160) == 320


def test_exact_steps_leave_a_config_without_a_per_frame_rule_alone():
    # The runner asks every config for exact steps; one with no per-frame rule (static) comes back unchanged.
    spec = get_method("static")
    req = RunRequest(scene=Path("."), method="static", preset="quick", overrides={"steps": 7})
    cfg, _ = resolve_config(spec, req)
    assert cfg == dataclasses.replace(spec.config("quick"), steps=7)
