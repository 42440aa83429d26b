"""`nvls build`'s options are generated from BuildConfig: every field is reachable from the command line with
its default and help, every option reaches a field, and `--sfm-threads` is no longer dropped."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import typing
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

import nvidia_ls.build
from nvidia_ls.build import BuildConfig
from nvidia_ls.cli import app
from nvidia_ls.config_options import ConfigCommand, Shown, config_options, field_docs
from nvidia_ls.masks import MaskConfig

# Parameters of `nvls build` that are not BuildConfig fields.
OWN_PARAMS = {"raw_dir", "out_dir"}


@pytest.fixture
def built(monkeypatch):
    """Run `nvls build ARGS` in-process with build_scene replaced; returns the (raw_dir, out_dir, cfg) it got."""
    calls = []

    def fake_build_scene(raw_dir, out_dir, cfg, log=None, progress=None):
        calls.append((raw_dir, out_dir, cfg))
        return Path(out_dir) / "Scene"

    monkeypatch.setattr(nvidia_ls.build, "build_scene", fake_build_scene)

    def run(*args: str):
        res = CliRunner().invoke(app, ["build", *map(str, args)])
        assert res.exit_code == 0, (res.output, res.exception)
        assert len(calls) == 1
        return calls.pop()

    return run


def _build_command() -> ConfigCommand:
    (info,) = [c for c in app.registered_commands if c.name == "build"]
    assert isinstance(info.callback, ConfigCommand)
    return info.callback


def _leaves(cls: type, prefix: tuple[str, ...] = ()) -> set[tuple[str, ...]]:
    """Paths of every non-dataclass field of ``cls``, nested dataclasses walked."""
    hints = typing.get_type_hints(cls)
    out = set()
    for f in dataclasses.fields(cls):
        path = (*prefix, f.name)
        out |= _leaves(hints[f.name], path) if dataclasses.is_dataclass(hints[f.name]) else {path}
    return out


@pytest.mark.parametrize("threads", [1, 3])
def test_sfm_threads_reaches_build_config(built, threads):
    raw_dir, out_dir, cfg = built("raw", "--sfm-threads", threads, "-o", "out")
    assert isinstance(cfg, BuildConfig)
    assert cfg.sfm_threads == threads
    assert (raw_dir, out_dir) == (Path("raw"), Path("out"))


def test_no_options_give_the_dataclass_defaults(built):
    _, out_dir, cfg = built("raw")
    assert cfg == BuildConfig()
    assert out_dir == Path("scenes")


def test_every_field_is_an_option_and_every_option_a_field():
    options = _build_command().options
    assert {o.path for o in options} == _leaves(BuildConfig)
    command = typer.main.get_command(app).commands["build"]
    params = {p.name for p in command.params} - {"help"}
    assert params == {o.param for o in options} | OWN_PARAMS


def test_help_and_defaults_come_from_build_config():
    docs = field_docs(BuildConfig)
    by_path = {o.path: o for o in _build_command().options}
    assert by_path[("sfm_threads",)].help == docs["sfm_threads"]
    assert by_path[("sfm_threads",)].default == BuildConfig().sfm_threads
    assert by_path[("mask", "threshold")].default == MaskConfig().threshold
    assert by_path[("mask", "threshold")].help == field_docs(MaskConfig)["threshold"]
    out = subprocess.run(
        [sys.executable, "-m", "nvidia_ls.cli", "build", "--help"],
        capture_output=True, text=True, check=True, env={**os.environ, "COLUMNS": "200"},
    )  # fmt: skip
    assert "--sfm-threads" in out.stdout and "CPU threads given to pycolmap" in out.stdout
    assert "--mask-threshold" in out.stdout and "--preview-frames" in out.stdout


def _non_default_args(option, tmp: Path) -> tuple[list[str], object]:
    """Command-line words setting ``option`` to a value other than its default, and the field value expected."""
    flag = option.decls[0].split("/")[0]
    base = option.type
    if option.path == ("size",):
        return [flag, "64x48"], (64, 48)
    if base is bool or base == (bool | None):
        assert option.default is False
        return [flag], True
    if Path in getattr(base, "__args__", (base,)):
        return [flag, str(tmp / option.param)], tmp / option.param
    if int in getattr(base, "__args__", (base,)):
        value = (option.default or 0) + 2
        return [flag, str(value)], value
    if float in getattr(base, "__args__", (base,)):
        value = (option.default or 0.0) + 0.5
        return [flag, str(value)], value
    if str in getattr(base, "__args__", (base,)):
        value = f"{option.default}-changed"
        return [flag, value], value
    raise AssertionError(f"no test value for {option.dotted}: {base}")


def test_every_option_reaches_its_field(built, tmp_path):
    for option in _build_command().options:
        words, expected = _non_default_args(option, tmp_path)
        _, _, cfg = built("raw", *words)
        assert _get(cfg, option.path) == expected, option.dotted
        # ... and no other field moved
        changed = {
            o.dotted for o in _build_command().options if _get(cfg, o.path) != _get(BuildConfig(), o.path)
        }
        assert changed == {option.dotted}


def _get(obj, path):
    for name in path:
        obj = getattr(obj, name)
    return obj


@dataclasses.dataclass
class _Inner:
    level: float = 0.5
    """Inner level."""


@dataclasses.dataclass
class _Demo:
    count: int = 3
    """How many."""
    pair: tuple[int, int] | None = None
    """A pair."""
    inner: _Inner = dataclasses.field(default_factory=_Inner)
    """Nested."""
    on: bool = True
    """Switch."""


def test_generator_refuses_unknown_types_stale_entries_and_missing_help():
    with pytest.raises(TypeError, match="pair"):
        config_options(_Demo)
    pair = Shown(type=str | None, parse=lambda s: s and tuple(map(int, s.split(","))))
    with pytest.raises(KeyError, match="paire"):
        config_options(_Demo, {"pair": pair, "paire": Shown()})

    @dataclasses.dataclass
    class NoHelp:
        count: int = 3

    with pytest.raises(TypeError, match="string literal"):
        config_options(NoHelp)
    opts = {o.dotted: o for o in config_options(_Demo, {"pair": pair})}
    assert opts["inner.level"].decls == ("--inner-level",) and opts["inner.level"].help == "Inner level."
    assert opts["on"].decls == ("--on/--no-on",) and opts["count"].default == 3


def test_generated_command_builds_nested_configs_and_parses():
    got = []
    pair = Shown(type=str | None, parse=lambda s: s and tuple(map(int, s.split(","))))

    def make(name: str, cfg=None) -> None:
        got.append((name, cfg))

    demo = typer.Typer()
    demo.command()(ConfigCommand(make, lambda: (_Demo, config_options(_Demo, {"pair": pair}))))
    demo.command("other")(lambda: None)  # two commands, so typer keeps the subcommand name
    res = CliRunner().invoke(
        demo, ["make", "x", "--count", "5", "--pair", "1,2", "--inner-level", "0.25", "--no-on"]
    )
    assert res.exit_code == 0, res.output
    assert got == [("x", _Demo(count=5, pair=(1, 2), inner=_Inner(level=0.25), on=False))]


def test_docs_list_every_build_option():
    table = (Path(__file__).resolve().parents[2] / "docs" / "nvidia_ls.md").read_text()
    missing = [o.decls[0] for o in _build_command().options if f"`{o.decls[0]}" not in table]
    assert missing == [], "docs/nvidia_ls.md's `nvls build` table lacks these options"
