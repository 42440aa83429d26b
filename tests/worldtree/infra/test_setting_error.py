"""SettingError: the library names a config field (``WorldTreeConfig.depth``) or a parameter (``device``); a
command line names the option that set it (worldtree.infra.cli_runner.options_named), for options generated
from configs (nvls, `wtbench run`), options written by hand (`wtbench prep`) and options every command shares."""

from __future__ import annotations

import pickle
import sys
from dataclasses import dataclass, field

import pytest
import typer

from worldtree.infra.cli_runner import options_named, run_cli
from worldtree.infra.errors import SettingError, UserError
from worldtree.infra.typed_config import setting_paths


def test_message_option_and_pickle():
    e = SettingError("WorldTreeConfig.depth", -1, "must be >= 0")
    assert str(e) == "WorldTreeConfig.depth -1: must be >= 0" and isinstance(e, UserError)
    assert str(e.as_option("--depth")) == "--depth -1: must be >= 0"
    back = pickle.loads(pickle.dumps(e))  # sweeps carry errors across processes
    assert type(back) is SettingError and (back.setting, back.value, back.why) == (e.setting, -1, e.why)


def test_options_named_maps_known_settings_only():
    with pytest.raises(UserError, match=r"^--depth -1: must be >= 0$"):
        with options_named({"WorldTreeConfig.depth": "--depth"}):
            raise SettingError("WorldTreeConfig.depth", -1, "must be >= 0")
    with pytest.raises(SettingError, match=r"^WorldTreeConfig.split x: "):  # no option for it: as it was
        with options_named({"WorldTreeConfig.depth": "--depth"}):
            raise SettingError("WorldTreeConfig.split", "x", "choose one of median, flow")


@dataclass
class Leaf:
    a: int = 1


@dataclass
class Top:
    n: int = 0
    one: Leaf = field(default_factory=Leaf)
    other: Leaf = field(default_factory=Leaf)


def test_setting_paths_of_real_and_ambiguous_configs():
    from methods.worldtree import WorldTreeConfig

    paths = setting_paths(WorldTreeConfig)
    assert paths["WorldTreeConfig.depth"] == "depth"
    assert paths["PriorsConfig.depth_source"] == "priors.depth_source"
    assert setting_paths(Top) == {"Top.n": "n"}  # Leaf.a sits at two paths: not named by either


def test_library_names_fields_and_commands_name_options(tmp_path):
    from methods.worldtree import WorldTreeConfig
    from nvidia_ls.cli import _import_options, app
    from nvidia_ls.config_options import ConfigCommand

    with pytest.raises(SettingError, match=r"^WorldTreeConfig.depth -2: must be >= 0"):
        WorldTreeConfig(depth=-2)
    # nvls: generated options, nested configs included (ImportConfig.video -> --video-*).
    cmd = ConfigCommand(lambda **kw: None, _import_options)
    named = cmd._options(_import_options())
    assert named["VideoConfig.stride"] == "--video-stride" and named["ImportConfig.layout"] == "--layout"
    from typer.testing import CliRunner

    res = CliRunner().invoke(app, ["synth", str(tmp_path / "s"), "--objects", "5"])
    assert str(res.exception) == "--objects 5: choose 0, 1 or 2"


def test_run_cli_names_the_apps_shared_options(capsys, monkeypatch):
    app = typer.Typer()

    @app.command()
    def go(where: str) -> None:
        raise SettingError("device", repr(where), "not a device name")

    @app.command()
    def other() -> None:
        pass

    monkeypatch.setattr(sys, "argv", ["prog", "go", "gpu9"])
    with pytest.raises(SystemExit) as e:
        run_cli(app, options={"device": "--device"})
    assert e.value.code == 2 and capsys.readouterr().err == "error: --device 'gpu9': not a device name\n"
