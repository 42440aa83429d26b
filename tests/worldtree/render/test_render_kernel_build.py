"""The C++ rasterizer's build cache: what its key covers, one shared build for concurrent processes, and the
loading of its library (torch custom ops, one namespace per build)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from worldtree.infra.errors import UserError
from worldtree.render import kernel_build

REPO = Path(__file__).resolve().parents[3]


def test_key_covers_source_flags_target_and_cpu(monkeypatch, tmp_path):
    src = tmp_path / "k.cpp"
    src.write_text("int a;\n")
    extra = tmp_path / "e.cpp"
    extra.write_text("int e;\n")
    included = tmp_path / "i.cpp"  # #included by a unit, not compiled on its own
    included.write_text("int i;\n")
    monkeypatch.setattr(kernel_build, "SOURCE", src)
    monkeypatch.setattr(kernel_build, "EXTRA_SOURCES", (extra,))
    monkeypatch.setattr(kernel_build, "INCLUDED_SOURCES", (included,))
    monkeypatch.setattr(kernel_build.platform, "machine", lambda: "x86_64")  # every target has flags there
    base = {t: kernel_build.build_key(t) for t in kernel_build.TARGETS}
    assert len(set(base.values())) == len(kernel_build.TARGETS)  # different targets never share a build

    src.write_text("int b;\n")
    assert all(kernel_build.build_key(t) != base[t] for t in kernel_build.TARGETS)  # any source edit
    src.write_text("int a;\n")
    assert {t: kernel_build.build_key(t) for t in kernel_build.TARGETS} == base  # and back: same key
    extra.write_text("int f;\n")
    assert all(kernel_build.build_key(t) != base[t] for t in kernel_build.TARGETS)  # an edit of a further unit
    extra.write_text("int e;\n")
    included.write_text("int j;\n")
    assert all(kernel_build.build_key(t) != base[t] for t in kernel_build.TARGETS)  # an edit of an included file
    included.write_text("int i;\n")

    monkeypatch.setattr(kernel_build, "COMMON_CFLAGS", (*kernel_build.COMMON_CFLAGS, "-g"))
    assert all(kernel_build.build_key(t) != base[t] for t in kernel_build.TARGETS)  # any flag
    monkeypatch.undo()
    monkeypatch.setattr(kernel_build, "SOURCE", src)
    monkeypatch.setattr(kernel_build, "EXTRA_SOURCES", (extra,))
    monkeypatch.setattr(kernel_build, "INCLUDED_SOURCES", (included,))
    monkeypatch.setattr(kernel_build.platform, "machine", lambda: "x86_64")

    # -march=native compiles for this CPU: another CPU needs another native build, not another portable one.
    monkeypatch.setattr(kernel_build, "cpu_signature", lambda: "Other CPU|sse2 avx2")
    assert kernel_build.build_key("native") != base["native"]
    assert kernel_build.build_key("portable") == base["portable"]
    assert kernel_build.build_key("avx2") == base["avx2"]  # a fixed instruction set, like portable
    # Another compiler, or another torch, changes every build.
    monkeypatch.setattr(kernel_build, "compiler_identity", lambda: "c++ (Other) 99.1")
    assert kernel_build.build_key("portable") != base["portable"]
    monkeypatch.setattr(kernel_build.torch, "__version__", "0.0.1")
    assert kernel_build.build_key("portable") != base["portable"]


def test_target_flags_and_choice(monkeypatch):
    assert kernel_build.target_cflags("native") == ("-march=native",)
    monkeypatch.setattr(kernel_build.platform, "machine", lambda: "x86_64")
    assert "-march=x86-64" in kernel_build.target_cflags("portable")
    avx2 = kernel_build.target_cflags("avx2")
    assert {"-mavx2", "-mfma"} <= set(avx2) and not any("512" in f or "native" in f for f in avx2)
    with pytest.raises(ValueError, match="unknown rasterizer target"):
        kernel_build.target_cflags("fastest")
    monkeypatch.setenv(kernel_build.ENV_TARGET, "AVX2")
    assert kernel_build.requested_target() == "avx2"
    monkeypatch.setenv(kernel_build.ENV_TARGET, "Portable")
    assert kernel_build.requested_target() == "portable"
    monkeypatch.delenv(kernel_build.ENV_TARGET)
    assert kernel_build.requested_target() == "auto"
    monkeypatch.setenv(kernel_build.ENV_TARGET, "avx9")
    with pytest.raises(UserError, match="WORLDTREE_RASTER_TARGET"):
        kernel_build.requested_target()


def test_auto_order_follows_the_cpu_flags(monkeypatch):
    """auto: native, then avx2 only where the CPU reports avx, avx2 and fma (on x86-64), then portable."""
    monkeypatch.setattr(kernel_build.platform, "machine", lambda: "x86_64")
    flags = {
        "sse2 avx avx2 fma": True,
        "sse2 avx avx2 fma avx512f": True,
        "sse2 avx": False,
        "sse2 avx avx2": False,
    }
    for line, has in flags.items():
        monkeypatch.setattr(kernel_build, "_cpuinfo", lambda line=line: ("Some CPU", line))
        assert kernel_build.runs_here("avx2") is has
        want = ("native", "avx2", "portable") if has else ("native", "portable")
        assert kernel_build.auto_order() == want
        assert kernel_build.runs_here("native") and kernel_build.runs_here("portable")
    # Another architecture never gets the x86 build, whatever its flags say.
    monkeypatch.setattr(kernel_build, "_cpuinfo", lambda: ("Some CPU", "avx avx2 fma"))
    monkeypatch.setattr(kernel_build.platform, "machine", lambda: "aarch64")
    assert kernel_build.auto_order() == ("native", "portable")
    with pytest.raises(ValueError, match="x86-64"):
        kernel_build.target_cflags("avx2")


def test_build_refuses_a_target_this_cpu_cannot_run(monkeypatch, tmp_path):
    """Building avx2 on a CPU without it would load fine and then die of an illegal instruction: refused first."""
    monkeypatch.setattr(kernel_build.platform, "machine", lambda: "x86_64")
    monkeypatch.setattr(kernel_build, "_cpuinfo", lambda: ("Old CPU", "sse2 sse4_2 avx"))
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    with pytest.raises(RuntimeError, match="lacks .*avx2"):
        kernel_build.build("avx2")
    assert not (tmp_path / "ext").exists()  # nothing was compiled or even prepared


def _tiny_source(path: Path, value: str) -> Path:
    """A tiny library built like the kernel: one op ``value() -> int`` in the namespace of the build's name."""
    path.write_text(
        "#include <torch/library.h>\n"
        f"int64_t value() {{\n  return\n{value}\n;\n}}\n"
        "#define TINY_LIBRARY(ns, m) TORCH_LIBRARY(ns, m)\n"
        'TINY_LIBRARY(TORCH_EXTENSION_NAME, m) { m.def("value", &value); }\n'
    )
    return path


