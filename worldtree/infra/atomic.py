"""Write outputs so that an interrupted run never leaves a half-written file or folder behind."""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder, then rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            os.fchmod(f.fileno(), 0o666 & ~_umask())  # mkstemp's 0600 -> the usual mode of a new file
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write UTF-8 ``text`` atomically (see :func:`atomic_write_bytes`)."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | Path, obj: Any) -> None:
    """Write ``obj`` as indented, key-sorted JSON atomically."""
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True, default=_json_default) + "\n")


def _json_default(o: Any) -> Any:
    # numpy scalars/arrays and paths appear in records; store them as plain JSON values.
    if hasattr(o, "tolist"):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


@contextlib.contextmanager
def atomic_dir(final: str | Path, *, force: bool = False) -> Iterator[Path]:
    """Yield a temporary sibling folder; on success it replaces ``final`` in one rename.

    On an exception the temporary folder is removed and ``final`` is left untouched. With ``force`` an
    existing ``final`` is replaced; without it the caller is expected to have refused already.
    """
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.", suffix=".partial", dir=final.parent))
    # mkdtemp makes the folder private (0700); the finished folder gets the usual permissions of a new folder.
    os.chmod(tmp, 0o777 & ~_umask())
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if final.exists() or final.is_symlink():
        if not force:
            shutil.rmtree(tmp, ignore_errors=True)
            raise FileExistsError(final)
        old = _old_path(final)
        remove_path(old)
        os.replace(final, old)
        os.replace(tmp, final)
        remove_path(old)
    else:
        os.replace(tmp, final)


def _umask() -> int:
    """The process's umask (read by setting it and putting it back at once)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _old_path(final: Path) -> Path:
    return final.with_name(f".{final.name}.old")


def remove_path(path: str | Path) -> None:
    """Remove ``path`` whatever it is: a folder tree, a file or a symbolic link (never what a link points
    to); nothing when it does not exist."""
    path = Path(path)
    if path.is_symlink() or path.is_file():
        path.unlink()
    elif path.is_dir():
        shutil.rmtree(path)


#: mkstemp's and mkdtemp's random part of a temporary's name: 8 characters of [a-z0-9_].
_RANDOM = "[a-z0-9_]{8}"


def remove_stale_partials(final: str | Path) -> list[Path]:
    """Remove what killed :func:`atomic_dir` calls for ``final`` left beside it: temporary
    ``.NAME.XXXXXXXX.partial`` folders and a ``.NAME.old``. Returns the paths removed.

    Only safe while the caller holds ``final``'s :class:`worldtree.infra.folder_lock.FolderLock`: then no live
    writer of ``final`` owns any of them.
    """
    final = Path(final)
    if not final.parent.is_dir():
        return []
    # mkdtemp's random part is 8 characters of [a-z0-9_]; matching it exactly keeps ``A``'s cleanup away
    # from the temporaries of a sibling called ``A.b``.
    pattern = re.compile(rf"\.{re.escape(final.name)}\.{_RANDOM}\.partial")
    stale = [p for p in final.parent.iterdir() if pattern.fullmatch(p.name)]
    old = _old_path(final)
    if old.exists() or old.is_symlink():
        stale.append(old)
    for p in stale:
        remove_path(p)
    return stale


# What a killed writer leaves: mkstemp/mkdtemp's ``.NAME.`` + 8 random characters + ``.tmp`` / ``.partial``, and
# atomic_dir's ``.NAME.old``.
_STALE = re.compile(rf"\..+\.(?:{_RANDOM}\.(?:tmp|partial)|old)")


def remove_stale_temporaries(folder: str | Path) -> list[Path]:
    """Remove, anywhere under ``folder``, what killed :func:`atomic_write_bytes` and :func:`atomic_dir` calls
    left: ``.NAME.XXXXXXXX.tmp`` files, ``.NAME.XXXXXXXX.partial`` folders and ``.NAME.old``. Linked folders
    are not entered (a lent root's checkpoints belong to another run). Returns the paths removed.

    Only safe while the caller holds ``folder``'s :class:`worldtree.infra.folder_lock.FolderLock`: then no live
    writer owns any of them.
    """
    removed: list[Path] = []
    for top, dirs, files in os.walk(folder):  # followlinks=False: a link is listed, never entered
        stale_dirs = [d for d in dirs if _STALE.fullmatch(d)]
        dirs[:] = [d for d in dirs if d not in stale_dirs]  # removed below, not walked into
        for name in stale_dirs + [f for f in files if _STALE.fullmatch(f)]:
            path = Path(top) / name
            remove_path(path)
            removed.append(path)
    return sorted(removed)
