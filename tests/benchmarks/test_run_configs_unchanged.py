"""The configs `wtbench run` and `wtbench sweep` build, frozen: every method x preset x ablation subset (and the
tree options, --set, overrides, every grid of every method) resolves to the same config, run-folder name,
recorded options and command line as in tests/benchmarks/data/run_configs.json. A config is recorded as what
it changes from its preset's config (every setting, derived fields included), so that a new default of the
library changes no entry while a request that builds another config does.

The file was written before the method options moved from the harness into the methods' specs (issue 29), so
this test is the proof that the move changed no run. Regenerate it only for a deliberate change of configs:
``python tests/benchmarks/test_run_configs_unchanged.py --write`` (and say why in the commit).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import os
import sys
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace

EXPECTED = Path(__file__).parent / "data" / "run_configs.json"

# Options of `wtbench run` per method besides the ablation subsets (argv fragments).
WORLDTREE_ARGS: tuple[tuple[str, ...], ...] = (
    *(("--depth", d) for d in ("0", "1", "2", "3", "4", "auto")),
    *(("--depth", "4", "--chain-length", str(k)) for k in range(5)),
    *(("--split", s) for s in ("binary", "gradient", "flow")),
    ("--sequential",),
    ("--depth", "auto", "--ablate", "tpt"),
    ("--depth", "auto", "--set", "auto_split.max_depth=3"),
    ("--set", "depth=auto"),
    ("--depth", "3", "--split", "flow", "--sequential", "--chain-length", "1", "--ablate", "sac"),
)
COMMON_ARGS: tuple[tuple[str, ...], ...] = (
    (),
    ("--steps", "3", "--seed", "1", "--downscale", "2"),
    ("--set", "checkpoint_every=7", "--set", "seed=5"),
)


def _leaves(tree: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in tree.items():
        if isinstance(v, dict):
            out.update(_leaves(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _changes(cfg, preset) -> dict:
    """``{dotted key: value}`` of every setting where ``cfg`` differs from ``preset`` (both as config.json has
    them)."""
    new, old = (_leaves(json.loads(json.dumps(dataclasses.asdict(c), default=str))) for c in (cfg, preset))
    assert set(new) == set(old)
    return {k: new[k] for k in sorted(new) if new[k] != old[k]}


def _entry(req) -> dict:
    from benchmarks.runner.runs import resolve_config, run_folder_of
    from methods.registry import get_method

    spec = get_method(req.method)
    cfg, _ = resolve_config(spec, req)
    return {
        "folder": run_folder_of(req).root.as_posix(),
        "config_changes": _changes(cfg, spec.config(req.preset)),
        "options": json.loads(json.dumps(req.options)),
        "command": req.command,
    }


@contextmanager
def _captured(seen: list):
    """`execute` of the runner replaced by one that records the request (nothing runs)."""
    import benchmarks.runner.runs as runs

    def fake_execute(req):
        seen.append(req)
        return SimpleNamespace(skipped=True, folder=SimpleNamespace(root=Path(".")), mean={})

    real = runs.execute
    runs.execute = fake_execute
    try:
        yield
    finally:
        runs.execute = real


def _invoke(args: list[str]) -> list:
    from typer.testing import CliRunner

    from benchmarks.cli import app

    seen: list = []
    with _captured(seen):
        res = CliRunner().invoke(app, args, catch_exceptions=False)
    assert res.exit_code == 0, (args, res.output)
    return seen


def _ablation_subsets(cfg_cls) -> list[tuple[str, ...]]:
    names = cfg_cls.ablation_names() if hasattr(cfg_cls, "ablation_names") else ()
    return [c for r in range(len(names) + 1) for c in itertools.combinations(names, r)]


def dump(root: Path) -> dict[str, dict]:
    """``{label: entry}`` of every request, with ``root`` as the working folder (scenes/S, runs)."""
    from methods.registry import list_methods

    scene = root / "scenes" / "S"
    scene.mkdir(parents=True, exist_ok=True)
    (scene / "cameras.json").write_text("{}")
    old = Path.cwd()
    os.chdir(root)
    out: dict[str, dict] = {}
    try:
        for spec in list_methods():
            for preset in sorted(spec.presets):
                base = ["run", "--method", spec.name, "--scene", "scenes/S", "--preset", preset]
                subsets = _ablation_subsets(spec.config_cls)
                requests = [tuple(x for n in sub for x in ("--ablate", n)) for sub in subsets]
                requests += list(COMMON_ARGS[1:])
                if spec.name == "worldtree":
                    requests += list(WORLDTREE_ARGS)
                for extra in requests:
                    (req,) = _invoke(base + list(extra))
                    out[" ".join(["run", spec.name, preset, *extra])] = _entry(req)
                for grid in _grids_of(spec.name):
                    args = ["sweep", "--scenes", "scenes", "--grid", grid, "--method", spec.name]
                    for req in _invoke(args + ["--preset", preset, "--device", "cpu", "-o", "runs"]):
                        key = f"sweep {spec.name} {preset} {grid} {req.command}"
                        out[key] = _entry(req)
    finally:
        os.chdir(old)
    return out


def _grids_of(method: str) -> list[str]:
    """The grids a method sweeps: the harness's ``seeds`` and, for WorldTree, the tree's."""
    if method == "worldtree":
        return ["paper-ablation", "depth", "adaptive", "tree", "chain", "split", "seeds"]
    return ["seeds"]


def test_the_dump_covers_every_grid_of_every_method():
    from benchmarks.runner.sweep import grids_of
    from methods.registry import list_methods

    for spec in list_methods():
        if spec.name in ("static", "base", "worldtree"):
            assert sorted(grids_of(spec)) == sorted(_grids_of(spec.name)), spec.name


def test_run_and_sweep_configs_are_unchanged(tmp_path):
    expected = json.loads(EXPECTED.read_text())
    got = dump(tmp_path)
    assert sorted(got) == sorted(expected)
    changed = [k for k in expected if got[k] != expected[k]]
    assert not changed, (
        f"{len(changed)} changed, e.g. {changed[0]}: {expected[changed[0]]} -> {got[changed[0]]}"
    )


if __name__ == "__main__":
    import tempfile

    if sys.argv[1:] != ["--write"]:
        sys.exit(f"usage: python {sys.argv[0]} --write  (rewrites {EXPECTED})")
    with tempfile.TemporaryDirectory() as tmp:
        data = dump(Path(tmp))
    EXPECTED.parent.mkdir(exist_ok=True)
    EXPECTED.write_text(json.dumps(data, indent=1, sort_keys=True) + "\n")
    print(f"{len(data)} requests written to {EXPECTED}")
