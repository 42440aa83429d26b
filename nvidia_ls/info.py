"""A human-readable summary of a built scene (``nvls info``)."""

from __future__ import annotations

import json
from pathlib import Path

from rich.table import Table

from worldtree.infra.errors import UserError


def _fmt(v) -> str:
    return f"{v:.3g}" if isinstance(v, float) else str(v)


def describe_scene(scene: str | Path) -> Table:
    """A rich table with the scene's size, counts, cameras, pose and mask provenance, bounds and timings."""
    scene = Path(scene)
    try:
        man = json.loads((scene / "manifest.json").read_text())
        cams = json.loads((scene / "cameras.json").read_text())
    except FileNotFoundError as e:
        raise UserError(
            f"{scene}: {Path(e.filename).name} missing; is it a scene built by `nvls build`?"
        ) from None
    except json.JSONDecodeError as e:
        raise UserError(f"{scene}: unreadable JSON ({e.msg}); run `nvls verify` or rebuild") from None
    table = Table(title=f"NVIDIA-LS scene {scene.name}", show_header=False)
    table.add_column("field", style="bold")
    table.add_column("value")
    src = man.get("source", {})
    poses, masks = man.get("poses", {}), man.get("masks", {})
    src_times = man.get("source_times", [])
    rows = [
        (
            "image size",
            f"{cams.get('width')}x{cams.get('height')} (raw {src.get('width')}x{src.get('height')})",
        ),
        ("training frames", str(len(cams.get("frames", [])))),
        ("test frames", f"{len(cams.get('test_frames', []))} (camera {cams.get('test_camera')})"),
        ("rig cameras", str(len(cams.get("cameras", [])))),
        ("training cameras", " ".join(str(c) for c in man.get("train_cameras", []))),
        ("source", f"{src.get('path')} ({src.get('layout')}, {src.get('time_steps')} time steps)"),
        ("kept source times", f"{src_times[0]}..{src_times[-1]} ({len(src_times)})" if src_times else "-"),
        (
            "poses",
            ", ".join(
                f"{k}={_fmt(poses[k])}"
                for k in ("method", "camera_model", "sfm_time", "reprojection_error_px", "normalize")
                if k in poses
            ),
        ),
        ("masks", str(masks.get("method"))),
        ("near / far", f"{cams.get('near', float('nan')):.4g} / {cams.get('far', float('nan')):.4g}"),
        ("world scale", f"{man.get('world_transform', {}).get('scale', 1.0):.6g}"),
        ("timings (s)", ", ".join(f"{k} {v:.2f}" for k, v in man.get("timings_s", {}).items())),
        ("files", str(len(man.get("files", {})))),
        ("tool version", str(man.get("tool_version"))),
        ("warnings", "; ".join(man.get("warnings", [])) or "none"),
    ]
    for k, v in rows:
        table.add_row(k, v)
    return table
