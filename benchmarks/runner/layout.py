"""Where run folders are: ``RUNS_DIR/<scene>/<method>/<tag>`` (:mod:`benchmarks.runner.runs` writes them; the
sweep's status and the tables read them). Standard library only, so that readers import nothing heavy."""

from __future__ import annotations

from pathlib import Path


def find_run_folders(runs_dir: Path) -> list[Path]:
    """Folders ``runs_dir/<scene>/<method>/<tag>`` holding a ``config.json``, ``DONE`` or ``job.json`` (a run
    a sweep has submitted, perhaps still queued), sorted; hidden names (temporary folders of atomic writes,
    locks) are left out."""
    return sorted(
        p
        for p in runs_dir.glob("*/*/*")
        if p.is_dir()
        and not any(part.startswith(".") for part in p.relative_to(runs_dir).parts)
        and any((p / name).is_file() for name in ("config.json", "DONE", "job.json"))
    )
