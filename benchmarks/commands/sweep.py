"""`wtbench sweep`: run a named grid of configurations over scenes (the grids are the methods' own,
``MethodSpec.grids``, plus the harness's ``seeds``)."""

from __future__ import annotations

from pathlib import Path

import typer

from benchmarks.commands import run_options as opt
from benchmarks.commands.run_options import RunOptions


def register(app: typer.Typer) -> None:
    @app.command(
        "sweep",
        help=(
            "Run a grid of configurations over scenes; skips finished runs, goes on past a failed one and "
            "reports it. Each method declares its grids (`wtbench sweep --list`); seeds works with every method."
        ),
    )
    def _cmd(
        scenes: list[Path] | None = typer.Option(
            None, "--scenes", help="Scene folders, or folders of scene folders (repeatable)."
        ),
        grid: str | None = typer.Option(
            None, "--grid", help="A grid of the method (--list; default: its first) or seeds."
        ),
        method: str | None = typer.Option(
            None, "--method", "-m", help="Method to sweep (default: the one that declares the --grid)."
        ),
        runs_dir: Path = opt.OUT,
        preset: str = opt.PRESET,
        device: str = opt.DEVICE,
        steps: int | None = opt.STEPS,
        seed: int | None = opt.SEED,
        lpips_weights: Path | None = opt.LPIPS_WEIGHTS,
        set_: list[str] | None = opt.SET,
        masks: Path | None = opt.MASKS,
        tracks: Path | None = opt.TRACKS,
        depth_maps: Path | None = opt.DEPTH_MAPS,
        flow: Path | None = opt.FLOW,
        dry_run: bool = typer.Option(False, "--dry-run", help="List the runs and exit."),
        executor: str = typer.Option(
            "local",
            "--executor",
            help="local (this machine: one run per GPU, or CPU workers), slurm (one Slurm job per run, "
            "through submitit) or auto (slurm when sbatch is on PATH).",
        ),
        max_parallel: int | None = typer.Option(
            None,
            "--max-parallel",
            min=1,
            help="Most runs at once (local default: one per GPU, 1 on CPU, which runs in this process; "
            "slurm default: all, the queue decides).",
        ),
        slurm_partition: str | None = typer.Option(None, "--slurm-partition", help="Slurm partition."),
        slurm_time: str = typer.Option(
            "24:00:00",
            "--slurm-time",
            help="Time limit per job (minutes or [D-]HH:MM:SS); a job reaching it is requeued and resumes.",
        ),
        slurm_gpus_per_job: int = typer.Option(
            1, "--slurm-gpus-per-job", min=0, help="GPUs per job (none when --device cpu)."
        ),
        slurm_cpus_per_job: int = typer.Option(4, "--slurm-cpus-per-job", min=1, help="CPUs per job."),
        slurm_mem: str | None = typer.Option(None, "--slurm-mem", help="Memory per job, e.g. 32G."),
        slurm_arg: list[str] | None = typer.Option(
            None,
            "--slurm-arg",
            metavar="KEY=VALUE",
            help="More sbatch options, e.g. account=myproject or qos=high; repeatable.",
        ),
        status: Path | None = typer.Option(
            None,
            "--status",
            metavar="RUNS_DIR",
            help="Show each run's state under RUNS_DIR (done, running, queued, failed) and exit.",
        ),
        list_: bool = typer.Option(False, "--list", help="List every method's grids, then exit."),
        share_root: bool = typer.Option(
            False,
            "--share-root",
            help="Train each root once per scene: a run whose first stages another run of the grid trains "
            "alike (WorldTree: the same settings but the tree's) takes them from it (`wtbench run --root-from`).",
        ),
    ) -> None:
        from benchmarks.runner.sweep import resolve_grid
        from benchmarks.runner.sweep_executors import (
            ExecutorConfig,
            SlurmOptions,
            parse_slurm_args,
            parse_slurm_time,
        )
        from worldtree.infra.errors import UserError

        if status is not None:
            show_status(status)
            return
        if list_:
            list_grids()
            return
        if not scenes:
            raise UserError("`wtbench sweep` needs --scenes FOLDER (or --status RUNS_DIR)")
        method, grid = resolve_grid(method, grid)
        run = RunOptions.from_cli(
            method, masks, tracks, depth_maps, flow, steps, seed, sets=set_, runs_dir=runs_dir, preset=preset,
            device=device, lpips_weights=lpips_weights,
        )  # fmt: skip
        slurm = SlurmOptions(
            partition=slurm_partition,
            time_min=parse_slurm_time(slurm_time),
            gpus_per_job=slurm_gpus_per_job,
            cpus_per_job=slurm_cpus_per_job,
            mem=slurm_mem,
            extra=parse_slurm_args(slurm_arg or []),
        )
        sweep(scenes, grid, run, dry_run, ExecutorConfig(kind=executor, max_parallel=max_parallel, slurm=slurm),
              share_root=share_root)  # fmt: skip