_BUILD_ONE = textwrap.dedent(
    """
    import json, sys
    from pathlib import Path
    from worldtree.render import kernel_build
    kernel_build.SOURCE = Path(sys.argv[1])
    kernel_build.EXTRA_SOURCES = kernel_build.INCLUDED_SOURCES = ()
    built = kernel_build.build("portable")
    print(json.dumps({"name": built.name, "value": built.module.value()}))
    """
)


def test_concurrent_processes_share_one_build(tmp_path):
    """Two processes asking for the same build at once: one compiles, the other waits and loads it."""
    pytest.importorskip("ninja")
    src = _tiny_source(tmp_path / "tiny.cpp", "42")
    env = {**os.environ, "TORCH_EXTENSIONS_DIR": str(tmp_path / "ext"), "PYTHONPATH": str(REPO)}
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", _BUILD_ONE, str(src)], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True,
        )
        for _ in range(2)
    ]  # fmt: skip
    results = []
    for p in procs:
        out, err = p.communicate(timeout=600)
        if p.returncode != 0 and "compiler" in err.lower():
            pytest.skip("no C++ compiler here")
        assert p.returncode == 0, err
        results.append(json.loads(out.strip().splitlines()[-1]))
    assert results[0] == results[1] and results[0]["value"] == 42
    folder = tmp_path / "ext" / "worldtree" / results[0]["name"]
    # ninja's log has one line per command it ran: one compile and one link, whoever ran them.
    ran = [ln for ln in (folder / ".ninja_log").read_text().splitlines() if not ln.startswith("#")]
    assert len(ran) == 2, ran
    assert (folder / src.name).read_text() == src.read_text()  # the build compiled its own copy of the source


