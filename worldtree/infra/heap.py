"""Give freed heap memory back to the operating system.

Rule: call :func:`release_freed_memory` after a stage drops large caches, before a stage that starts other
processes. glibc keeps freed blocks in the process's heap (its mmap threshold rises after each large free, so
later tensors of that size come from the heap too), and the resident size then still counts them while the
tree's workers need their own memory. ``malloc_trim(0)`` returns what is free; elsewhere (macOS, musl,
Windows) nothing is done.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import sys

__all__ = ["release_freed_memory"]


def release_freed_memory() -> bool:
    """Collect garbage, then ask glibc to return the freed heap to the system. Returns whether it trimmed
    (False where the C library has no ``malloc_trim``)."""
    gc.collect()
    if not sys.platform.startswith("linux"):
        return False
    name = ctypes.util.find_library("c") or "libc.so.6"
    try:
        trim = ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):  # musl and other C libraries without it
        return False
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    trim(0)
    return True
