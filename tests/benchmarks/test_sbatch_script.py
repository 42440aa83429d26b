"""The sbatch script of a Slurm sweep, rendered by submitit without a cluster: every value that reaches it
is one line (issue #30: a newline in --slurm-partition, --slurm-mem or a --slurm-arg started a shell command
of its own and ended the #SBATCH header, so --time and the requeue --signal were ignored)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
from submitit.slurm.slurm import _make_sbatch_string

from benchmarks.runner.sweep_executors import (
    SlurmOptions,
    check_jobs_folder,
    parse_slurm_args,
    slurm_job_name,
    slurm_parameters,
)
from worldtree.infra.errors import UserError

COMMAND = "/usr/bin/python3 -u -m submitit.core._submit /runs/.sweep-jobs/%j"


def _script(opts: SlurmOptions, device: str = "cuda", job_name: str = "wtbench-tiny-quick") -> str:
    """The script submitit writes for one job of a sweep with ``opts`` (as ``run_tasks`` configures it)."""
    return _make_sbatch_string(
        command=COMMAND,
        folder=Path("/runs/.sweep-jobs/%j"),
        job_name=job_name,
        **slurm_parameters(opts, device),
    )


def _lines_ok(script: str) -> list[str]:
    """The lines of ``script`` that are none of the expected ones."""
    sbatch = re.compile(r"#SBATCH --[a-z][a-z0-9-]*=(?:[A-Za-z0-9_.,:%@/+-]+|'[^'\n]*')")
    expected = {"#!/bin/bash", "", "# Parameters", "# command", "export SUBMITIT_EXECUTOR=slurm"}
    odd = []
    for line in script.split("\n"):
        if line in expected or sbatch.fullmatch(line):
            continue
        if line.startswith("srun --unbuffered --output /runs/.sweep-jobs/%j/") and line.endswith(COMMAND):
            continue
        odd.append(line)
    return odd


def test_a_normal_script_has_only_expected_lines():
    extra = parse_slurm_args(["account=proj", "qos=high", "comment=ablation sweep", "--constraint=a100"])
    script = _script(SlurmOptions(partition="gpu", time_min=90, cpus_per_job=4, mem="32G", extra=extra))
    assert _lines_ok(script) == []
    keys = re.findall(r"^#SBATCH --([a-z-]+)=", script, flags=re.M)
    assert sorted(keys) == sorted([
        "account", "comment", "constraint", "cpus-per-task", "error", "gpus-per-node", "job-name", "mem",
        "nodes", "ntasks-per-node", "open-mode", "output", "partition", "qos", "signal", "time", "wckey",
    ])  # fmt: skip
    assert "#SBATCH --time=90" in script and "#SBATCH --comment='ablation sweep'" in script
    assert "#SBATCH --signal=USR2@90" in script  # requeue on the time limit relies on it


@pytest.mark.parametrize(
    ("make", "needle"),
    [
        (lambda: SlurmOptions(partition="gpu\necho PWNED"), "--slurm-partition"),
        (lambda: SlurmOptions(partition="gpu\recho PWNED"), "--slurm-partition"),
        (lambda: SlurmOptions(partition="gpu debug"), "--slurm-partition"),
        (lambda: SlurmOptions(mem="1G\n#SBATCH --time=1"), "--slurm-mem"),
        (lambda: SlurmOptions(mem="lots"), "--slurm-mem"),
        (lambda: SlurmOptions(cpus_per_job=0), "--slurm-cpus-per-job"),
        (lambda: SlurmOptions(time_min=0), "--slurm-time"),
        (lambda: parse_slurm_args(["qos\necho PWNED=normal"]), "--slurm-arg"),
        (lambda: parse_slurm_args(["qos=normal\necho PWNED"]), "--slurm-arg"),
        (lambda: parse_slurm_args(["qos=normal\x00x"]), "--slurm-arg"),
        (lambda: parse_slurm_args(["qos;rm -rf x=1"]), "--slurm-arg"),
        (lambda: parse_slurm_args(["'qos'=1"]), "--slurm-arg"),
        (lambda: parse_slurm_args(["signal=USR1@1"]), "`wtbench sweep` sets"),
        (lambda: parse_slurm_args(["output=/tmp/x"]), "`wtbench sweep` sets"),
        (lambda: parse_slurm_args(["time=1"]), "use --slurm-time instead"),
        (lambda: SlurmOptions(extra={"qos\necho PWNED": "normal"}), "--slurm-arg"),
        (lambda: SlurmOptions(extra={"qos": "normal\necho PWNED"}), "--slurm-arg"),
        (lambda: check_jobs_folder(Path("/runs\necho PWNED/.sweep-jobs")), "-o"),
    ],
)
def test_hostile_values_are_refused_in_one_line(make, needle):
    with pytest.raises(UserError) as err:
        make()
    msg = str(err.value)
    assert msg.startswith(needle) or needle in msg
    assert "\n" not in msg and "\r" not in msg


def test_job_name_from_a_hostile_scene_name_stays_one_line():
    name = slurm_job_name("evil\necho PWNED", "quick\r")
    assert name == "wtbench-evil_echo_PWNED-quick_"
    assert _lines_ok(_script(SlurmOptions(), job_name=name)) == []


def test_sweep_cli_refuses_a_hostile_slurm_arg_in_one_line(tmp_path, write_tiny_scene):
    scene = write_tiny_scene(tmp_path / "scenes" / "tiny", frames=1)
    out = subprocess.run(
        [sys.executable, "-m", "benchmarks.cli", "sweep", "--scenes", str(scene), "--grid", "seeds",
         "--method", "static", "--preset", "quick", "-o", str(tmp_path / "runs"), "--executor", "slurm",
         "--slurm-arg", "qos\necho PWNED=normal"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert out.returncode == 2, out.stderr
    assert out.stderr.splitlines() == [
        "error: --slurm-arg 'qos\\necho PWNED=normal': KEY must be an sbatch option name (letters, digits, "
        "'-', '_'), e.g. --slurm-arg account=myproject"
    ]
    assert not (tmp_path / "runs").exists()
