"""Building and caching the C++ rasterizer (csrc/rasterize_cpu.cpp) and, in the same library, the motion kernels
(csrc/motion_cpu.cpp: ARAP, smoothness terms, DQB skinning, relative node motions): one build per target, shared
by processes.

Three targets are compiled from the same sources:

- ``native``: ``-march=native``, the instruction set of this CPU (AVX-512, AVX2, ...); the fastest.
- ``avx2``: x86-64 with AVX2 and FMA and nothing newer (the x86-64-v3 level's vector instructions, no
  AVX-512), what every x86-64 CPU since about 2013-2015 runs; only on x86-64 CPUs that report both flags.
- ``portable``: the architecture's baseline (``-march=x86-64`` on x86-64: SSE2 only), runs on any CPU of the
  architecture.

``WORLDTREE_RASTER_TARGET`` (``auto``, ``native``, ``avx2`` or ``portable``) chooses; ``auto`` (the default)
takes ``native``, falls back to ``avx2`` where this CPU has it and then to ``portable`` (:func:`auto_order`).
The kernel sizes its SIMD vectors from the target's instruction set, so every target computes the same image
formation. ``-ffp-contract=off`` keeps the compiler from fusing multiply-adds, so the compositing rounds the same
on every target; the float ``exp`` and the backward's gradient sums use FMA explicitly where the target has it,
so the float results of the targets differ by a few roundings there (and by the order of the gradient sums).

Cache: ``$TORCH_EXTENSIONS_DIR/worldtree/<name>`` (default root ``~/.cache/torch_extensions``), where the name
carries a hash of everything that changes the built library: the sources (included ones too), the compile
flags, the target, the torch version and install path, the Python version, the compiler (its ``--version``)
and, for ``native``, the CPU's model and instruction-set flags. The sources are copied into the build folder, so
checkouts in different places share one build. A file lock around the build makes concurrent processes wait for
one build instead of compiling the same library twice.

The kernel includes only the ATen headers it uses (not ``<torch/extension.h>``, which alone took about 22 s to
compile) and registers its functions as torch custom ops in the namespace ``torch.ops.<name>`` (the build's name,
so every target's build has its own), not as a pybind11 module. Each translation unit still spends about 4.5 s
parsing those headers, so the library is two units compiled in parallel, one per core of a 2-core machine: SOURCE
and motion_cpu.cpp, which #includes the ARAP, smoothness, skinning and relative-motion files and their shared
quaternion header (INCLUDED_SOURCES). A first build
(``cpu_kernel.prepare()`` in a fresh process, Python start and torch import included) took 10.1-11.6 s on the
2-core development machine, against 13.6-14.0 s as three units (2026-11-26, docs/rendering.md); loading a
finished build takes a few milliseconds once torch is imported.
"""

from __future__ import annotations

import hashlib
import logging
import os
import platform
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import torch

log = logging.getLogger("worldtree.render")

_CSRC = Path(__file__).parent / "csrc"
SOURCE = _CSRC / "rasterize_cpu.cpp"
#: Further translation units linked into the same library (their ops join the namespace as fragments), compiled
#: in parallel with SOURCE: motion_cpu.cpp, the ARAP regulariser of the motion scaffold and its velocity and
#: acceleration terms (worldtree.motion.regularizers), the DQB skinning of Gaussians and the relative node motions
#: it blends (worldtree.motion.skinning) as one unit.
EXTRA_SOURCES: tuple[Path, ...] = (_CSRC / "motion_cpu.cpp",)
#: Sources a unit #includes instead of compiling them on their own (motion_cpu.cpp's kernels): copied next to
#: the units and covered by the build key like them. Each unit parses the ATen headers once (about 4.5 s here), so
#: two units, one per core of a 2-core machine, build faster than three (docs/rendering.md).
INCLUDED_SOURCES: tuple[Path, ...] = (
    _CSRC / "arap_cpu.cpp",
    _CSRC / "skinning_cpu.cpp",
    _CSRC / "quat_cpu.h",
    _CSRC / "relative_cpu.cpp",
    _CSRC / "smooth_cpu.cpp",
)
TARGETS = ("native", "avx2", "portable")
ENV_TARGET = "WORLDTREE_RASTER_TARGET"

