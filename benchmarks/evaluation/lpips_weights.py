"""Find, check, install and download the two LPIPS weight files.

LPIPS (AlexNet, v0.1) needs:

- torchvision's ImageNet AlexNet, ``alexnet-owt-7be5be79.pth``: a state dict whose ``features.*`` keys we
  use. Like torchvision, we check that the file's sha256 starts with the 8 hex digits in its name.
- the LPIPS project's linear heads, ``alex.pth`` (``lin0.model.1.weight`` .. ``lin4.model.1.weight``). No
  published checksum exists for it, so its keys and shapes are checked strictly and its sha256 is recorded
  with every evaluation.

A weights folder holds both files. Folders are searched in this order: the ``--lpips-weights DIR`` option,
the ``WTBENCH_LPIPS_WEIGHTS`` environment variable, then the user cache folder
(``$XDG_CACHE_HOME/worldtree-bench/lpips``, default ``~/.cache/worldtree-bench/lpips``). A folder named by
the option or the variable must hold valid files (else :class:`~worldtree.infra.errors.UserError`); only when
neither is given do missing weights mean "no LPIPS" (:class:`WeightsNotFound`).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from worldtree.infra.errors import UserError
from worldtree.infra.hashing import sha256_file

ALEXNET_FILE = "alexnet-owt-7be5be79.pth"
#: First 8 hex digits of the sha256 of torchvision's AlexNet file (torchvision's naming convention).
ALEXNET_SHA256_PREFIX = "7be5be79"
LIN_FILE = "alex.pth"
ALEXNET_URL = "https://download.pytorch.org/models/alexnet-owt-7be5be79.pth"
LIN_URL = (
    "https://raw.githubusercontent.com/richzhang/PerceptualSimilarity/master/lpips/weights/v0.1/alex.pth"
)
ENV_VAR = "WTBENCH_LPIPS_WEIGHTS"
FIX_HINT = (
    f"copy {ALEXNET_FILE} and {LIN_FILE} into a folder and run `wtbench weights install --from DIR` "
    f"(or pass --lpips-weights DIR, or set {ENV_VAR}); online: `wtbench weights download`"
)


class WeightsNotFound(UserError):
    """No LPIPS weights in the default cache and none named explicitly (evaluation goes on without LPIPS)."""


@dataclass(frozen=True)
class WeightsFolder:
    """One place where weights are looked for."""

    path: Path  #: the folder
    origin: str  #: why it is searched: "--lpips-weights", "$WTBENCH_LPIPS_WEIGHTS" or "user cache"


@dataclass(frozen=True)
class LpipsWeights:
    """Checked weight files; :meth:`record` is what evaluation records store."""

    folder: Path  #: folder holding both files
    alexnet_sha256: str  #: sha256 of the AlexNet file
    lin_sha256: str  #: sha256 of alex.pth

    def record(self) -> dict[str, Any]:
        return {
            "net": "alex",
            "version": "0.1",
            "folder": str(self.folder),
            "alexnet_file": ALEXNET_FILE,
            "alexnet_sha256": self.alexnet_sha256,
            "lin_file": LIN_FILE,
            "lin_sha256": self.lin_sha256,
        }


def default_folder() -> Path:
    """The user cache folder for the weights (honours ``XDG_CACHE_HOME``)."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "worldtree-bench" / "lpips"


def search_folders(explicit: str | Path | None = None) -> list[WeightsFolder]:
    """The folders searched, in order (the explicit one and the environment's only when given)."""
    out = []
    if explicit:
        out.append(WeightsFolder(Path(explicit).expanduser(), "--lpips-weights"))
    if os.environ.get(ENV_VAR):
        out.append(WeightsFolder(Path(os.environ[ENV_VAR]).expanduser(), f"${ENV_VAR}"))
    out.append(WeightsFolder(default_folder(), "user cache"))
    return out


def locate(explicit: str | Path | None = None) -> WeightsFolder:
    """The folder to load from: the first of :func:`search_folders` (an explicit one must be complete).

    Raises :class:`UserError` when the option or the variable names a folder lacking a file, and
    :class:`WeightsNotFound` when nothing was named and the cache lacks a file.
    """
    first = search_folders(explicit)[0]
    missing = [n for n in (ALEXNET_FILE, LIN_FILE) if not (first.path / n).is_file()]
    if not missing:
        return first
    what = f"{first.path} ({first.origin}) has no {' and no '.join(missing)}"
    if first.origin == "user cache":
        raise WeightsNotFound(f"LPIPS weights not found: {what}; {FIX_HINT}")
    raise UserError(f"{what}; put both LPIPS weight files there or {FIX_HINT}")


def _load_state_dict(path: Path) -> dict:
    import torch

    try:
        sd = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises many types for corrupt or foreign files
        raise UserError(
            f"{path}: cannot read as a PyTorch state dict ({type(e).__name__}); {FIX_HINT}"
        ) from e
    if not isinstance(sd, dict):
        raise UserError(f"{path}: holds a {type(sd).__name__}, not a state dict; {FIX_HINT}")
    return sd


