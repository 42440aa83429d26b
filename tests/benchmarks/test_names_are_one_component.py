"""A name the user gives that becomes a folder (``wtbench run --tag``, ``nvls import/build --name``) is exactly
one path component, checked before anything is created or deleted; ``--force`` deletes only a folder the tool
made itself (issue #30: ``--tag $PWD/victim --force`` deleted ``victim/``, ``--name . --force`` emptied -o)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from benchmarks.runner.runs import RunRequest, execute
from nvidia_ls.build import BuildConfig
from nvidia_ls.importer import ImportConfig, import_scene
from nvidia_ls.synth import SynthConfig, write_raw_scene
from worldtree.infra.errors import UserError
from worldtree.infra.output_paths import check_name, check_replaceable

HOSTILE = [
    "",
    ".",
    "..",
    "../x",
    "../../x",
    "a/b",
    "a\\b",
    "/abs",
    "a\nb",
    "a\rb",
    "tab\there",
    ".hidden",
    " x",
]


@settings(max_examples=300, deadline=None)
@given(st.text(min_size=0, max_size=40))
def test_an_accepted_name_is_one_child_of_its_parent(name):
    try:
        check_name(name, "--tag")
    except UserError as e:
        assert "\n" not in str(e) and "\r" not in str(e)  # the message stays one line, whatever the name
        assert str(e).startswith("--tag ")
        return
    root = Path("/r/o/o/t")
    child = Path(os.path.normpath(root / name))
    assert child.parent == root and child.name == name


@pytest.mark.parametrize("name", HOSTILE + ["/".join(["x"] * 3), "x" * 256])
def test_hostile_names_are_refused(name):
    with pytest.raises(UserError):
        check_name(name, "--name")


def _victim(folder: Path) -> Path:
    folder.mkdir(parents=True)
    (folder / "precious.txt").write_text("mine")
    return folder


def _nothing_under(path: Path) -> list[str]:
    return sorted(str(p.relative_to(path)) for p in path.rglob("*")) if path.exists() else []


@pytest.mark.parametrize("tag", HOSTILE + ["ABS"])
def test_run_tag_that_is_not_one_name_is_refused_before_anything(scene, tmp_path, tag):
    victim = _victim(tmp_path / "victim")
    tag = str(victim) if tag == "ABS" else tag
    runs = tmp_path / "runs"
    req = RunRequest(scene=scene, method="static", runs_dir=runs, preset="quick", device="cpu",
                     overrides={"steps": 1}, tag=tag, force=True, progress=False)  # fmt: skip
    with pytest.raises(UserError, match="^--tag ") as err:
        execute(req)
    assert "\n" not in str(err.value)
    assert (victim / "precious.txt").read_text() == "mine"
    assert _nothing_under(runs) == [] and sorted(p.name for p in tmp_path.iterdir()) == ["victim"]


def test_run_force_deletes_only_a_run_folder(scene, tmp_path, small_quick):
    runs = tmp_path / "runs"
    mine = _victim(runs / "tiny" / "static" / "mine")
    req = RunRequest(scene=scene, method="static", runs_dir=runs, preset="quick", device="cpu",
                     overrides={"steps": 1}, tag="mine", force=True, progress=False)  # fmt: skip
    with pytest.raises(UserError, match="not a run folder this tool made .*no config.json"):
        execute(req)
    assert (mine / "precious.txt").is_file()
    # Without --force the run will not write into it either.
    with pytest.raises(UserError, match="holds files but no config.json"):
        execute(RunRequest(**{**req.__dict__, "force": False}))
    (mine / "precious.txt").unlink()
    execute(req)  # an empty folder, then a real run folder, is replaced
    assert (mine / "DONE").is_file()
    execute(req)
    assert (mine / "DONE").is_file() and not (mine / "precious.txt").exists()


def test_run_scene_dot_keeps_the_scene_name(scene, tmp_path, small_quick, monkeypatch):
    monkeypatch.chdir(scene)
    runs = tmp_path / "runs"
    execute(RunRequest(scene=Path("."), method="static", runs_dir=runs, preset="quick", device="cpu",
                       overrides={"steps": 1}, progress=False))  # fmt: skip
    assert (runs / "tiny" / "static" / "quick-steps1" / "DONE").is_file()


def test_run_tag_cli_is_one_line(scene, tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "benchmarks.cli", "run", "--method", "static", "--scene", str(scene),
         "-o", str(tmp_path / "runs"), "--preset", "quick", "--device", "cpu", "--tag", "../../x", "--force"],
        capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path)),
    )  # fmt: skip
    assert out.returncode == 2, out.stderr
    assert out.stderr.splitlines() == [
        "error: --tag '../../x': is a path (holds '/' or '\\'), not one folder name; give one folder name "
        "(letters, digits, '-', '_', '.'), e.g. run1"
    ]
    assert not (tmp_path / "runs").exists() and not (tmp_path / "x").exists()


@pytest.mark.parametrize("name", HOSTILE)
def test_import_name_is_refused_before_anything(tmp_path, name):
    box = _victim(tmp_path / "box")
    src = tmp_path / "src"  # never read: the name is refused first
    with pytest.raises(UserError, match="^--name ") as err:
        import_scene(src, box, ImportConfig(name=name, force=True), log=lambda m: None)
    assert "--force" not in str(err.value)  # not the fix for a name that is a path
    assert sorted(p.name for p in box.iterdir()) == ["precious.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["box"]


def test_import_force_over_a_user_folder_is_refused(tmp_path):
    user = _victim(tmp_path / "box" / "Scene")
    with pytest.raises(UserError, match="not a scene folder this tool made"):
        import_scene(tmp_path / "src", tmp_path / "box", ImportConfig(name="Scene", force=True), log=print)
    assert (user / "precious.txt").is_file()


@pytest.mark.parametrize("name", HOSTILE)
def test_build_name_is_refused(name):
    with pytest.raises(UserError, match="^--name "):
        BuildConfig(name=name).check()


def test_synth_force_replaces_only_its_own_capture(tmp_path):
    user = _victim(tmp_path / "raw")
    with pytest.raises(UserError, match="not a raw capture of `nvls synth`"):
        write_raw_scene(user, SynthConfig(), force=True)
    assert (user / "precious.txt").is_file()


def test_check_replaceable_refuses_links_and_files(tmp_path):
    target = _victim(tmp_path / "target")
    (tmp_path / "link").symlink_to(target)
    (tmp_path / "file").write_text("x")
    for p in ("link", "file"):
        with pytest.raises(UserError, match="not a run folder this tool made"):
            check_replaceable(tmp_path / p, "--force", "run folder", ("config.json",))
    (tmp_path / "empty").mkdir()
    check_replaceable(tmp_path / "empty", "--force", "run folder", ("config.json",))  # nothing to lose
    (target / "config.json").write_text("{}")
    check_replaceable(target, "--force", "run folder", ("config.json",))
