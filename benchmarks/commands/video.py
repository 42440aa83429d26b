"""`wtbench video`: an mp4 of a run's test-view renders next to the ground truth."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command("video", help="Write an mp4 of a run's test-view renders next to the ground truth.")
    def _cmd(
        run_dir: Path = typer.Argument(..., help="A run folder written by `wtbench run`."),
        out: Path | None = typer.Option(
            None, "--out", "-o", help="mp4 to write (default RUN_DIR/test_view.mp4)."
        ),
        fps: float = typer.Option(10.0, "--fps", help="Frames per second."),
    ) -> None:
        from benchmarks.reporting.video import compose_frames, write_video
        from worldtree.infra.output_paths import check_output_file

        check_output_file(out or run_dir / "test_view.mp4", "-o")
        frames, _ = compose_frames(run_dir)
        path = write_video(frames, out or run_dir / "test_view.mp4", fps)
        print(f"wrote {path} ({len(frames)} frames)")
