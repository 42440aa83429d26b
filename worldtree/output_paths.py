"""Check an output path before long work: a folder or file that cannot be created there is refused at once,
with one line naming the option, instead of failing (or being misdiagnosed) after the work is done."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

from worldtree.errors import UserError


def _nearest_existing(path: Path, option: str, shown: Path) -> Path:
    probe = path.absolute()
    while not probe.exists():
        if probe.is_symlink():  # a dangling link: neither a folder nor creatable
            raise UserError(
                f"{option} {shown}: {probe} is a broken symbolic link; remove it or choose another path"
            )
        probe = probe.parent
    return probe


def check_output_folder(path: str | Path, option: str) -> None:
    """Refuse an output folder ``path`` (given by ``option``) that cannot be created or written: an existing
    non-folder, a path running through a regular file, or a nearest existing ancestor that is not writable."""
    path = Path(path)
    probe = _nearest_existing(path, option, path)
    if not probe.is_dir():
        what = (
            "is a file, not a folder"
            if probe == path.absolute()
            else "is a file, so no folder can be made under it"
        )
        raise UserError(f"{option} {path}: {probe} {what}; choose another output folder")
    if not os.access(probe, os.W_OK | os.X_OK):
        raise UserError(f"{option} {path}: {probe} is not writable; choose another output folder")


def check_output_file(path: str | Path, option: str) -> None:
    """Refuse an output file ``path`` that cannot be written: an existing folder of that name, or a parent
    that cannot be created or written (see :func:`check_output_folder`)."""
    path = Path(path)
    if path.is_dir():
        raise UserError(f"{option} {path}: is a folder; give a file name")
    _check_parent(path, option)


def _check_parent(path: Path, option: str) -> None:
    """:func:`check_output_folder` of ``path``'s parent, worded for the file ``path``."""
    probe = _nearest_existing(path.parent, option, path)
    if not probe.is_dir():
        raise UserError(
            f"{option} {path}: {probe} is a file, so nothing can be written under it; choose another path"
        )
    if not os.access(probe, os.W_OK | os.X_OK):
        raise UserError(f"{option} {path}: {probe} is not writable; choose another path")


@contextlib.contextmanager
def remove_new_folders_on_failure(folder: str | Path, leftovers: tuple[str, ...] = ()) -> Iterator[None]:
    """On an exception, remove the folders on the way to ``folder`` that did not exist on entry, when they
    hold nothing but the names in ``leftovers`` (e.g. the lock files of a released
    :class:`worldtree.folder_lock.FolderLock`), so that a failed command leaves no empty output folder.
    Folders that existed before, or that hold anything else, are kept."""
    folder = Path(folder).absolute()
    new: list[Path] = []
    probe = folder
    while not probe.exists():
        new.append(probe)
        probe = probe.parent
    try:
        yield
    except BaseException:
        for d in new:  # deepest first
            try:
                for name in leftovers:
                    (d / name).unlink(missing_ok=True)
                d.rmdir()
            except OSError:
                break  # not empty (or not ours to remove): keep it and its parents
        raise