def list_grids() -> None:
    """Print every grid: each method's own, then the harness's."""
    from benchmarks.runner.sweep import HARNESS_GRIDS
    from methods.registry import list_methods

    rows = [(s.name, name, g.description) for s in list_methods() for name, g in s.grids.items()]
    rows += [("(any)", name, g.description) for name, g in HARNESS_GRIDS.items()]
    for method, name, description in rows:
        print(f"{method:12s} {name:16s} {description}")


def show_status(runs_dir: Path) -> None:
    """Print one line per run folder under ``runs_dir`` (state, run, job id, detail) and the counts."""
    from benchmarks.runner.sweep_executors import run_states
    from worldtree.infra.errors import UserError

    states = run_states(runs_dir)
    if not states:
        raise UserError(f"--status {runs_dir}: holds no run folder (RUNS_DIR/<scene>/<method>/<tag>)")
    width = max(len(r.run) for r in states)
    for r in states:
        job = f"job {r.job_id}" if r.job_id else "-"
        print(f"{r.state:10s} {r.run:{width}s}  {job:12s} {r.detail}".rstrip())
    order = ("done", "running", "queued", "failed", "unfinished")
    counts = [f"{sum(r.state == k for r in states)} {k}" for k in order]
    print(f"{len(states)} runs: " + ", ".join(counts))


def sweep(scenes, grid: str, run: RunOptions, dry_run: bool = False, executor=None, share_root: bool = False) -> None:
    """Resolve scenes and grid, run them, print a summary and write RUNS_DIR/sweep-<grid>.json. ``run`` (the
    options `wtbench run` would get; its ``sets`` and ``priors`` go to every run) is checked against the
    method's config once, before the first run. ``executor``
    (:class:`benchmarks.runner.sweep_executors.ExecutorConfig`; None: in this process) says where runs execute: one
    local run at a time without GPUs runs in this process, anything else as submitit jobs. ``share_root``:
    each run whose root an earlier run of the same scene trains alike takes it from there
    (:func:`benchmarks.runner.shared_root.plan_lenders`); as jobs, the lending runs go first, then the rest."""
    import dataclasses
    import warnings

    from benchmarks.commands.run_options import one_line_warning
    from benchmarks.runner.runs import execute, resolve_config, run_folder_of
    from benchmarks.runner.shared_root import sweep_lender
    from benchmarks.runner.sweep import find_scenes, grid_points, run_sweep, write_report
    from benchmarks.runner.sweep_executors import JOBS_DIR, Task, resolve_kind, run_tasks
    from methods.config_overrides import split_assignment
    from methods.registry import get_method
    from worldtree.infra.errors import UserError
    from worldtree.infra.folder_lock import FolderLock
    from worldtree.infra.output_paths import check_output_folder

    method, runs_dir, device = run.method, run.runs_dir, run.device
    sets, priors, overrides = run.sets, run.priors, run.overrides
    found = find_scenes(scenes)
    points = grid_points(grid, get_method(method))
    for k in sorted({k for p in points for k in p.overrides} & set(overrides)):
        raise UserError(f"--{k}: the {grid} grid sets {k} itself; drop --{k}")
    grid_keys = {k for p in points for k in p.options} | {k for p in points for k in p.overrides}
    for item in sets:
        key = split_assignment(item)[0]
        if key in grid_keys:
            raise UserError(f"--set {item}: the {grid} grid sets {key} itself; drop the --set")
    if sets or priors:
        # A bad key or path would fail every run of the grid alike: refuse it once, up front.
        resolve_config(get_method(method), run.request(Path(".")))
    lenders = _root_lenders(found, points, run) if share_root else {}
    shared = get_method(method).shared_root
    if dry_run:
        for s in found:
            for p in points:
                extra = f"  set {sets}" if sets else ""
                extra += f"  priors {priors}" if priors else ""
                lender = lenders.get((s.name, p.label))
                extra += f"  root from {lender}" if lender is not None else ""
                print(f"{s.name}: {p.label}  {p.options or p.overrides}{extra}")
        return

    def make_request(scene: Path, pt):
        lender = lenders.get((scene.name, pt.label))
        if lender is not None:
            req = run.request(scene, pt.options, pt.overrides)
            lender = sweep_lender(lender, run_folder_of(req).root, shared)
        return run.request(scene, pt.options, pt.overrides, root_from=lender)

    check_output_folder(runs_dir, "-o")
    report = runs_dir / f"sweep-{grid}.json"
    kind = resolve_kind(executor.kind) if executor is not None else "local"
    in_process = kind == "local" and (executor is None or _local_in_process(executor, device))
    report_cfg = _report_config(method, run.preset, device, overrides, sets, priors, found)
    report_cfg["share_root"] = share_root
    report_cfg["executor"] = kind if not in_process else "in-process"
    report_cfg["executor_config"] = dataclasses.asdict(executor) if not in_process else None
    # One sweep per report: a second `wtbench sweep` of the same grid into the same RUNS_DIR stops at once
    # (each run folder is locked by `wtbench run`'s execute as well).
    with FolderLock(report, "sweep report"), warnings.catch_warnings():
        warnings.showwarning = one_line_warning
        if in_process:
            outcomes = run_sweep(found, points, make_request, execute)
        else:
            # Lending runs first (every run when nothing is shared), then the runs that borrow their roots.
            outcomes = []
            for borrowing in (False, True):
                tasks = []
                for s in found:
                    for p in points:
                        if ((s.name, p.label) in lenders) != borrowing:
                            continue
                        req = make_request(s, p)
                        req.progress = False  # job logs are files: no progress bar redrawn in them
                        try:
                            tasks.append(Task(s.name, p.label, req, run_folder_of(req)))
                        except UserError as e:  # this run's config is refused; the others still run
                            tasks.append(Task(s.name, p.label, req, None, error=str(e)))
                if tasks:
                    outcomes += run_tasks(tasks, dataclasses.replace(executor, kind=kind), runs_dir / JOBS_DIR)
        write_report(report, grid, outcomes, report_cfg)
    counts = {s: sum(o.status == s for o in outcomes) for s in ("done", "skipped", "failed", "elsewhere")}
    print(
        f"sweep {grid}: {counts['done']} done, {counts['skipped']} already finished, {counts['failed']} failed"
        + (f", {counts['elsewhere']} left to another sweep" if counts["elsewhere"] else "")
    )
    for o in outcomes:
        if o.status == "failed":
            print(f"  failed: {o.scene} {o.label}: {o.error}" + (f" (log: {o.log})" if o.log else ""))
    print(f"report: {report}; tables: wtbench table {runs_dir} -o table.csv")
    if counts["failed"]:
        raise typer.Exit(1)


