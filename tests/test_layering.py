"""The import graph of the four packages, read from their source (every import statement, those inside
functions included): no package imports one above it, no sub-package of ``benchmarks`` imports one above it,
``worldtree.infra`` imports nothing else of ``worldtree``, nothing else of ``worldtree`` imports
``worldtree.diagnostics``, nothing outside ``benchmarks.speed`` imports it, and no cycle among the
sub-packages and top-level modules of any package.

Package order: ``worldtree`` (the library) < ``methods`` and ``nvidia_ls`` (each on the library alone) <
``benchmarks`` (the harness, on all three). Inside ``benchmarks``: fixtures < evaluation < runner < api (a
finished run loaded) < reporting < viewer < commands < cli < speed, where ``speed`` (measurement scripts
run from a clone, not installed) is a leaf. Inside ``worldtree``: ``infra`` (errors, atomic files, locks,
clocks: what the model uses) at the bottom, ``diagnostics`` (reads a fitted model) at the top. A known upward edge is listed in :data:`ALLOWED` with why it is there; an entry that no longer matches an
import fails, so the list only shrinks.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("worldtree", "methods", "nvidia_ls", "benchmarks")
MAY_IMPORT = {
    "worldtree": set(),
    "methods": {"worldtree"},
    "nvidia_ls": {"worldtree"},
    "benchmarks": {"worldtree", "methods", "nvidia_ls"},
}
BENCHMARKS_ORDER = (
    "fixtures",
    "evaluation",
    "runner",
    "api",
    "reporting",
    "viewer",
    "commands",
    "cli",
    "speed",
)
#: Not part of the installed distribution (pyproject.toml excludes it), so nothing outside it may import it.
LEAVES = ("benchmarks.speed",)
#: Sub-packages of ``worldtree`` that import nothing else of ``worldtree`` (the bottom layer).
WORLDTREE_BOTTOM = ("worldtree.infra",)
#: Sub-packages of ``worldtree`` that nothing else of ``worldtree`` imports (the top layer).
WORLDTREE_TOP = ("worldtree.diagnostics",)

#: (importing node, imported node) -> why the edge stays for now.
ALLOWED: dict[tuple[str, str], str] = {}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_module(name: str) -> bool:
    path = ROOT.joinpath(*name.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def import_edges() -> list[tuple[str, str, str]]:
    """``(importing module, imported module, "file:line")`` of every import of the four packages; ``from pkg
    import sub`` of a module ``sub`` counts as an import of ``pkg.sub``."""
    edges = []
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            name = _module_name(path)
            here = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.Import):
                    targets = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom):
                    if node.level:
                        base = here[: len(here) - node.level + 1]
                        module = ".".join([*base, *([node.module] if node.module else [])])
                    else:
                        module = node.module
                    subs = [f"{module}.{a.name}" for a in node.names]
                    targets = [sub if _is_module(sub) else module for sub in subs]
                else:
                    continue
                where = f"{path.relative_to(ROOT)}:{node.lineno}"
                edges += [(name, t, where) for t in targets if t.split(".")[0] in PACKAGES]
    return edges


def node_of(module: str) -> str:
    """The sub-package or top-level module a module belongs to (``benchmarks.runner``, ``worldtree.dynamic``)."""
    return ".".join(module.split(".")[:2])


def test_no_package_imports_one_above_it():
    bad = [f"{w}: {a} imports {b}" for a, b, w in import_edges()
           if a.split(".")[0] != b.split(".")[0] and b.split(".")[0] not in MAY_IMPORT[a.split(".")[0]]]  # fmt: skip
    assert not bad, "\n".join(bad)


def _edges_between_nodes() -> dict[tuple[str, str], list[str]]:
    out = defaultdict(list)
    for a, b, where in import_edges():
        na, nb = node_of(a), node_of(b)
        if na != nb and a.split(".")[0] == b.split(".")[0] and "." in nb:
            out[(na, nb)].append(where)
    return out


def test_no_benchmarks_subpackage_imports_one_above_it():
    rank = {f"benchmarks.{n}": i for i, n in enumerate(BENCHMARKS_ORDER)}
    bad = []
    for (a, b), where in _edges_between_nodes().items():
        if not a.startswith("benchmarks."):
            continue
        missing = [n for n in (a, b) if n not in rank]
        assert not missing, f"place {missing} in BENCHMARKS_ORDER of {__file__}"
        if rank[a] < rank[b] and (a, b) not in ALLOWED:
            bad.append(f"{a} imports {b} ({', '.join(where)})")
    assert not bad, "\n".join(bad)


def test_nothing_imports_a_leaf():
    bad = [f"{w}: {a} imports {b}" for a, b, w in import_edges() for leaf in LEAVES
           if (b == leaf or b.startswith(leaf + ".")) and not (a == leaf or a.startswith(leaf + "."))]  # fmt: skip
    assert not bad, "\n".join(bad)


def test_worldtree_layers_inside():
    bad = []
    for a, b, where in import_edges():
        na, nb = node_of(a), node_of(b)
        if na == nb or a.split(".")[0] != "worldtree" or b.split(".")[0] != "worldtree":
            continue
        if na in WORLDTREE_BOTTOM:
            bad.append(f"{where}: {a} imports {b} ({na} may import nothing else of worldtree)")
        if nb in WORLDTREE_TOP:
            bad.append(f"{where}: {a} imports {b} (nothing else of worldtree may import {nb})")
    assert not bad, "\n".join(bad)


def test_worldtree_layers_exist():
    """The layers named above are sub-packages (a renamed one would make the check above vacuous)."""
    layers = (*WORLDTREE_BOTTOM, *WORLDTREE_TOP, *LEAVES)
    missing = [n for n in layers if not (ROOT.joinpath(*n.split(".")) / "__init__.py").is_file()]
    assert not missing, f"not sub-packages: {missing}"


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one node (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while not comp or comp[-1] != v:
                comp.append(stack.pop())
                on.discard(comp[-1])
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in list(graph):
        if v not in index:
            visit(v)
    return out


def test_no_cycle_among_subpackages_and_modules():
    graph: dict[str, set[str]] = defaultdict(set)
    for a, b in _edges_between_nodes():
        if (a, b) not in ALLOWED:
            graph[a].add(b)
    cycles = _cycles(graph)
    assert not cycles, "import cycles: " + "; ".join(" <-> ".join(c) for c in cycles)


def test_every_allowed_edge_still_exists():
    edges = _edges_between_nodes()
    gone = [k for k in ALLOWED if k not in edges]
    assert not gone, f"remove from ALLOWED (fixed): {gone}"
