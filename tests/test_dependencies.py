"""pyproject.toml declares what the installed packages import, and the README and CI install with constraints.txt.

Rule: a third-party import anywhere in the installed packages (module level or inside a function) needs a
runtime dependency; an import inside ``try: ... except ImportError`` (or a broader except) may instead come from
an extra, since the code handles its absence. Import names differ from distribution names for a few packages
(``cv2``, ``skimage``); where the package is installed, ``importlib.metadata`` confirms the mapping.
"""

from __future__ import annotations

import ast
import importlib.metadata
import re
import sys
from pathlib import Path

import pytest

try:
    import tomllib
except ImportError:  # Python 3.10
    tomllib = pytest.importorskip("tomli")

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())

# Import name -> distribution name, where they differ.
DIST_OF_IMPORT = {"cv2": "opencv-contrib-python-headless", "skimage": "scikit-image"}
# Unguarded imports of an extra's package, each reached only behind a check: (file, import) -> extra, reason.
REACHED_BEHIND_A_CHECK = {
    ("worldtree/render/gsplat_backend.py", "gsplat"): (
        "cuda",
        "rasterize_gsplat runs only after worldtree.render.backends.gsplat_available()",
    ),
}
# Runtime dependencies that no module imports, with the reason they are needed.
NOT_IMPORTED = {"ninja": "torch.utils.cpp_extension builds the CPU rasterizer kernel with it"}
CATCHES_IMPORT_ERROR = {"ImportError", "ModuleNotFoundError", "Exception", "BaseException"}


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _req_name(req: str) -> str:
    m = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", req)
    assert m, f"cannot read a distribution name from {req!r}"
    return _norm(m.group(1))


def _local_packages() -> tuple[str, ...]:
    patterns = PYPROJECT["tool"]["setuptools"]["packages"]["find"]["include"]
    return tuple(p.rstrip("*") for p in patterns)


def _catches_import_error(handler: ast.ExceptHandler) -> bool:
    if handler.type is None:
        return True
    types = handler.type.elts if isinstance(handler.type, ast.Tuple) else [handler.type]
    return any(isinstance(t, ast.Name) and t.id in CATCHES_IMPORT_ERROR for t in types)


def third_party_imports(source: str, local: tuple[str, ...]) -> list[tuple[str, bool, int]]:
    """``(top-level name, guarded by an except that catches ImportError, line)`` of each third-party import."""
    tree = ast.parse(source)
    guarded_nodes: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Try) and any(_catches_import_error(h) for h in node.handlers):
            for stmt in node.body:
                guarded_nodes.update(id(n) for n in ast.walk(stmt))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module]
        else:
            continue
        for name in names:
            top = name.split(".")[0]
            if top in sys.stdlib_module_names or top == "__future__" or top in local:
                continue
            out.append((top, id(node) in guarded_nodes, node.lineno))
    return out


def undeclared(files: dict[str, str], deps: set[str], extras: dict[str, set[str]], local: tuple[str, ...]):
    """Problems (one line each) of the imports in ``files`` (relative path -> source) against the declarations."""
    in_extras = set().union(*extras.values()) if extras else set()
    problems = []
    for rel, source in sorted(files.items()):
        for top, guarded, line in third_party_imports(source, local):
            dist = _norm(DIST_OF_IMPORT.get(top, top))
            if dist in deps:
                continue
            behind = REACHED_BEHIND_A_CHECK.get((rel, top))
            if behind is not None and dist in extras.get(behind[0], set()):
                continue
            if guarded and dist in in_extras:
                continue
            where = "an extra or a dependency" if guarded else "a dependency (or guard the import)"
            problems.append(f"{rel}:{line}: imports {top} ({dist}), which is not declared as {where}")
    return problems


def _declarations() -> tuple[set[str], dict[str, set[str]]]:
    project = PYPROJECT["project"]
    deps = {_req_name(r) for r in project["dependencies"]}
    extras = {k: {_req_name(r) for r in v} for k, v in project["optional-dependencies"].items()}
    return deps, extras


