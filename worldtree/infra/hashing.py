"""Content hashes recorded in manifests and evaluation records."""

from __future__ import annotations

import hashlib
from collections.abc import Iterable
from pathlib import Path

_CHUNK = 1 << 20


def sha256_file(path: str | Path) -> str:
    """Hex sha256 of one file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def sha256_files(paths: Iterable[str | Path]) -> str:
    """One hex sha256 over several files: the hash of ``name  sha256`` lines in the given order.

    Names (not full paths) enter the hash so that the same files in another folder hash the same.
    """
    h = hashlib.sha256()
    for p in paths:
        p = Path(p)
        h.update(f"{p.name}  {sha256_file(p)}\n".encode())
    return h.hexdigest()
