"""`wtbench export`: a finished run's Gaussians at chosen times as standard 3DGS PLY files (one per time) or one
npz of the raw time-dependent model, with an ``index.json`` (docs/python_api.md).

PLY layout (what the 3DGS reference writes, so splat viewers and editors open it): binary little-endian
float32 ``x y z nx ny nz f_dc_0..2 [f_rest_*] opacity scale_0..2 rot_0..3`` with the opacity as a logit, the
scales as natural logs of the standard deviations and the rotation as a unit quaternion (w, x, y, z), in the
model's world frame (``index.json``'s ``scene_to_model`` maps the scene's cameras into it).

Every file is written to a temporary name inside the output folder and renamed when complete; ``index.json``
is written last, so a folder without it holds an interrupted export. Nothing is written outside the folder.
"""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Any

import numpy as np
import torch

import worldtree
from worldtree.gaussian_frame import GaussianFrame
from worldtree.infra.errors import UserError

FORMATS = ("ply", "npz")
INDEX = "index.json"
PLY_LAYOUT = (
    "3DGS PLY, binary little-endian float32: x y z, nx ny nz (0), f_dc_0..2 (SH DC), f_rest_* (channel-major, "
    "when the model has them), opacity (logit), scale_0..2 (log standard deviation), rot_0..3 (unit w x y z); "
    "model world frame"
)
FRAME_FIELDS = ("means", "quats", "log_scales", "opacities", "sh0", "dynamic")


def parse_times(text: str) -> list[int] | None:
    """``--times``: None for ``all``, else the comma-separated time indices (``0,5,10``) ascending, without
    repeats (checked against the run's times by :func:`check_times`)."""
    text = text.strip()
    if text.lower() == "all":
        return None
    out: list[int] = []
    for part in text.split(","):
        try:
            out.append(int(part.strip()))
        except ValueError:
            raise UserError(
                f"--times {text}: {part.strip()!r} is not a time index; give e.g. 0,5,10 or all"
            ) from None
    return sorted(set(out))


def check_times(chosen: list[int] | None, times: list[int], text: str) -> list[int]:
    """``chosen`` (None: all of ``times``), each one of the run's ``times``."""
    if chosen is None:
        return list(times)
    bad = [t for t in chosen if t not in times]
    if bad:
        raise UserError(
            f"--times {text}: time {bad[0]} is not one of the run's times {times[0]}..{times[-1]}"
        )
    return chosen


def _same(a: GaussianFrame, b: GaussianFrame) -> bool:
    """Whether two frames hold the same Gaussians (a static model's, or a time the same node draws still)."""
    if len(a) != len(b) or (a.shN is None) != (b.shN is None):
        return False
    same = all(torch.equal(getattr(a, f), getattr(b, f)) for f in FRAME_FIELDS)
    return same and (a.shN is None or torch.equal(a.shN, b.shN))


