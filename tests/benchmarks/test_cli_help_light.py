"""`wtbench --help` and commands other than `run` do not import the methods (nor torch): generating `run`'s
method options imports every registered method, which takes seconds; only `wtbench run ...` needs them."""

from __future__ import annotations

import subprocess
import sys

import pytest

PROBE = """
import sys
sys.argv = ["wtbench", *{args!r}]
from benchmarks.cli import main
try:
    main()
except SystemExit:
    pass
print("LOADED", "torch" in sys.modules, "methods.worldtree" in sys.modules, file=sys.stderr)
"""


def _loaded(args: list[str]) -> tuple[bool, bool, str]:
    out = subprocess.run([sys.executable, "-c", PROBE.format(args=args)], capture_output=True, text=True,
                         timeout=120)  # fmt: skip
    line = [ln for ln in out.stderr.splitlines() if ln.startswith("LOADED")][-1].split()
    return line[1] == "True", line[2] == "True", out.stdout


@pytest.mark.parametrize("args", [["--help"], ["table", "--help"], ["sweep", "--help"]])
def test_help_of_other_commands_imports_no_method(args):
    torch_loaded, method_loaded, out = _loaded(args)
    assert not torch_loaded and not method_loaded
    assert "Usage" in out


def test_run_help_lists_the_methods_options():
    _, method_loaded, out = _loaded(["run", "--help"])
    assert method_loaded and "--depth" in out and "--chain-length" in out
