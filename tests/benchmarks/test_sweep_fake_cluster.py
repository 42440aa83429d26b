"""A Slurm sweep against a fake cluster: small `sbatch`, `squeue` and `scancel` shell scripts on PATH (no real
Slurm). sbatch refusing a job is one line saying what sbatch said and the option that fixes it; --device cpu
asks for no GPU; a job the cluster will never start (pending for PartitionConfig) stops the sweep in one line
and is cancelled instead of being waited for, for ever."""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import pytest
from typer.testing import CliRunner

from benchmarks.cli import app
from benchmarks.runner import sweep_executors as se
from worldtree.infra.errors import UserError

SBATCH = """#!/bin/sh
if [ -e "$FAKE/refuse" ]; then
  echo "sbatch: error: $(cat "$FAKE/refuse")" >&2
  exit 1
fi
n=$(( $(cat "$FAKE/count" 2>/dev/null || echo 100) + 1 ))
echo $n > "$FAKE/count"
cp "$1" "$FAKE/script_$n.sh"
echo "Submitted batch job $n"
"""
# squeue -h -o FORMAT --states=all -j ID,ID: every job pending for the reason in $FAKE/reason.
SQUEUE = """#!/bin/sh
while [ $# -gt 0 ]; do [ "$1" = "-j" ] && ids=$2; shift; done
for id in $(echo "$ids" | tr , ' '); do echo "$id|PENDING|$(cat "$FAKE/reason")"; done
"""
SCANCEL = """#!/bin/sh
echo "$@" >> "$FAKE/cancelled"
"""


@pytest.fixture
def fake(tmp_path, monkeypatch) -> Path:
    state = tmp_path / "fake"
    bin_dir = state / "bin"
    bin_dir.mkdir(parents=True)
    # srun is only looked for by submitit (the job script calls it; no job runs here).
    for name, text in (
        ("sbatch", SBATCH),
        ("squeue", SQUEUE),
        ("scancel", SCANCEL),
        ("srun", "#!/bin/sh\nexit 1\n"),
    ):
        p = bin_dir / name
        p.write_text(text)
        p.chmod(p.stat().st_mode | stat.S_IXUSR)
    (state / "reason").write_text("Priority")
    monkeypatch.setenv("FAKE", str(state))
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    return state


def _sweep(scene: Path, runs: Path, *extra: str):
    argv = ["sweep", "--scenes", str(scene), "--grid", "seeds", "--method", "static", "--preset", "quick",
            "-o", str(runs), "--executor", "slurm", *extra]  # fmt: skip
    return CliRunner().invoke(app, argv)


def test_a_refused_submission_says_what_sbatch_said_and_the_fix(fake, tmp_path, write_tiny_scene):
    scene = write_tiny_scene(tmp_path / "scenes" / "tiny", frames=1)
    (fake / "refuse").write_text("Batch job submission failed: Requested node configuration is not available")
    res = _sweep(scene, tmp_path / "runs")
    assert isinstance(res.exception, UserError), res.output
    msg = str(res.exception)
    assert "\n" not in msg
    assert "sbatch refused" in msg and "Requested node configuration is not available" in msg
    assert "--slurm-gpus-per-job 1" in msg and "--device cpu" in msg  # what was asked, and the fix
    assert "sbatch: error" not in res.output  # sbatch's words once, in the error line, not printed before it
    (fake / "refuse").write_text("Batch job submission failed: Invalid generic resource (gres) specification")
    res = _sweep(scene, tmp_path / "runs")
    assert "Invalid generic resource" in str(res.exception) and "--device cpu" in str(res.exception)


def test_cpu_sweep_asks_for_no_gpu_and_stops_on_a_job_that_never_runs(
    fake, tmp_path, write_tiny_scene, monkeypatch
):
    monkeypatch.setattr(se, "NEVER_RUNS_GRACE_S", 0.0)
    scene = write_tiny_scene(tmp_path / "scenes" / "tiny", frames=1)
    (fake / "reason").write_text("PartitionConfig")
    runs = tmp_path / "runs"
    res = _sweep(scene, runs, "--device", "cpu", "--slurm-cpus-per-job", "3")
    assert isinstance(res.exception, UserError), res.output
    msg = str(res.exception)
    assert "\n" not in msg
    assert "Slurm will never start job" in msg and "PartitionConfig" in msg
    assert "--slurm-cpus-per-job 3" in msg and "cancelled 4 pending job(s)" in msg
    scripts = sorted(fake.glob("script_*.sh"))
    assert len(scripts) == 4  # the four seeds, submitted at once
    for s in scripts:
        text = s.read_text()
        assert "#SBATCH --cpus-per-task=3" in text
        options = [ln.split("=")[0] for ln in text.splitlines() if ln.startswith("#SBATCH")]
        assert "#SBATCH --cpus-per-task" in options
        assert not [o for o in options if "gpu" in o or "gres" in o], options  # --device cpu: no GPU
    assert sorted((fake / "cancelled").read_text().split()) == ["101", "102", "103", "104"]
    jobs = [json.loads(p.read_text())["jobs"][-1] for p in runs.rglob("job.json")]
    assert len(jobs) == 4 and all(j["state"] == "failed" and "PartitionConfig" in j["error"] for j in jobs)


def test_a_job_waiting_for_resources_is_waited_for(fake, tmp_path, monkeypatch):
    """Reasons a job leaves by itself (Priority, Resources) never stop a sweep; unknown reasons neither."""
    for reason in ("Priority", "Resources", "None", "AssocGrpCpuLimit", ""):
        assert se.never_runs(reason) is None
    assert se.never_runs("ReqNodeNotAvail, UnavailableNodes:wtnode") is not None
    assert se.slurm_jobs(["7", "8"]) == {"7": ("PENDING", "Priority"), "8": ("PENDING", "Priority")}