def _root_lenders(found, points, run: RunOptions) -> dict[tuple[str, str], Path]:
    """``(scene name, point label) -> run folder`` lending that run of the sweep its first stages
    (``--share-root``); runs absent train their own. A run whose config is refused lends and borrows nothing
    (it fails on its own)."""
    from benchmarks.runner.runs import config_record_of, run_folder_of
    from methods.registry import get_method
    from methods.shared_root import plan_lenders
    from worldtree.infra.errors import UserError

    shared = get_method(run.method).shared_root
    if shared is None:
        raise UserError(f"--share-root: method {run.method!r} trains every stage itself; drop --share-root")
    out: dict[tuple[str, str], Path] = {}
    for s in found:
        records, folders = [], []
        for p in points:
            req = run.request(s, p.options, p.overrides)
            try:
                records.append(config_record_of(req))
                folders.append(run_folder_of(req).root)
            except UserError:
                records.append({"method": None})  # lends to no one, takes from no one
                folders.append(None)
        for k, j in enumerate(plan_lenders(shared, records)):
            if j is not None and folders[k] is not None:
                out[(s.name, points[k].label)] = folders[j]
    return out


def _report_config(method, preset, device, overrides, sets, priors, scenes) -> dict:
    """The sweep's settings as recorded in its report."""
    return {
        "method": method,
        "preset": preset,
        "device": device,
        "overrides": overrides,
        "sets": sets,
        "imported_priors": priors,
        "scenes": scenes,
    }


def _local_in_process(executor, device: str) -> bool:
    """Whether a local sweep runs in this process: one run at a time and no GPU to fan out over."""
    if executor.max_parallel not in (None, 1):
        return False
    if device == "cpu":
        return True
    from benchmarks.runner.sweep_executors import local_gpus

    return local_gpus() <= 1
