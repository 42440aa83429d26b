"""Check an output path before long work: a folder or file that cannot be created there is refused at once,
with one line naming the option, instead of failing (or being misdiagnosed) after the work is done."""

from __future__ import annotations

import contextlib
import os
import unicodedata
from collections.abc import Iterator
from pathlib import Path

from worldtree.infra.errors import UserError


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
    :class:`worldtree.infra.folder_lock.FolderLock`), so that a failed command leaves no empty output folder.
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


# The longest file name most file systems take (ext4, XFS, APFS: 255 bytes).
NAME_MAX_BYTES = 255


def check_name(value: str, option: str) -> str:
    """Return ``value`` when it is exactly one ordinary path component, else raise :class:`UserError`
    naming ``option``. Every name a user gives that becomes a folder or file name (``--tag``, ``--name``)
    goes through here before anything is created or deleted: a separator, ``.``/``..``, an absolute path or
    a control character would put the output somewhere else than under the output folder (or break a line
    of a script or log that names it)."""
    why = _name_problem(value)
    if why is not None:
        raise UserError(
            f"{option} {value!r}: {why}; give one folder name (letters, digits, '-', '_', '.'), e.g. run1"
        )
    return value


def _name_problem(value: str) -> str | None:
    if not isinstance(value, str) or value == "":
        return "is empty"
    if value in (".", ".."):
        return f"{value!r} names an existing folder, not a new one"
    if "/" in value or "\\" in value:
        return "is a path (holds '/' or '\\'), not one folder name"
    if has_control_characters(value):
        return "holds a newline or another control character"
    if value.startswith("."):
        # Hidden names beside an output folder are the tool's own: lock files and partial folders.
        return "starts with '.', which is kept for the tool's own lock files and partial folders"
    if value != value.strip():
        return "starts or ends with a space"
    if len(value.encode("utf-8", "surrogateescape")) > NAME_MAX_BYTES:
        return f"is longer than {NAME_MAX_BYTES} bytes"
    return None


def has_control_characters(text: str) -> bool:
    """Whether ``text`` holds a newline, carriage return, tab or any other control or format character
    (Unicode categories Cc, Cf, Zl, Zp): text that ends up in a file name, a log line or a script line
    must not."""
    return any(unicodedata.category(c) in ("Cc", "Cf", "Zl", "Zp") for c in text)


def folder_name_of(path: str | Path) -> str:
    """The name of the folder ``path`` points at, with ``.`` and ``..`` resolved lexically (symbolic links
    are not followed, so a linked folder keeps its link's name): ``Path('.').name`` is ``''`` and
    ``Path('a/..').name`` is ``'..'``, neither of which may name an output folder."""
    return Path(os.path.abspath(path)).name


def check_replaceable(
    folder: str | Path, option: str, what: str, markers: tuple[str, ...], also_own: tuple[str, ...] = ()
) -> None:
    """Refuse to delete an existing ``folder`` (for ``--force``) unless this tool made it: a real folder
    (not a link or file) that holds every file in ``markers`` (the files the tool writes into every
    ``what`` it makes), or nothing but names in ``also_own`` (files the tool may write there first, e.g. a
    sweep's job record). Nothing happens when ``folder`` does not exist."""
    folder = Path(folder)
    if not (folder.exists() or folder.is_symlink()):
        return
    if folder.is_symlink() or not folder.is_dir():
        kind = "a symbolic link" if folder.is_symlink() else "a file"
        raise UserError(
            f"{option}: {folder} is {kind}, not a {what} this tool made, so --force will not delete it; "
            "remove it yourself or choose another name"
        )
    if {p.name for p in folder.iterdir()} <= set(also_own):
        return
    missing = [m for m in markers if not (folder / m).is_file()]
    if missing:
        raise UserError(
            f"{option}: {folder} is not a {what} this tool made (no {', '.join(missing)}), so --force will not "
            "delete it; remove it yourself or choose another name"
        )
