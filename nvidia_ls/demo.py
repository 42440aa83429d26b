"""One call from nothing to a built scene: render a synthetic rig and build it (for demos and tests)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from nvidia_ls.build import BuildConfig, build_scene
from nvidia_ls.synth import SynthConfig, write_raw_scene


def build_synthetic_scene(
    out_dir: str | Path,
    synth: SynthConfig | None = None,
    build: BuildConfig | None = None,
    name: str = "Synth",
    gt_poses: bool = True,
) -> tuple[Path, Path]:
    """Render ``out_dir/raw/<name>`` and build it into ``out_dir/scenes/<name>``.

    Args:
        out_dir: working folder (created).
        synth: generator settings (default :class:`SynthConfig`).
        build: builder settings (default :class:`BuildConfig`); ``poses`` is overridden when ``gt_poses``.
        name: scene name.
        gt_poses: build with the ground-truth LLFF poses (skips SfM; the built world is the synthetic world,
            so ``RAW/gt`` depth, masks and object motion apply directly). False runs SfM.

    Returns:
        ``(raw_dir, scene_dir)``.
    """
    out_dir = Path(out_dir)
    raw = write_raw_scene(out_dir / "raw" / name, synth or SynthConfig(), force=True)
    cfg = build or BuildConfig()
    if gt_poses:
        cfg = replace(cfg, poses=raw / "gt" / "poses_bounds.npy")
    cfg = replace(cfg, force=True, name=name)
    return raw, build_scene(raw, out_dir / "scenes", cfg)
