"""What a speed figure was measured on: CPU model, SIMD instruction sets, cores, load; printed by speed scripts."""

from __future__ import annotations

import os
import platform
from pathlib import Path

# The instruction sets that decide how fast the rasterizer's and PyTorch's vector code runs.
SIMD_FLAGS = ("sse2", "sse4_2", "avx", "avx2", "fma", "avx512f", "avx512bw", "avx512vl", "neon", "asimd", "sve")


def cpu_model() -> str:
    """The CPU's model name (from /proc/cpuinfo on Linux, else what :mod:`platform` knows)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.split(":", 1)[0].strip() in ("model name", "cpu model"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def simd_flags() -> list[str]:
    """The instruction sets of :data:`SIMD_FLAGS` this CPU reports, in that order."""
    have: set[str] = set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.split(":", 1)[0].strip() in ("flags", "Features"):
                have = set(line.split(":", 1)[1].split())
                break
    except OSError:
        pass
    return [f for f in SIMD_FLAGS if f in have]


def describe() -> str:
    """One line: model, SIMD flags, CPU count, load average, torch's own SIMD level."""
    import torch

    load = " ".join(f"{x:.2f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else "n/a"
    try:
        torch_simd = torch.backends.cpu.get_cpu_capability()
    except Exception:  # older torch builds do not have it
        torch_simd = "?"
    return (
        f"CPU: {cpu_model()} | SIMD: {' '.join(simd_flags()) or 'unknown'} | {os.cpu_count()} CPUs | "
        f"load average {load} | torch {torch.__version__} kernels: {torch_simd}"
    )