def check_alexnet(path: Path) -> tuple[dict, str]:
    """Check torchvision's AlexNet file (sha256 prefix, keys, shapes) -> (state dict, sha256)."""
    digest = sha256_file(path)
    if not digest.startswith(ALEXNET_SHA256_PREFIX):
        raise UserError(
            f"{path}: sha256 {digest[:8]}... does not start with {ALEXNET_SHA256_PREFIX} (corrupt or a different "
            f"file); download it again from {ALEXNET_URL}"
        )
    from benchmarks.evaluation.lpips import AlexNetFeatures

    sd = _load_state_dict(path)
    try:
        AlexNetFeatures().load_torchvision_state_dict(sd)
    except ValueError as e:
        raise UserError(f"{path}: not torchvision's AlexNet weights ({e}); {FIX_HINT}") from e
    return sd, digest


def check_lin(path: Path) -> tuple[dict, str]:
    """Check LPIPS' ``alex.pth`` (exact keys and shapes) -> (state dict, sha256)."""
    from benchmarks.evaluation.lpips import LPIPS

    sd = _load_state_dict(path)
    try:
        LPIPS().load_lin_state_dict(sd)
    except ValueError as e:
        raise UserError(f"{path}: not LPIPS v0.1 AlexNet linear heads ({e}); {FIX_HINT}") from e
    return sd, sha256_file(path)


def load_lpips(explicit: str | Path | None = None, device=None):
    """Locate, check and load the weights -> (:class:`benchmarks.evaluation.lpips.LPIPS` on ``device``, :class:`LpipsWeights`).

    Raises :class:`WeightsNotFound` (nothing named, nothing cached) or :class:`UserError` (bad files).
    """
    from benchmarks.evaluation.lpips import LPIPS

    folder = locate(explicit).path
    alex_sd, alex_sha = check_alexnet(folder / ALEXNET_FILE)
    lin_sd, lin_sha = check_lin(folder / LIN_FILE)
    model = LPIPS.from_state_dicts(alex_sd, lin_sd)
    if device is not None:
        model = model.to(device)
    return model, LpipsWeights(folder.resolve(), alex_sha, lin_sha)


def _copy_atomic(src: Path, dest: Path) -> None:
    dest.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=".tmp", dir=dest.parent)
    os.close(fd)
    try:
        shutil.copyfile(src, tmp)
        os.replace(tmp, dest)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def install_from(src: str | Path, dest: str | Path | None = None) -> dict[str, str]:
    """Check the weight files found in ``src`` and copy them into ``dest`` (default: the user cache).

    ``src`` may hold one or both files. Returns {file name: sha256} of what was installed.
    """
    src = Path(src).expanduser()
    dest = Path(dest).expanduser() if dest else default_folder()
    if not src.is_dir():
        raise UserError(
            f"--from {src}: not a folder; give the folder holding {ALEXNET_FILE} and/or {LIN_FILE}"
        )
    checks = {ALEXNET_FILE: check_alexnet, LIN_FILE: check_lin}
    found = {n: src / n for n in checks if (src / n).is_file()}
    if not found:
        raise UserError(
            f"--from {src}: neither {ALEXNET_FILE} nor {LIN_FILE} is there; give the folder holding the copied "
            f"files (sources: {ALEXNET_URL} and {LIN_URL})"
        )
    installed = {}
    for name, path in found.items():
        _, digest = checks[name](path)  # check before copying so a bad file never lands in the cache
        if path.resolve() != (dest / name).resolve():
            _copy_atomic(path, dest / name)
        installed[name] = digest
    return installed


def download(dest: str | Path | None = None, timeout: float = 60.0) -> dict[str, str]:
    """Download both files from their public URLs into ``dest`` (default: the user cache), then check them.

    A machine without internet access gets a one-line :class:`UserError` with the offline fix.
    """
    import urllib.error
    import urllib.request

    dest = Path(dest).expanduser() if dest else default_folder()
    dest.mkdir(parents=True, exist_ok=True)
    installed = {}
    for name, url, check in ((ALEXNET_FILE, ALEXNET_URL, check_alexnet), (LIN_FILE, LIN_URL, check_lin)):
        fd, tmp = tempfile.mkstemp(prefix=f".{name}.", suffix=".download", dir=dest)
        try:
            with os.fdopen(fd, "wb") as f, urllib.request.urlopen(url, timeout=timeout) as r:
                shutil.copyfileobj(r, f)
            _, digest = check(Path(tmp))
            os.replace(tmp, dest / name)
        except (urllib.error.URLError, OSError, TimeoutError) as e:
            reason = getattr(e, "reason", None) or e
            raise UserError(
                f"cannot download {url} ({reason}); on a machine without internet copy {ALEXNET_FILE} and "
                f"{LIN_FILE} into a folder and run `wtbench weights install --from DIR`"
            ) from None
        finally:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
        installed[name] = digest
    return installed