# -ffp-contract=off: no fused multiply-adds the source does not ask for (the forward's compositing is unfused and
# rounds like the PyTorch reference; the exp and the backward's sums ask for FMA explicitly).
# No -ffast-math: the kernel's NaN guards (comparisons that are false for NaN) must keep their meaning.
# -fno-math-errno, -fno-trapping-math: sqrt need not set errno and floating-point exceptions are not observed
# (nothing reads either), so loops with a square root or a select can vectorise (the skinning kernel's loops);
# every operation still rounds as IEEE says, NaN and infinities included.
COMMON_CFLAGS = ("-O3", "-fopenmp", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math", "-std=c++17")
LDFLAGS = ("-fopenmp",)


_X86_64 = ("x86_64", "amd64")
# CPU flags (as /proc/cpuinfo names them) a target's code needs beyond the architecture's baseline.
_NEEDS = {"avx2": ("avx", "avx2", "fma")}


def target_cflags(target: str) -> tuple[str, ...]:
    """The instruction-set flags of ``target`` on this machine's architecture."""
    if target == "native":
        return ("-march=native",)
    machine = platform.machine().lower()
    if target == "avx2":
        if machine not in _X86_64:
            raise ValueError(f"the avx2 rasterizer target is for x86-64 CPUs; this machine is {machine}")
        return ("-march=x86-64", "-mavx2", "-mfma", "-mtune=generic")
    if target == "portable":
        if machine in _X86_64:
            return ("-march=x86-64", "-mtune=generic")
        if machine in ("aarch64", "arm64"):
            return ("-march=armv8-a",)
        return ()  # the compiler's default target is its portable baseline
    raise ValueError(f"unknown rasterizer target {target!r}; use one of {', '.join(TARGETS)}")


def _cpuinfo() -> tuple[str, str]:
    """(model name, instruction-set flags) of this CPU from /proc/cpuinfo; empty strings where unknown."""
    model, flags = "", ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key = line.split(":", 1)[0].strip()
            if key in ("model name", "cpu model") and not model:
                model = line.split(":", 1)[1].strip()
            elif key in ("flags", "Features") and not flags:
                flags = line.split(":", 1)[1].strip()
    except OSError:
        pass
    return model, flags


def cpu_signature() -> str:
    """This CPU's model name and instruction-set flags (what ``-march=native`` compiles for)."""
    model, flags = _cpuinfo()
    return f"{model}|{flags}" if (model or flags) else platform.processor() or platform.machine()


def cpu_flags() -> set[str]:
    """This CPU's instruction-set flags as /proc/cpuinfo names them (empty where it cannot be read)."""
    return set(_cpuinfo()[1].split())


def runs_here(target: str) -> bool:
    """Whether code built for ``target`` can run on this CPU (``native`` and ``portable`` always can)."""
    if target not in _NEEDS:
        return target in TARGETS
    return platform.machine().lower() in _X86_64 and set(_NEEDS[target]) <= cpu_flags()


def auto_order() -> tuple[str, ...]:
    """The targets ``auto`` tries, in order: ``native``, then ``avx2`` where this CPU runs it, then ``portable``."""
    return tuple(t for t in TARGETS if runs_here(t))


def compiler_identity() -> str:
    """First line of ``$CXX --version`` (the compiler torch's build will call); '' when it cannot run."""
    cxx = os.environ.get("CXX", "c++")
    try:
        out = subprocess.run([cxx, "--version"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        return ""
    return out.strip().splitlines()[0] if out.strip() else ""


def build_key(target: str) -> str:
    """Hash (hex, 16 digits) of everything that changes the library built for ``target``."""
    h = hashlib.sha256()
    parts = [
        *(src.read_bytes() for src in (SOURCE, *EXTRA_SOURCES, *INCLUDED_SOURCES)),
        " ".join(COMMON_CFLAGS + target_cflags(target) + LDFLAGS).encode(),
        target.encode(),
        torch.__version__.encode(),
        str(Path(torch.__file__).parent).encode(),
        sys.version.encode(),
        platform.machine().encode(),
        compiler_identity().encode(),
    ]
    if target == "native":
        parts.append(cpu_signature().encode())
    for p in parts:
        h.update(len(p).to_bytes(8, "little"))
        h.update(p)
    return h.hexdigest()[:16]


def cache_root() -> Path:
    """Folder holding the builds: ``$TORCH_EXTENSIONS_DIR/worldtree`` (default ``~/.cache/torch_extensions``)."""
    from torch.utils.cpp_extension import get_default_build_root

    return Path(os.environ.get("TORCH_EXTENSIONS_DIR") or get_default_build_root()) / "worldtree"


def module_name(target: str) -> str:
    """Name of ``target``'s build (unique per build key): its folder, its library's file name and the namespace of
    its ops (``torch.ops.<name>``), hence a valid identifier."""
    name = f"worldtree_raster_{target}_{build_key(target)}"
    if not name.isidentifier():
        raise ValueError(f"rasterizer build name {name!r} is not a valid identifier")
    return name


class Ops:
    """The custom ops a loaded build registered, as attributes: ``ops.forward`` is
    ``torch.ops.<namespace>.forward`` (called like the function it wraps; a ``std::vector<Tensor>`` comes back as a
    list)."""

    def __init__(self, namespace: str, path: Path):
        self.namespace = namespace
        self.path = path

    def __getattr__(self, fn: str):
        if fn.startswith("_") or fn in ("namespace", "path"):
            raise AttributeError(fn)
        op = getattr(getattr(torch.ops, self.namespace), fn)  # AttributeError when the library has no such op
        setattr(self, fn, op)
        return op

    def __repr__(self) -> str:
        return f"Ops({self.namespace!r}, {str(self.path)!r})"


# The libraries loaded in this process, by namespace. A namespace can be registered only once per process (a
# second library of the same name, from another folder, would fail to load) and the build name covers everything
# that changes the library, so a name loaded once is reused.
_loaded: dict[str, Ops] = {}
_loaded_lock = threading.Lock()


def _load_library(path: Path) -> Ops:
    """The ops of the library at ``path`` (``<namespace>.so``), loaded with ``torch.ops.load_library`` unless its
    namespace is loaded already (or torch's ``load()`` has just loaded it); raises OSError when it does not
    load."""
    namespace = path.name.split(".", 1)[0]
    if not namespace.isidentifier():
        raise ValueError(f"{path}: {namespace!r} is not a valid op namespace")
    with _loaded_lock:
        if namespace not in _loaded:
            if os.path.realpath(path) not in torch.ops.loaded_libraries:
                torch.ops.load_library(str(path))
            _loaded[namespace] = Ops(namespace, path)
        return _loaded[namespace]


@dataclass
class Built:
    """A loaded build."""

    module: Ops
    """The build's ops as attributes (project_forward, project_backward, forward, backward): torch.ops.<name>."""
    target: str
    """One of :data:`TARGETS`."""
    name: str
    """Build name: its folder and the namespace of its ops."""
    seconds: float
    """Time spent building or loading it in this process."""


def _libraries(name: str, folder: Path) -> list[Path]:
    """The built libraries of ``name`` in ``folder`` (``<name>.so``; torch names a rebuild in the same process
    ``<name>_v<N>.so``)."""
    return sorted(folder.glob(f"{name}*.so")) + sorted(folder.glob(f"{name}*.pyd"))


def _load_finished(name: str, folder: Path) -> Ops | None:
    """The ops of a finished build in ``folder``, loaded directly (no ninja run); None when there is none or it
    does not load, e.g. a build killed while linking or a damaged file: that file is removed, so that the build
    that follows links it again instead of trusting ninja's log."""
    for path in _libraries(name, folder):
        try:
            return _load_library(path)
        except OSError as e:
            log.info("cached rasterizer build %s does not load (%s); rebuilding", path, e.__cause__ or e)
            path.unlink(missing_ok=True)
    return None


def build(target: str, *, verbose: bool = False) -> Built:
    """Build ``target`` (or load its cached build) and import it; raises whatever the build raises.

    Holds ``<cache>/<name>.lock`` (a file lock, released if the process dies) while building and loading, so a
    second process waits for the first's build and then loads it.
    """
    from filelock import FileLock
    from torch.utils.cpp_extension import load, verify_ninja_availability

    target_cflags(target)  # unknown target or wrong architecture: ValueError before anything is built
    if not runs_here(target):
        # Building would succeed, but the first call would die of an illegal instruction.
        raise RuntimeError(
            f"this CPU lacks the instruction sets of the {target} target ({', '.join(_NEEDS[target])})"
        )
    t0 = time.perf_counter()
    name = module_name(target)
    if name in _loaded:  # loaded before in this process (from this cache or another one)
        return Built(_loaded[name], target, name, time.perf_counter() - t0)
    folder = cache_root() / name
    folder.mkdir(parents=True, exist_ok=True)
    with FileLock(str(folder.parent / f"{name}.lock")):
        # The build key names the source and flags, so a finished build is loaded directly: torch's load()
        # would run whichever ninja is first on PATH, and pip's and Debian's ninja each read the other's log
        # as stale and rebuild (a venv started with and without its bin on PATH).
        ops = _loaded.get(name) or _load_finished(name, folder)
        if ops is not None:
            return Built(ops, target, name, time.perf_counter() - t0)
        verify_ninja_availability()
        # torch's own lock file inside the folder is left behind by a build that was killed; under our lock
        # nobody else is building, so one found now is stale and would make torch wait for ever.
        (folder / "lock").unlink(missing_ok=True)
        units = (SOURCE, *EXTRA_SOURCES)
        for source in (*units, *INCLUDED_SOURCES):
            src = folder / source.name
            if not src.is_file() or src.read_bytes() != source.read_bytes():
                tmp = folder / (source.name + ".tmp")
                shutil.copyfile(source, tmp)
                os.replace(tmp, src)
        log.info("compiling the C++ rasterizer (%s target) into %s; about 11 s, once", target, folder)
        # is_python_module=False: torch loads the library with torch.ops.load_library (registering its ops) and
        # returns its path; _load_library then only records it.
        path = load(
            name=name,
            sources=[str(folder / source.name) for source in units],
            extra_cflags=list(COMMON_CFLAGS + target_cflags(target)),
            extra_ldflags=list(LDFLAGS),
            build_directory=str(folder),
            verbose=verbose,
            is_python_module=False,
        )
        ops = _load_library(Path(path))
    return Built(ops, target, name, time.perf_counter() - t0)


def requested_target() -> str:
    """The target asked for by ``WORLDTREE_RASTER_TARGET``: ``auto`` (default) or one of :data:`TARGETS`."""
    value = os.environ.get(ENV_TARGET, "auto").strip().lower() or "auto"
    if value not in ("auto", *TARGETS):
        from worldtree.infra.errors import UserError

        raise UserError(f"{ENV_TARGET}={value!r} is unknown; use auto, {', '.join(TARGETS)}")
    return value