def _flatten(prefix: str, obj: Any, out: dict[str, np.ndarray]) -> None:
    """Tensors, numbers and strings of a nested dict / list as ``prefix/key/...`` arrays (None left out)."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            _flatten(f"{prefix}/{k}", v, out)
    elif isinstance(obj, list | tuple):
        for i, v in enumerate(obj):
            _flatten(f"{prefix}/{i}", v, out)
    elif isinstance(obj, torch.Tensor):
        out[prefix] = obj.detach().cpu().numpy()
    elif isinstance(obj, bool | int | float | str):
        out[prefix] = np.asarray(obj)


def raw_model_arrays(model_dir: Path) -> dict[str, np.ndarray]:
    """Every torch file of a run's ``model/`` folder (the method's own saved model: canonical Gaussians,
    scaffold, cameras, tree nodes) flattened to ``model/<file>/<key>/...`` arrays, and ``model/model.json``."""
    from worldtree.infra.torchfile import load_torch

    out: dict[str, np.ndarray] = {"model/model.json": np.asarray((model_dir / "model.json").read_text())}
    for path in sorted(model_dir.rglob("*.pt")):
        rel = path.relative_to(model_dir).with_suffix("").as_posix()
        data = load_torch(path, "cpu", missing="missing", unreadable="unreadable ({error}); re-run the run")
        _flatten(f"model/{rel}", data, out)
    return out


def export_run(run, out: Path, fmt: str, times: list[int]) -> dict[str, Any]:
    """Write ``run``'s (:class:`benchmarks.api.LoadedRun`) Gaussians at ``times`` into the folder ``out`` as
    ``fmt`` (``ply``: ``time_<t>.ply`` per time, a time drawing the same Gaussians as the time before sharing
    its file; ``npz``: ``model.npz`` with the raw model under ``model/...`` and each time's frame under
    ``frames/<t>/<field>``) and ``index.json``. Returns the index."""
    from worldtree.infra.atomic import atomic_write_bytes, atomic_write_json

    if fmt not in FORMATS:
        raise UserError(f"--format {fmt}: choose ply or npz")
    digits = max(4, len(str(max(run.times))))
    entries: dict[str, dict[str, Any]] = {}
    arrays: dict[str, np.ndarray] = {}
    last: tuple[GaussianFrame, str] | None = None
    frame = None
    for t in times:
        frame = run.gaussians_at(t)
        entry: dict[str, Any] = {
            "gaussians": len(frame),
            "dynamic": int(frame.dynamic.sum()),
            "node": frame.node,
        }
        if fmt == "ply":
            if last is not None and _same(last[0], frame):
                name = last[1]
            else:
                name = f"time_{t:0{digits}d}.ply"
                frame.write_ply(out / name)
            entry["file"] = name
            last = (frame, name)
        else:
            key = f"frames/{t:0{digits}d}"
            for f in FRAME_FIELDS:
                arrays[f"{key}/{f}"] = getattr(frame, f).numpy()
            if frame.shN is not None:
                arrays[f"{key}/shN"] = frame.shN.numpy()
            entry.update(file="model.npz", key=key)
        entries[str(t)] = entry
    if fmt == "npz":
        arrays.update(raw_model_arrays(run.folder / "model"))
        buf = io.BytesIO()
        np.savez_compressed(buf, **arrays)
        atomic_write_bytes(out / "model.npz", buf.getvalue())
    index = {
        "format": fmt,
        "run": str(Path(run.folder).resolve()),
        "method": run.method_name,
        "preset": run.record.get("preset"),
        "config_digest": run.digest,
        "tool_version": worldtree.__version__,
        "run_tool_version": run.record.get("version"),
        "layout": PLY_LAYOUT
        if fmt == "ply"
        else (
            "npz: frames/<t>/{means [N,3], quats [N,4] w x y z, log_scales [N,3], opacities [N] activated, sh0 "
            "[N,3], dynamic [N] bool[, shN [N,K,3]]} per time (model world frame); model/<file>/... the "
            "method's saved model as written in the run's model/ folder"
        ),  # fmt: skip
        "scene_to_model": frame.scene_to_model.to_dict() if frame is not None else None,
        "times": entries,
    }
    atomic_write_json(out / INDEX, index)
    return index


def export_folder(
    run_dir: Path, out: Path, fmt: str = "ply", times: str = "all", device: str = "auto"
) -> dict:
    """``wtbench export``: load ``run_dir`` (:func:`benchmarks.api.load_run`), check ``--times`` and ``-o``
    before any work, export; a failed export removes the output folders it created."""
    from benchmarks.api import load_run
    from worldtree.infra.output_paths import check_output_folder, remove_new_folders_on_failure

    if fmt not in FORMATS:
        raise UserError(f"--format {fmt}: choose ply or npz")
    wanted = parse_times(times)  # before loading the run: a typo costs nothing
    check_output_folder(out, "-o")
    run = load_run(run_dir, device=device)
    chosen = check_times(wanted, run.times, times)
    with remove_new_folders_on_failure(out):
        Path(out).mkdir(parents=True, exist_ok=True)
        return export_run(run, Path(out), fmt, chosen)


def read_index(out: Path) -> dict[str, Any]:
    """The ``index.json`` of an export folder."""
    return json.loads((Path(out) / INDEX).read_text())
