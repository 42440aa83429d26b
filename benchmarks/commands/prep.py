"""`wtbench prep`: compute and cache 2D priors (flow, tracks, depth, dynamic masks) for a scene."""

from __future__ import annotations

from pathlib import Path

import typer

from nvidia_ls.config_options import setting_options
from worldtree.infra.cli_runner import options_named
from worldtree.infra.errors import UserError
from worldtree.priors.config import (  # light: dataclasses only
    DepthConfig,
    DepthImportConfig,
    EpiConfig,
    MotionConfig,
    PriorsConfig,
)


def register(app: typer.Typer) -> None:
    @app.command(
        "prep",
        help="Compute and cache 2D priors (flow, tracks, depth, dynamic masks) for a scene. A second run with "
        "the same inputs and settings reuses the cache; an interrupted run resumes. See docs/priors.md.",
    )
    def _cmd(
        scene: Path = typer.Argument(..., help="Scene folder written by `nvls build` (holds cameras.json)."),
        depth: str = typer.Option(
            "classical", help="'classical' (plane-sweep stereo) or a file/folder to import."
        ),
        depth_kind: str = typer.Option("depth", help="Imported maps hold 'depth' or 'disparity'."),
        depth_fit: bool = typer.Option(
            False, help="Fit a per-frame scale/shift of the imported depth to the classical depth."
        ),
        depth_merge: str = typer.Option(
            "replace",
            help="replace: the imported depth is the prior; fill: keep confident classical depth, "
            "imported (fitted, needs --depth-fit) on moving objects and unconfident pixels.",
        ),
        depth_png_scale: float = typer.Option(
            DepthImportConfig.png_scale, help="16-bit depth PNG values are divided by this."
        ),
        tracks: str = typer.Option(
            "classical", help="'classical' (Lucas-Kanade) or a CoTracker .npy/.npz/.pt file."
        ),
        flow: str = typer.Option(
            "classical", help="'classical' (OpenCV DIS) or a folder of <i>_<j>.flo/.npy."
        ),
        masks: Path | None = typer.Option(
            None, help="Folder of dynamic masks (one per frame) replacing EPI masks."
        ),
        cache: Path | None = typer.Option(None, help="Cache folder (default: SCENE/priors, per downscale)."),
        preview: bool = typer.Option(False, help="Also write PNG previews (depth, tracks, EPI masks)."),
        downscale: int = typer.Option(1, help="Shrink frames by this integer factor first."),
        epi_threshold: float = typer.Option(
            1.5, help="Sampson distance (pixels) above which a pixel is dynamic."
        ),
        planes: int = typer.Option(64, help="Depth hypotheses of the plane sweep."),
        epi_from_flow: bool = typer.Option(
            False,
            help="Epipolar errors from fundamental matrices estimated on the flow (LMedS), not from the "
            "poses: for a clip imported with `nvls import --no-poses`.",
        ),
        motion: bool | None = typer.Option(
            None,
            "--motion/--no-motion",
            help="Motion discovery (cues fused into the masks, dynamic tracks chained through flow); "
            "default: priors.motion.enabled's default.",
        ),
    ) -> None:
        with options_named(setting_options(PriorsConfig, PRIOR_OPTIONS) | {"downscale": "--downscale"}):
            _run(scene, depth, depth_kind, depth_fit, depth_png_scale, tracks, flow, masks, cache, preview,
                 downscale, epi_threshold, planes, epi_from_flow, depth_merge, motion)  # fmt: skip


#: The options of `wtbench prep` that set a field of PriorsConfig (by its path); library errors about these
#: fields name them (worldtree.infra.cli_runner.options_named).
PRIOR_OPTIONS = {"depth_source": "--depth", "tracks_source": "--tracks", "flow_source": "--flow",
                 "masks_source": "--masks"}  # fmt: skip


def _run(scene_dir, depth, depth_kind, depth_fit, depth_png_scale, tracks, flow, masks, cache, preview,
         downscale, epi_threshold, planes, epi_from_flow=False, depth_merge="replace",
         motion=None) -> None:  # fmt: skip
    import dataclasses

    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from worldtree.priors import compute_priors
    from worldtree.priors.preview import write_previews
    from worldtree.scene import load_scene

    if depth_kind not in ("depth", "disparity"):
        raise UserError(f"--depth-kind {depth_kind!r}: choose depth or disparity")
    if planes < 2:
        raise UserError(f"--planes {planes}: need at least 2 depth hypotheses")
    if not epi_threshold > 0:
        raise UserError(f"--epi-threshold {epi_threshold}: must be a positive number of pixels")
    if depth_merge not in ("replace", "fill"):
        raise UserError(f"--depth-merge {depth_merge!r}: choose replace or fill")
    if depth_merge == "fill" and not depth_fit:
        raise UserError("--depth-merge fill needs --depth-fit (the import must be in the classical scale)")
    if depth_fit and depth == "classical":
        raise UserError("--depth-fit applies to imported depth; pass --depth DIR or drop --depth-fit")
    console = Console(stderr=True)
    sc = load_scene(scene_dir, downscale=downscale, load_masks=False)
    cfg = PriorsConfig(
        depth=dataclasses.replace(DepthConfig(), num_planes=planes),
        epi=dataclasses.replace(EpiConfig(), threshold_px=epi_threshold, use_poses=not epi_from_flow),
        depth_import=DepthImportConfig(
            kind=depth_kind, png_scale=depth_png_scale, fit_scale_shift=depth_fit, merge=depth_merge
        ),
        depth_source=depth,
        tracks_source=tracks,
        flow_source=flow,
        masks_source=str(masks) if masks is not None else None,
        motion=MotionConfig() if motion is None else dataclasses.replace(MotionConfig(), enabled=motion),
    )
    cache_dir = cache if cache is not None else Path(scene_dir) / "priors" / f"x{downscale}"
    with Progress(
        TextColumn("{task.description:<9}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
        console=console, transient=False,
    ) as bar:  # fmt: skip
        tasks: dict[str, int] = {}

        def progress(stage: str, done: int, total: int) -> None:
            if stage not in tasks:
                tasks[stage] = bar.add_task(stage, total=total)
            bar.update(tasks[stage], completed=done)

        pri = compute_priors(sc, cfg, cache_dir, progress)
    console.print(f"scene {sc.name}: {sc.num_frames} frames at {sc.width}x{sc.height}")
    for k, v in pri.sources.items():
        console.print(f"  {k:<7} {v}")
    console.print(
        f"  {pri.tracks.shape[1]} tracks ({int(pri.track_dynamic.sum())} dynamic), "
        f"dynamic pixels {100 * pri.epi_mask.mean():.1f}%, flow pairs {len(pri.flow)}"
    )
    console.print(f"cache: {cache_dir}")
    if preview:
        from worldtree.pixels import as_uint8

        imgs = as_uint8(sc.images).numpy()
        files = write_previews(pri, imgs, Path(cache_dir) / "preview", threshold=epi_threshold)
        console.print(
            f"previews: {len(files)} PNGs in {Path(cache_dir) / 'preview'} (sheet.png is the overview)"
        )
