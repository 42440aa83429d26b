"""The sampling-profile summary: py-spy collapsed stacks counted by process, kind of work and stage."""

from __future__ import annotations

import pytest

from benchmarks.speed.sampled import main, report, summarise
from worldtree.infra.errors import UserError

MAIN = 'process 11:"python -m benchmarks.cli run --method worldtree"'
WORKER = 'process 12:"python -B -c from multiprocessing.spawn import spawn_main; spawn_main(tracker_fd=9)"'
STEP = "<module> (benchmarks/cli.py:1);PhotometricFit.training_step (worldtree/stages/photometric.py:400)"
BACKWARD = "backward (torch/autograd/__init__.py:200);_engine_run_backward (torch/autograd/graph.py:979)"

LINES = [
    f"{MAIN};{STEP};_RasterizeCPU.forward (worldtree/render/cpu_kernel.py:102) 7",
    # the kernel's backward runs inside autograd's: the innermost kind wins
    f"{MAIN};{STEP};{BACKWARD};_RasterizeCPU.backward (worldtree/render/cpu_kernel.py:120) 3",
    # a torch operator's backward has no Python frame of its own: autograd's
    f"{MAIN};{STEP};{BACKWARD} 5",
    f"{MAIN};{STEP};arap (worldtree/motion/regularizers.py:50);safe_unit (worldtree/motion/_safe.py:57) 2",
    # a tree worker importing torch while the root trains (its command line holds a ';')
    f"{MAIN};{WORKER};<module> (<string>:1);_warm (worldtree/tree/parallel.py:236);"
    "_find_and_load (<frozen importlib._bootstrap>:1) 4",
    f"{MAIN};<module> (benchmarks/cli.py:1);helper (benchmarks/runner/runs.py:10) 1",
    "",
]


def test_counts_by_process_kind_and_stage():
    s = summarise(LINES)
    assert s.total == 22
    assert s.processes == {"main": 18, "tree worker": 4}
    assert s.kinds == {
        "raster fwd": 7, "raster bwd": 3, "autograd other": 5, "motion regs": 2, "imports": 4, "other Python": 1,
    }  # fmt: skip
    assert s.stages == {"photometric": 17, "tree": 4, "outside the stages": 1}
    text = report(s, top=3)
    assert "31.8 %  raster fwd" in text  # 7 / 22
    assert "18.2 %  tree worker" in text  # 4 / 22


def test_bad_line_and_missing_file_are_one_line_errors(tmp_path, capsys):
    with pytest.raises(UserError, match="line 2: not a collapsed stack"):
        summarise(["a;b 1", "no count here"])
    with pytest.raises(SystemExit) as e:
        main([str(tmp_path / "missing.txt")])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "missing.txt" in err and err.count("\n") == 1


def test_empty_profile():
    assert report(summarise([]), top=5) == "no samples"