def test_a_finished_build_is_loaded_whatever_ninja_is_on_path(tmp_path):
    """A process started with another PATH (the venv's bin first or not: pip's ninja or Debian's, or none at
    all) loads the finished build as it is: nothing is compiled again, ninja is not even run."""
    pytest.importorskip("ninja")
    src = _tiny_source(tmp_path / "tiny.cpp", "7")
    env = {**os.environ, "TORCH_EXTENSIONS_DIR": str(tmp_path / "ext"), "PYTHONPATH": str(REPO)}

    def run(path: str) -> dict:
        p = subprocess.run([sys.executable, "-c", _BUILD_ONE, str(src)], env={**env, "PATH": path},
                           capture_output=True, text=True, timeout=600)  # fmt: skip
        if p.returncode != 0 and "compiler" in p.stderr.lower():
            pytest.skip("no C++ compiler here")
        assert p.returncode == 0, p.stderr
        return json.loads(p.stdout.strip().splitlines()[-1])

    first = run(os.environ.get("PATH", ""))
    folder = tmp_path / "ext" / "worldtree" / first["name"]
    log_before = (folder / ".ninja_log").read_text()
    so = sorted(folder.glob(f"{first['name']}*.so"))
    stamps = [p.stat().st_mtime_ns for p in so]
    # Another ninja first on PATH (as pip's and Debian's swap places when a venv is or is not activated); it
    # leaves a mark if anything runs it. The compiler stays the same: it is part of the build key.
    other = tmp_path / "other-ninja"
    other.mkdir()
    mark = tmp_path / "ninja-ran"
    fake = other / "ninja"
    fake.write_text(f"#!/bin/sh\ntouch {mark}\nexit 1\n")
    fake.chmod(0o755)
    second = run(os.pathsep.join([str(other), os.environ.get("PATH", "")]))
    assert not mark.exists()
    assert second == first and second["value"] == 7
    assert (folder / ".ninja_log").read_text() == log_before
    assert [p.stat().st_mtime_ns for p in so] == stamps


def test_a_damaged_finished_build_is_rebuilt(tmp_path):
    """A library that does not load (a damaged file, newer than its object file, so ninja alone would call it up to
    date) is removed and linked again, and the new one is loaded."""
    pytest.importorskip("ninja")
    src = _tiny_source(tmp_path / "tiny.cpp", "5")
    env = {**os.environ, "TORCH_EXTENSIONS_DIR": str(tmp_path / "ext"), "PYTHONPATH": str(REPO)}

    def run() -> dict:
        p = subprocess.run([sys.executable, "-c", _BUILD_ONE, str(src)], env=env, capture_output=True, text=True,
                           timeout=600)  # fmt: skip
        if p.returncode != 0 and "compiler" in p.stderr.lower():
            pytest.skip("no C++ compiler here")
        assert p.returncode == 0, p.stderr
        return json.loads(p.stdout.strip().splitlines()[-1])

    first = run()
    so = tmp_path / "ext" / "worldtree" / first["name"] / f"{first['name']}.so"
    so.write_bytes(b"not a shared library")
    assert run() == first and first["value"] == 5
    assert so.read_bytes()[:4] == b"\x7fELF"  # linked again


def test_two_targets_in_one_process_have_their_own_ops(monkeypatch, tmp_path):
    """Each build registers its ops in its own namespace (its name), so several targets load side by side in one
    process; asking for a build again returns the ops already loaded, without loading the library again."""
    pytest.importorskip("ninja")
    import torch

    value = "#if defined(__AVX2__)\n2\n#else\n1\n#endif\n"  # what the target's flags compiled
    monkeypatch.setattr(kernel_build, "SOURCE", _tiny_source(tmp_path / "tiny.cpp", value))
    monkeypatch.setattr(kernel_build, "EXTRA_SOURCES", ())
    monkeypatch.setattr(kernel_build, "INCLUDED_SOURCES", ())
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    try:
        native, portable = kernel_build.build("native"), kernel_build.build("portable")
    except Exception as e:
        if "compiler" in str(e).lower() or "ninja" in str(e).lower():
            pytest.skip(f"no build here: {e}")
        raise
    assert native.name != portable.name
    assert native.module.namespace == native.name and portable.module.namespace == portable.name
    assert native.module.value is getattr(torch.ops, native.name).value
    assert portable.module.value is getattr(torch.ops, portable.name).value
    if kernel_build.platform.machine().lower() in ("x86_64", "amd64"):
        assert portable.module.value() == 1  # SSE2 only
        assert native.module.value() == (2 if "avx2" in kernel_build.cpu_flags() else 1)
    loaded = {str(native.module.path.resolve()), str(portable.module.path.resolve())}
    assert loaded <= torch.ops.loaded_libraries

    def no_second_load(path):
        raise AssertionError(f"{path} loaded again")

    monkeypatch.setattr(torch.ops, "load_library", no_second_load)
    again = kernel_build.build("portable")
    assert again.module is portable.module and again.module.value() == portable.module.value()
    # Even from another cache folder: the name (the build key) is what identifies the library.
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "other-ext"))
    assert kernel_build.build("native").module is native.module


def test_included_sources_are_compiled_through_a_unit():
    """Each INCLUDED_SOURCES file is #included by a compiled unit (else its ops would be missing), none is a unit."""
    units = (kernel_build.SOURCE, *kernel_build.EXTRA_SOURCES)
    for inc in kernel_build.INCLUDED_SOURCES:
        assert inc.is_file() and inc not in units
        assert sum(f'#include "{inc.name}"' in unit.read_text() for unit in units) == 1, inc.name