def _package_sources() -> dict[str, str]:
    files = {}
    for pkg in _local_packages():
        for path in sorted((ROOT / pkg).rglob("*.py")):
            files[path.relative_to(ROOT).as_posix()] = path.read_text(encoding="utf-8")
    assert len(files) > 50, f"found only {len(files)} modules under {_local_packages()}"
    return files


def test_every_third_party_import_of_the_installed_packages_is_declared():
    deps, extras = _declarations()
    assert undeclared(_package_sources(), deps, extras, _local_packages()) == []


def test_the_checker_flags_undeclared_and_unguarded_imports():
    deps, extras = {"numpy"}, {"speed": {"scikit-image"}}
    src = (
        "import numpy as np\n"
        "import scipy.spatial\n"  # undeclared
        "def f():\n"
        "    from skimage.metrics import structural_similarity\n"  # extra only, not guarded
        "try:\n"
        "    import skimage\n"  # extra, guarded: fine
        "except ImportError:\n"
        "    skimage = None\n"
        "import json, worldtree.infra.atomic\n"  # stdlib and local: ignored
    )
    problems = undeclared({"pkg/m.py": src}, deps, extras, ("worldtree",))
    assert problems == [
        "pkg/m.py:2: imports scipy (scipy), which is not declared as a dependency (or guard the import)",
        "pkg/m.py:4: imports skimage (scikit-image), which is not declared as a dependency (or guard the import)",
    ]


def test_import_names_map_to_the_declared_distributions_where_installed():
    provided = importlib.metadata.packages_distributions()
    checked = 0
    for top, dist in DIST_OF_IMPORT.items():
        if top in provided:
            assert dist in {_norm(d) for d in provided[top]}, (
                f"{top} is provided by {provided[top]}, not {dist}"
            )
            checked += 1
    assert checked >= 1  # cv2 is a runtime dependency, so it is installed wherever the tests run


def test_exceptions_are_still_needed_and_every_dependency_is_used():
    deps, extras = _declarations()
    files = _package_sources()
    imported = {
        _norm(DIST_OF_IMPORT.get(top, top))
        for src in files.values()
        for top, _, _ in third_party_imports(src, _local_packages())
    }
    assert deps - imported == set(NOT_IMPORTED), "declared runtime dependencies nothing imports"
    for (rel, top), (extra, _) in REACHED_BEHIND_A_CHECK.items():
        assert any(t == top for t, _, _ in third_party_imports(files[rel], _local_packages())), (rel, top)
        assert _norm(DIST_OF_IMPORT.get(top, top)) in extras[extra]


def _readme_command(tag: str) -> str:
    text = (ROOT / "README.md").read_text()
    m = re.search(rf"<!-- {tag} -->\n```bash\n(.+?)\n```", text, re.S)
    assert m, f"README.md has no <!-- {tag} --> block"
    return m.group(1)


def test_torch_is_a_range_in_pyproject_and_pinned_in_constraints():
    torch_req = next(r for r in PYPROJECT["project"]["dependencies"] if _req_name(r) == "torch")
    assert "==" not in torch_req, "pin torch in constraints.txt, not in the package's dependencies"
    low, high = re.fullmatch(r"torch>=([\d.]+),<([\d.]+)", torch_req.replace(" ", "")).groups()
    pins = re.findall(r"^torch==([\d.]+)$", (ROOT / "constraints.txt").read_text(), re.M)
    assert len(pins) == 1, "constraints.txt pins torch exactly once"

    def key(v: str) -> tuple[int, ...]:
        return tuple(int(p) for p in v.split("."))

    assert key(low) <= key(pins[0]) < key(high), f"torch=={pins[0]} is outside {torch_req}"


def test_readme_commands_and_ci_install_with_the_constraints():
    for tag in ("main-command", "test-command"):
        cmd = _readme_command(tag)
        assert "pip install -c constraints.txt " in cmd, f"README {tag}: {cmd}"
    ci = (ROOT / ".ci" / "run").read_text()
    installs = [line for line in ci.splitlines() if re.search(r"\bpip install\b", line)]
    assert installs, "no pip install in .ci/run"
    for line in installs:
        assert "-c constraints.txt" in line, f".ci/run installs without the constraints: {line.strip()}"
