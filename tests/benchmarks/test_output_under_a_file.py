"""`-o FILE/sub` (an output path running through a file) is one line naming the option, for every command
that writes a folder or file, before any work; and the CLI runner turns any NotADirectoryError that a
command's own check missed into one line too."""

from __future__ import annotations

import pytest
from typer.testing import CliRunner

from benchmarks.cli import app as wtbench
from nvidia_ls.cli import app as nvls
from worldtree.infra.errors import UserError


@pytest.fixture
def afile(tmp_path):
    f = tmp_path / "FILE"
    f.write_text("not a folder")
    return f


def _cases(tmp_path, afile):
    src = tmp_path / "src"
    src.mkdir()
    return [
        (wtbench, ["report", str(tmp_path), "-o", str(afile / "sub")], "-o"),
        (wtbench, ["plot", str(tmp_path), "-o", str(afile / "x.png")], "-o"),
        (wtbench, ["video", str(tmp_path), "-o", str(afile / "x.mp4")], "-o"),
        (wtbench, ["demo", "-o", str(afile / "sub")], "-o"),
        (nvls, ["import", str(src), "-o", str(afile / "sub")], "-o"),
        (nvls, ["synth", str(afile / "sub")], "OUT_DIR"),
        (nvls, ["gt-priors", str(src), str(src), "--out", str(afile / "sub")], "--out"),
    ]


def test_output_under_a_file_is_one_line(tmp_path, afile):
    for app, argv, option in _cases(tmp_path, afile):
        res = CliRunner().invoke(app, argv)
        assert isinstance(res.exception, UserError), (argv, res.output, res.exception)
        msg = str(res.exception)
        assert "\n" not in msg and msg.startswith(f"{option} {afile}/") and "is a file" in msg, (argv, msg)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["FILE", "src"]  # nothing was created


def test_cli_runner_turns_not_a_directory_into_one_line(tmp_path, afile, capsys):
    from worldtree.infra.cli_runner import run_cli

    def app(standalone_mode=False):
        (afile / "sub").mkdir(parents=True)

    with pytest.raises(SystemExit) as e:
        run_cli(app)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error:") and "is a file, not a folder" in err
