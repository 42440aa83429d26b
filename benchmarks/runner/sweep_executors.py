"""Where a sweep's runs execute: local worker processes (one per GPU, or CPU shares) or Slurm jobs, through
submitit; and what a sweep's run folders say about their state (``wtbench sweep --status``).

Each run is one job that calls :func:`benchmarks.runner.runs.execute` on its request; the job is a submitit
``Checkpointable``, so a Slurm job warned of preemption or of its time limit is requeued and resumes from the
run's own checkpoints. Before submitting, a run already finished is skipped, and a run that another process
holds (its run-folder lock) or that a live job of another sweep will run is left to it; the run-folder lock in
``execute`` catches the rest, so two sweeps never train one run twice.

Bookkeeping: the sweep writes ``job.json`` into each run folder it submits (one entry per submission: executor,
job id, submission time, log, then its end: state, host, device, queue wait, wall time, error). submitit's own
files (pickled job, stdout/stderr logs) live in ``RUNS_DIR/.sweep-jobs/``.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import shutil
import socket
import subprocess
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import submitit

from benchmarks.runner.runs import RunFolder, RunRequest
from benchmarks.runner.sweep import SweepOutcome, run_device
from worldtree.infra.atomic import atomic_write_json
from worldtree.infra.errors import UserError
from worldtree.infra.folder_lock import is_locked, read_holder
from worldtree.infra.output_paths import has_control_characters

EXECUTORS = ("local", "slurm", "auto")
JOB_RECORD = "job.json"
JOBS_DIR = ".sweep-jobs"
# Slurm job states (squeue %T) of a job that will still run or is running.
SLURM_ALIVE = {
    "PENDING", "RUNNING", "CONFIGURING", "COMPLETING", "REQUEUED", "REQUEUE_HOLD", "REQUEUE_FED", "RESIZING",
    "SUSPENDED", "SIGNALING", "STAGE_OUT", "STOPPED",
}  # fmt: skip
# An sbatch option name (``--slurm-arg KEY=VALUE``): submitit writes keys unquoted into ``#SBATCH --KEY=...``.
SBATCH_KEY = re.compile(r"[A-Za-z][A-Za-z0-9_-]*")
# Memory in Slurm's syntax: an integer with an optional K, M, G or T suffix.
SBATCH_MEM = re.compile(r"[0-9]+[KMGTkmgt]?")
# sbatch options the sweep sets itself (job logs, requeue signal, job name) or that have their own option;
# a --slurm-arg of one of them would silently break requeue or the sweep's bookkeeping, or say one thing twice.
SBATCH_OWN = {
    "output": None, "error": None, "open-mode": None, "signal": None, "job-name": None, "array": None,
    "wckey": None, "nodes": None, "ntasks-per-node": None, "partition": "--slurm-partition",
    "time": "--slurm-time", "mem": "--slurm-mem", "cpus-per-task": "--slurm-cpus-per-job",
    "gpus-per-node": "--slurm-gpus-per-job",
}  # fmt: skip
# Seconds a Slurm job may be gone from the queue before its result file shows up (shared file systems lag).
RESULT_GRACE_S = 10.0
# squeue reasons (%r) of a pending job that the cluster, as configured, will never start: the job asks for
# more than a node or partition has (CPUs, GPUs, memory, time), for nodes that are not available, or under
# an account/QOS that does not allow it. Slurm keeps such a job pending for ever; the sweep stops instead.
NEVER_RUNS = {
    "PartitionConfig": "the job asks for more than the partition's nodes have (CPUs, GPUs or memory)",
    "ReqNodeNotAvail": "the nodes the job needs are not available (down, drained or too small)",
    "PartitionNodeLimit": "the job asks for more nodes than the partition allows",
    "PartitionTimeLimit": "the job's time limit is above the partition's",
    "BadConstraints": "no node satisfies the job's constraints",
    "InvalidAccount": "the account is not valid",
    "InvalidQOS": "the QOS is not valid",
    "QOSMaxCpuPerJobLimit": "the job asks for more CPUs than its QOS allows",
    "QOSMaxGRESPerJob": "the job asks for more GPUs than its QOS allows",
    "QOSMaxMemoryPerJob": "the job asks for more memory than its QOS allows",
    "QOSMaxWallDurationPerJobLimit": "the job's time limit is above its QOS's",
}
# Seconds a job may show one of NEVER_RUNS before the sweep gives up on it (Slurm may show a reason briefly
# while a node comes back).
NEVER_RUNS_GRACE_S = 60.0


@dataclass(frozen=True)
class SlurmOptions:
    """Resources of every Slurm job of a sweep (one run per job)."""

    partition: str | None = None
    time_min: int = 24 * 60
    """Time limit per job, minutes; a job reaching it is requeued and resumes from its checkpoint."""
    gpus_per_job: int = 1
    cpus_per_job: int = 4
    mem: str | None = None
    """Memory per job in Slurm's syntax (16G); None: the partition's default."""
    extra: dict[str, str] = field(default_factory=dict)
    """More sbatch options, ``--KEY=VALUE`` (``--slurm-arg KEY=VALUE``), e.g. account, qos, constraint."""

    def __post_init__(self) -> None:
        # Every value here becomes a line of the batch script: a newline in one would start a line of its own
        # (a shell command) and end the #SBATCH header, so --time and the requeue --signal would be ignored.
        if self.partition is not None:
            _script_value(self.partition, "--slurm-partition")
            if not self.partition or any(c.isspace() for c in self.partition):
                raise UserError(f"--slurm-partition {self.partition!r}: give a partition name, e.g. gpu")
        if self.mem is not None and not SBATCH_MEM.fullmatch(self.mem):
            raise UserError(
                f"--slurm-mem {self.mem!r}: give an amount such as 32G (a number with K, M, G or T)"
            )
        for name, value, least in (("--slurm-time", self.time_min, 1), ("--slurm-cpus-per-job", self.cpus_per_job, 1),
                                   ("--slurm-gpus-per-job", self.gpus_per_job, 0)):  # fmt: skip
            if isinstance(value, bool) or not isinstance(value, int) or value < least:
                raise UserError(f"{name} {value!r}: must be a whole number of at least {least}")
        for key, value in self.extra.items():
            check_sbatch_key(key, f"{key}={value}")
            _script_value(str(value), f"--slurm-arg {key}")


def check_sbatch_key(key: str, item: str) -> None:
    """Refuse an sbatch option name ``key`` (of ``--slurm-arg item``) that is not a plain option name, or
    that the sweep sets itself."""
    if not isinstance(key, str) or not SBATCH_KEY.fullmatch(key):
        raise UserError(
            f"--slurm-arg {item!r}: KEY must be an sbatch option name (letters, digits, '-', '_'), "
            "e.g. --slurm-arg account=myproject"
        )
    norm = key.replace("_", "-")
    if norm in SBATCH_OWN:
        use = SBATCH_OWN[norm]
        if use:
            raise UserError(f"--slurm-arg {item!r}: {norm} has its own option; use {use} instead")
        raise UserError(
            f"--slurm-arg {item!r}: `wtbench sweep` sets {norm} itself (job logs, requeue signal, job name); "
            "drop it"
        )


def _script_value(value: str, option: str) -> None:
    if has_control_characters(value):
        raise UserError(f"{option} {value!r}: holds a newline or another control character; give one line")


@dataclass(frozen=True)
class ExecutorConfig:
    """How a sweep runs its runs."""

    kind: str = "local"
    """local or slurm (resolve ``auto`` with :func:`resolve_kind`)."""
    max_parallel: int | None = None
    """Most runs at once; None: local, one per GPU or 1 on CPU; Slurm, every run (the queue decides)."""
    slurm: SlurmOptions = field(default_factory=SlurmOptions)
    poll_s: float = 1.0
    """Seconds between looks at the jobs."""


def resolve_kind(kind: str) -> str:
    """``auto`` -> ``slurm`` when ``sbatch`` is on PATH, else ``local``; other names checked."""
    if kind not in EXECUTORS:
        raise UserError(f"--executor {kind}: choose one of {', '.join(EXECUTORS)}")
    if kind == "auto":
        return "slurm" if shutil.which("sbatch") else "local"
    if kind == "slurm" and not shutil.which("sbatch"):
        raise UserError(
            "--executor slurm: `sbatch` is not on PATH; run on a Slurm login node or use --executor local"
        )
    return kind


def parse_slurm_time(text: str) -> int:
    """A Slurm time limit (``MM``, ``MM:SS``, ``HH:MM:SS``, ``D-HH``, ``D-HH:MM``, ``D-HH:MM:SS``) in whole
    minutes, seconds rounded up."""
    m = re.fullmatch(r"(?:(\d+)-)?(\d+)(?::(\d+))?(?::(\d+))?", text.strip())
    if not m:
        raise UserError(
            f"--slurm-time {text}: give minutes (90), HH:MM:SS (1:30:00) or D-HH:MM:SS (1-00:00:00)"
        )
    days, a, b, c = (int(x) if x is not None else None for x in m.groups())
    if days is not None:  # D-HH[:MM[:SS]]
        h, mins, sec = a, b or 0, c or 0
    elif c is not None:  # HH:MM:SS
        h, mins, sec = a, b, c
    else:  # MM[:SS]
        h, mins, sec = 0, a, b or 0
    minutes = (days or 0) * 1440 + h * 60 + mins + (1 if sec else 0)
    if minutes < 1:
        raise UserError(f"--slurm-time {text}: must be at least one minute")
    return minutes


def parse_slurm_args(items: Sequence[str]) -> dict[str, str]:
    """``--slurm-arg KEY=VALUE`` items as sbatch options (``account=abc`` -> ``--account=abc``)."""
    out: dict[str, str] = {}
    for item in items:
        key, sep, value = item.partition("=")
        key = key.strip().lstrip("-").replace("_", "-")
        if not sep or not key:
            raise UserError(f"--slurm-arg {item!r}: give KEY=VALUE, e.g. --slurm-arg account=myproject")
        check_sbatch_key(key, item)
        _script_value(value, f"--slurm-arg {key}")
        out[key] = value
    return out


def slurm_parameters(s: SlurmOptions, device: str) -> dict[str, Any]:
    """The ``SlurmExecutor.update_parameters`` of every job of a sweep with ``s`` on ``device`` (what the
    sbatch script's ``#SBATCH`` lines say; the job name is added per job, :func:`slurm_job_name`)."""
    params: dict[str, Any] = {
        "time": s.time_min,
        "cpus_per_task": s.cpus_per_job,
        "nodes": 1,
        "ntasks_per_node": 1,
        "additional_parameters": dict(s.extra),
    }
    if s.partition:
        params["partition"] = s.partition
    if s.mem:
        params["mem"] = s.mem
    if s.gpus_per_job > 0 and device != "cpu":
        params["gpus_per_node"] = s.gpus_per_job
    return params


def slurm_job_name(scene: str, tag: str) -> str:
    """The Slurm job name of a run: ``wtbench-<scene>-<tag>``, characters other than letters, digits, ``.``,
    ``_`` and ``-`` replaced by ``_`` (scene folder names come from disk and may hold anything), at most 120."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", f"wtbench-{scene}-{tag}")[:120]


def check_jobs_folder(jobs_dir: Path) -> None:
    """Refuse a jobs folder whose path cannot be written into a batch script line (it names the job logs)."""
    text = str(Path(jobs_dir).absolute())
    if has_control_characters(text):
        raise UserError(
            f"-o {text!r}: holds a newline or another control character; choose another -o for Slurm"
        )


@dataclass
class Task:
    """One run of a sweep: its grid coordinates, request and folder."""

    scene: str
    label: str
    request: RunRequest
    folder: RunFolder | None
    error: str | None = None
    """Why the run cannot start (its config was refused); it is reported failed without a job."""


# -- the job ------------------------------------------------------------------------------------------------


class RunJob(submitit.helpers.Checkpointable):
    """The callable a job runs: one :func:`benchmarks.runner.runs.execute`. submitit pickles it into the job;
    ``checkpoint()`` (from ``Checkpointable``) resubmits it unchanged when Slurm warns of preemption or the
    time limit, and ``execute`` then resumes the run from its newest checkpoint."""

    def __init__(self, request: RunRequest, threads: int | None) -> None:
        self.request = request
        self.threads = threads

    def __call__(self) -> dict[str, Any]:
        return run_in_job(self.request, self.threads)


def run_in_job(request: RunRequest, threads: int | None) -> dict[str, Any]:
    """Execute ``request`` inside a job (``threads``: torch CPU threads, None: torch's default); returns the
    folder, whether it was skipped, its mean scores, the job id, host, device and start/end times."""
    import torch

    from benchmarks.runner.runs import execute
    from worldtree.infra.cli_runner import one_line_warning

    started = time.time()
    if threads:
        torch.set_num_threads(threads)
    with warnings.catch_warnings():
        warnings.showwarning = one_line_warning
        res = execute(request)
    return {
        "folder": str(res.folder.root),
        "skipped": res.skipped,
        "mean": dict(res.mean),
        "job_id": submitit.JobEnvironment().job_id,
        "host": socket.gethostname(),
        "device": run_device(res.folder.root),
        "started": started,
        "ended": time.time(),
    }


# -- job records in run folders -------------------------------------------------------------------------------


def read_jobs(folder: RunFolder) -> list[dict[str, Any]]:
    """The submissions recorded in ``folder/job.json``, oldest first ([] when none or unreadable)."""
    try:
        jobs = json.loads((folder.root / JOB_RECORD).read_text()).get("jobs", [])
    except (OSError, ValueError, AttributeError):
        return []
    return [j for j in jobs if isinstance(j, dict)]


def _write_jobs(folder: RunFolder, jobs: list[dict[str, Any]]) -> None:
    folder.root.mkdir(parents=True, exist_ok=True)
    atomic_write_json(folder.root / JOB_RECORD, {"jobs": jobs})


def _update_last_job(folder: RunFolder, **fields: Any) -> None:
    jobs = read_jobs(folder)
    if jobs:
        jobs[-1].update(fields)
        _write_jobs(folder, jobs)


def slurm_states(job_ids: Sequence[str]) -> dict[str, str] | None:
    """squeue's state of each job still known to Slurm (jobs it has forgotten are absent); None when
    squeue could not be asked."""
    jobs = slurm_jobs(job_ids)
    return None if jobs is None else {jid: state for jid, (state, _) in jobs.items()}


def slurm_jobs(job_ids: Sequence[str]) -> dict[str, tuple[str, str]] | None:
    """squeue's ``(state, reason)`` of each job still known to Slurm (jobs it has forgotten are absent);
    None when squeue could not be asked."""
    if not job_ids:
        return {}
    cmd = ["squeue", "-h", "-o", "%i|%T|%r", "--states=all", "-j", ",".join(job_ids)]
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return None
    if out.returncode != 0 and "invalid job id" not in out.stderr.lower():
        return None
    jobs = {}
    for line in out.stdout.splitlines():
        jid, _, rest = line.strip().partition("|")
        state, _, reason = rest.partition("|")
        if jid:
            jobs[jid] = (state.split()[0] if state.strip() else "UNKNOWN", reason.strip())
    return jobs


def never_runs(reason: str) -> str | None:
    """Why a pending job with squeue reason ``reason`` will never start (:data:`NEVER_RUNS`), or None.
    squeue may append details: ``ReqNodeNotAvail, UnavailableNodes:n1``."""
    key = re.split(r"[,\s(]", reason.strip(), maxsplit=1)[0]
    return NEVER_RUNS.get(key)


def _resources(s: SlurmOptions, device: str) -> str:
    """What each job asks for, as the options that set it."""
    gpus = s.gpus_per_job if device != "cpu" else 0
    parts = [f"--slurm-gpus-per-job {gpus}", f"--slurm-cpus-per-job {s.cpus_per_job}",
             f"--slurm-time {s.time_min} (minutes)"]  # fmt: skip
    if s.mem:
        parts.append(f"--slurm-mem {s.mem}")
    if s.partition:
        parts.append(f"--slurm-partition {s.partition}")
    return ", ".join(parts)


def _fix_hint(text: str, s: SlurmOptions, device: str) -> str:
    """The option that most likely fixes what sbatch or squeue said (``text``)."""
    low = text.lower()
    gpus = s.gpus_per_job if device != "cpu" else 0
    if gpus and any(w in low for w in ("gres", "gpu", "tres")):
        return "on a cluster without GPUs pass --device cpu (or --slurm-gpus-per-job 0)"
    if "partition" in low and ("invalid" in low or "not" in low and "available" not in low):
        return "name an existing partition with --slurm-partition (see `sinfo`)"
    if "memory" in low or "mem" in low.split():
        return "lower --slurm-mem (see `sinfo -o '%P %m'`)"
    if "time limit" in low or "timelimit" in low:
        return "lower --slurm-time (see `sinfo -o '%P %l'`)"
    if "account" in low or "qos" in low:
        return "give a valid --slurm-arg account=... / --slurm-arg qos=..."
    if gpus:
        return (
            "ask for what a node has: --device cpu (or --slurm-gpus-per-job 0) where nodes have no GPU, "
            "and --slurm-cpus-per-job at most the node's CPUs (see `sinfo -o '%P %c %G %m'`)"
        )
    return "ask for what a node has: --slurm-cpus-per-job at most the node's CPUs (see `sinfo -o '%P %c %m'`)"


def _sbatch_refusal(e: BaseException) -> str:
    """The first line sbatch wrote about a refused submission (submitit's FailedJobError holds its stderr)."""
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    said = next((ln for ln in lines if "error" in ln.lower()), lines[0] if lines else type(e).__name__)
    return said.removeprefix("sbatch: error: ").removeprefix("sbatch: ")


def _cancel_slurm(job_ids: Sequence[str]) -> None:
    """``scancel`` the jobs (best effort: a job already gone, or no scancel, is fine)."""
    if not job_ids:
        return
    try:
        subprocess.run(["scancel", *job_ids], capture_output=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        pass


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def live_job(job: dict[str, Any], slurm: dict[str, str] | None = None) -> str | None:
    """The state of a submitted job that will still run it (``PENDING``, ``RUNNING``...), else None.
    ``slurm``: squeue states already fetched (else squeue is asked)."""
    if job.get("state") != "submitted" or not job.get("job_id"):
        return None
    jid = str(job["job_id"])
    if job.get("executor") == "slurm":
        states = slurm if slurm is not None else slurm_states([jid])
        if states is None:
            return "UNKNOWN"  # Slurm cannot be asked: assume the job lives rather than run the run twice
        state = states.get(jid)
        return state if state in SLURM_ALIVE else None
    if job.get("host") == socket.gethostname() and jid.isdigit() and _pid_alive(int(jid)):
        return "RUNNING"
    return None


# -- running a sweep's tasks ----------------------------------------------------------------------------------


def _first_error_line(text: str) -> str:
    """The exception line of a traceback (submitit reports a job's failure as its whole traceback)."""
    lines = [ln.strip() for ln in str(text).splitlines() if ln.strip()]
    user_error = f"{UserError.__module__}.{UserError.__qualname__}: "  # as a traceback names it
    for ln in reversed(lines):
        if ln.startswith(user_error):
            return ln.removeprefix(user_error)
        if ":" in ln and not ln.startswith(("File ", "raise ", "^")) and "Error" in ln.split(":")[0]:
            return ln
    return lines[-1] if lines else "failed"


def claimed_elsewhere(folder: RunFolder) -> str | None:
    """Why another process will finish ``folder``'s run (it holds the lock, or a live job of another sweep
    is queued for it), or None."""
    if is_locked(folder.root):
        holder = read_holder(folder.root)
        return f"in use by {holder.describe() if holder else 'another process'}"
    jobs = read_jobs(folder)
    if jobs:
        state = live_job(jobs[-1])
        if state:
            return f"{jobs[-1].get('executor')} job {jobs[-1]['job_id']} is {state.lower()}"
    return None


def local_gpus() -> int:
    """How many CUDA devices this process sees (0 without torch CUDA)."""
    import torch

    return torch.cuda.device_count() if torch.cuda.is_available() else 0


def run_tasks(
    tasks: Sequence[Task],
    cfg: ExecutorConfig,
    jobs_dir: Path,
    log: Callable[[str], None] = print,
) -> list[SweepOutcome]:
    """Run ``tasks`` as jobs of ``cfg.kind`` (local or slurm), at most ``cfg.max_parallel`` at once, and
    wait for them all. Finished runs are skipped, runs claimed by another sweep are left to it
    (status ``elsewhere``), a failed job is reported with its log and the others go on. Returns one outcome
    per task, in task order."""
    logging_quiet()
    total = len(tasks)
    outcomes: list[SweepOutcome | None] = [None] * total
    todo: list[int] = []
    for i, t in enumerate(tasks):
        if t.folder is None:
            outcomes[i] = SweepOutcome(t.scene, t.label, "failed", error=t.error)
            log(f"[{i + 1}/{total}] {t.scene}: {t.label}: failed: {t.error}")
            continue
        if t.folder.is_done():
            outcomes[i] = _with_last_job(
                SweepOutcome(t.scene, t.label, "skipped", str(t.folder.root), mean=_done_mean(t.folder)),
                t.folder,
            )
            log(f"[{i + 1}/{total}] {t.scene}: {t.label}: already finished")
            continue
        why = claimed_elsewhere(t.folder)
        if why:
            outcomes[i] = SweepOutcome(t.scene, t.label, "elsewhere", str(t.folder.root), error=why)
            log(f"[{i + 1}/{total}] {t.scene}: {t.label}: left to another sweep ({why})")
            continue
        todo.append(i)

    gpus: list[int] = []
    if cfg.kind == "local":
        executor = submitit.LocalExecutor(folder=str(jobs_dir / "%j"))
        if tasks and tasks[0].request.device != "cpu":
            gpus = list(range(local_gpus()))
        limit = cfg.max_parallel or max(1, len(gpus))
        if gpus:
            limit = min(limit, len(gpus))  # one run per GPU
        threads = None if gpus else max(1, (os.cpu_count() or 1) // limit)
        executor.update_parameters(timeout_min=cfg.slurm.time_min)
    else:
        check_jobs_folder(jobs_dir)
        executor = submitit.SlurmExecutor(folder=str(jobs_dir / "%j"))
        s = cfg.slurm
        executor.update_parameters(**slurm_parameters(s, tasks[0].request.device if tasks else "cpu"))
        limit = cfg.max_parallel or max(1, len(todo))
        threads = s.cpus_per_job

    free_gpus = list(gpus)
    running: dict[int, tuple[Any, int | None, float]] = {}  # task index -> (job, gpu, submitted time)
    gone_since: dict[int, float] = {}
    stuck_since: dict[str, float] = {}  # Slurm job id -> first seen pending for a NEVER_RUNS reason
    pending = list(todo)
    last_squeue = 0.0
    squeue: dict[str, str] | None = None
    try:
        while pending or running:
            while pending and len(running) < limit:
                i = pending.pop(0)
                t = tasks[i]
                gpu = free_gpus.pop(0) if gpus else None
                if cfg.kind == "local":
                    executor.update_parameters(
                        gpus_per_node=1 if gpu is not None else 0,
                        visible_gpus=(gpu,) if gpu is not None else (),
                    )
                else:
                    executor.update_parameters(job_name=slurm_job_name(t.scene, t.folder.root.name))
                submitted = time.time()
                try:
                    # submitit prints a refusing sbatch's stderr itself; the error below says it once.
                    with contextlib.redirect_stderr(io.StringIO()):
                        job = executor.submit(RunJob(t.request, threads))
                except (submitit.core.utils.FailedJobError, subprocess.CalledProcessError, OSError) as e:
                    if cfg.kind != "slurm":
                        raise
                    said = _sbatch_refusal(e)
                    device = t.request.device
                    others = [str(j.job_id) for j, _, _ in running.values()]
                    tail = f"; jobs {', '.join(others)} already queued go on" if others else ""
                    raise UserError(
                        f"sbatch refused the job of {t.scene}: {t.label}: {said} (asked for "
                        f"{_resources(cfg.slurm, device)}); {_fix_hint(said, cfg.slurm, device)}{tail}"
                    ) from None
                running[i] = (job, gpu, submitted)
                entry = {
                    "executor": cfg.kind,
                    "job_id": str(job.job_id),
                    "host": socket.gethostname() if cfg.kind == "local" else None,
                    "submitted": submitted,
                    "state": "submitted",
                    "log": str(job.paths.stderr),
                }
                earlier = read_jobs(t.folder)
                if earlier and earlier[-1].get("state") == "submitted":
                    earlier[-1]["state"] = (
                        "lost"  # its sweep stopped watching it, and it is gone (checked above)
                    )
                _write_jobs(t.folder, [*earlier, entry])
                where = f" on GPU {gpu}" if gpu is not None else ""
                log(f"[{i + 1}/{total}] {t.scene}: {t.label}: {cfg.kind} job {job.job_id}{where}")

            if cfg.kind == "slurm" and running and time.time() - last_squeue > 5 * cfg.poll_s:
                queue = slurm_jobs([str(j.job_id) for j, _, _ in running.values()])
                squeue = None if queue is None else {jid: st for jid, (st, _) in queue.items()}
                last_squeue = time.time()
                _stop_if_never_runs(queue or {}, running, tasks, cfg, stuck_since)
            for i in list(running):
                job, gpu, submitted = running[i]
                finished = _job_finished(job, cfg.kind, squeue, gone_since, i)
                if not finished:
                    continue
                del running[i]
                gone_since.pop(i, None)
                if gpu is not None:
                    free_gpus.append(gpu)
                outcomes[i] = _collect(tasks[i], job, cfg.kind, submitted, log, f"[{i + 1}/{total}]")
            if pending or running:
                time.sleep(cfg.poll_s)
    except KeyboardInterrupt:
        if cfg.kind == "local":
            for job, _, _ in running.values():
                job.cancel(check=False)
            log(f"interrupted: stopped {len(running)} local job(s); run the sweep again to resume them")
        else:
            ids = ", ".join(str(j.job_id) for j, _, _ in running.values())
            log(f"interrupted: Slurm jobs {ids} go on; `wtbench sweep --status RUNS_DIR` follows them")
        raise
    return [o for o in outcomes if o is not None]


def _stop_if_never_runs(
    queue: dict[str, tuple[str, str]],
    running: dict[int, tuple[Any, int | None, float]],
    tasks: Sequence[Task],
    cfg: ExecutorConfig,
    stuck_since: dict[str, float],
) -> None:
    """Raise a one-line :class:`UserError` once a job has been pending for a :data:`NEVER_RUNS` reason for
    :data:`NEVER_RUNS_GRACE_S`: the sweep's pending jobs (all ask for the same resources) are cancelled and
    recorded failed, with the reason and the option that fixes it; running jobs go on."""
    now = time.time()
    stuck = None
    for i, (job, _, _) in running.items():
        jid = str(job.job_id)
        state, reason = queue.get(jid, ("", ""))
        why = never_runs(reason) if state == "PENDING" else None
        if why is None:
            stuck_since.pop(jid, None)
            continue
        first = stuck_since.setdefault(jid, now)
        if stuck is None and now - first >= NEVER_RUNS_GRACE_S:
            stuck = (i, jid, reason, why)
    if stuck is None:
        return
    i, jid, reason, why = stuck
    pending = {
        k: str(j.job_id)
        for k, (j, _, _) in running.items()
        if queue.get(str(j.job_id), ("",))[0] == "PENDING"
    }
    _cancel_slurm(list(pending.values()))
    for k in pending:
        msg = f"cancelled: Slurm would never start it (pending for {reason})"
        _update_last_job(tasks[k].folder, state="failed", error=msg, ended=now)
        running.pop(k, None)
    t = tasks[i]
    device = t.request.device
    left = [str(j.job_id) for j, _, _ in running.values()]
    tail = f"; running jobs {', '.join(left)} go on" if left else ""
    raise UserError(
        f"Slurm will never start job {jid} ({t.scene}: {t.label}): pending for {reason}: {why} (asked for "
        f"{_resources(cfg.slurm, device)}); cancelled {len(pending)} pending job(s); "
        f"{_fix_hint(reason + ' ' + why, cfg.slurm, device)}{tail}"
    )


def logging_quiet() -> None:
    """submitit warns on every status poll where Slurm has no accounting (sacct); this sweep polls squeue."""
    import logging

    logging.getLogger("submitit").setLevel(logging.ERROR)


def _job_finished(
    job, kind: str, squeue: dict[str, str] | None, gone_since: dict[int, float], i: int
) -> bool:
    """Whether a job has ended: a local process has exited; a Slurm job has written its result, or has been
    out of the queue (or in an end state) for ``RESULT_GRACE_S`` without writing one."""
    if kind == "local":
        return job.done()
    if job.paths.result_pickle.exists():
        return True
    if squeue is None:
        return False  # not asked yet, or squeue failed: look again later
    if squeue.get(str(job.job_id)) in SLURM_ALIVE:
        gone_since.pop(i, None)
        return False
    first = gone_since.setdefault(i, time.time())
    return time.time() - first > RESULT_GRACE_S


def _collect(t: Task, job, kind: str, submitted: float, log, prefix: str) -> SweepOutcome:
    """The outcome of a finished job, recorded in the run folder's job.json."""
    log_path = str(job.paths.stderr)
    try:
        if kind == "slurm" and not job.paths.result_pickle.exists():
            raise RuntimeError(
                f"job {job.job_id} ended without a result (cancelled, preempted without requeue, or killed)"
            )
        res = job.result()
    except Exception as e:  # a failed job must not stop the sweep
        msg = _first_error_line(str(e))
        _update_last_job(t.folder, state="failed", error=msg, ended=time.time())
        log(f"{prefix} {t.scene}: {t.label}: failed: {msg} (log: {log_path})")
        return SweepOutcome(
            t.scene, t.label, "failed", str(t.folder.root), error=msg, executor=kind,
            job_id=str(job.job_id), log=log_path,
        )  # fmt: skip
    wait = max(0.0, res["started"] - submitted)
    wall = res["ended"] - res["started"]
    state = "skipped" if res["skipped"] else "done"
    _update_last_job(
        t.folder, state=state, host=res["host"], device=res["device"], started=res["started"],
        ended=res["ended"], queue_wait_s=wait, wall_s=wall,
    )  # fmt: skip
    log(f"{prefix} {t.scene}: {t.label}: {state} ({kind} job {job.job_id} on {res['host']}, {wall:.0f} s)")
    return SweepOutcome(
        t.scene, t.label, state, res["folder"], mean=res["mean"], executor=kind, job_id=str(job.job_id),
        host=res["host"], device=res["device"], queue_wait_s=wait, wall_s=wall, log=log_path,
    )  # fmt: skip


def _with_last_job(outcome: SweepOutcome, folder: RunFolder) -> SweepOutcome:
    """``outcome`` of a run finished earlier, with the job that finished it (from job.json), if any."""
    done = [j for j in read_jobs(folder) if j.get("state") == "done"]
    if done:
        j = done[-1]
        outcome.executor, outcome.job_id, outcome.host = j.get("executor"), j.get("job_id"), j.get("host")
        outcome.device, outcome.log = j.get("device"), j.get("log")
        outcome.queue_wait_s, outcome.wall_s = j.get("queue_wait_s"), j.get("wall_s")
    return outcome


def _done_mean(folder: RunFolder) -> dict[str, float]:
    try:
        return dict(json.loads(folder.done.read_text()).get("mean", {}))
    except (OSError, ValueError, AttributeError):
        return {}


# -- status ---------------------------------------------------------------------------------------------------


@dataclass
class RunState:
    """What one run folder says about its run."""

    run: str  # scene/method/tag
    state: str  # done, running, queued, failed or unfinished
    job_id: str | None = None
    detail: str = ""


def run_states(runs_dir: Path) -> list[RunState]:
    """The state of every run folder ``runs_dir/<scene>/<method>/<tag>`` (hidden folders skipped):
    ``done`` (DONE written), ``running`` (its lock is held, or its Slurm job runs), ``queued`` (its job
    waits), ``failed`` (its last job failed or vanished), ``unfinished`` (stopped outside a job; the next
    sweep resumes it)."""
    if not runs_dir.is_dir():
        raise UserError(f"--status {runs_dir}: no such folder; give the sweep's RUNS_DIR (-o)")
    from benchmarks.runner.layout import find_run_folders

    folders = [RunFolder(p) for p in find_run_folders(runs_dir)]
    last = {f.root: (read_jobs(f) or [{}])[-1] for f in folders}
    slurm_ids = [
        str(j["job_id"])
        for j in last.values()
        if j.get("executor") == "slurm" and j.get("state") == "submitted" and j.get("job_id")
    ]
    squeue = slurm_states(slurm_ids)
    out = []
    for f in folders:
        rel = str(f.root.relative_to(runs_dir))
        job = last[f.root]
        jid = str(job["job_id"]) if job.get("job_id") else None
        log_note = f"log: {job['log']}" if job.get("log") else ""
        if f.is_done():
            out.append(RunState(rel, "done", jid, _done_detail(f)))
        elif is_locked(f.root):
            holder = read_holder(f.root)
            out.append(RunState(rel, "running", jid, holder.describe() if holder else ""))
        elif job.get("state") == "submitted":
            state = live_job(job, squeue)
            if state == "RUNNING":
                out.append(RunState(rel, "running", jid, log_note))
            elif state:
                out.append(RunState(rel, "queued", jid, state.lower()))
            else:
                why = "its job ended without finishing (cancelled, preempted or killed); run the sweep again"
                out.append(RunState(rel, "failed", jid, f"{why}; {log_note}".strip("; ")))
        elif job.get("state") == "failed":
            out.append(RunState(rel, "failed", jid, f"{job.get('error', '')}; {log_note}".strip("; ")))
        else:
            out.append(
                RunState(rel, "unfinished", jid, "stopped before finishing; the next sweep resumes it")
            )
    return out


def _done_detail(folder: RunFolder) -> str:
    mean = _done_mean(folder)
    return "  ".join(f"{k} {mean[k]:.3f}" for k in ("psnr", "mpsnr") if isinstance(mean.get(k), int | float))
