"""`wtbench view`: look at a finished run in the browser (free camera, frusta, time slider, render modes)."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    @app.command(
        "view",
        help=(
            "Serve an interactive viewer of a finished run on this machine: free camera, the training and test "
            "cameras as frusta (click one to look through it), a time slider with play/pause, render modes "
            "colour, depth, dynamic part and (WorldTree) tree node. Rendered by the project's rasterizer, on "
            "CUDA when present. Ctrl-C stops it. Guide: docs/viewer.md."
        ),
    )
    def _cmd(
        run_dir: Path = typer.Argument(
            ..., help="A run folder written by `wtbench run` (RUNS/SCENE/METHOD/TAG)."
        ),
        port: int = typer.Option(8080, "--port", help="Port to serve on (0: any free port)."),
        host: str = typer.Option(
            "127.0.0.1",
            "--host",
            help="Address to serve on; the default is this machine only (use SSH port forwarding from elsewhere).",
        ),
        device: str = typer.Option("auto", "--device", help="auto (CUDA when present), cpu, cuda or cuda:N."),
        max_size: int | None = typer.Option(
            None,
            "--max-size",
            min=16,
            help="Longest side of a still image, pixels (default: the run's image size); previews while moving "
            "are 4 times smaller per side.",
        ),
        fps: float = typer.Option(10.0, "--fps", min=0.5, max=60.0, help="Frames per second when playing."),
    ) -> None:
        import signal
        import sys
        import threading

        from benchmarks.viewer.server import check_can_serve
        from benchmarks.viewer.source import open_run

        check_can_serve(host, port)  # before loading the model: a busy port is said at once
        print(f"loading {run_dir} ...", flush=True)
        try:
            source = open_run(run_dir, device)
        except KeyboardInterrupt:  # stopping is the normal end of a viewer, also while it loads
            print("viewer stopped")
            return

        from benchmarks.viewer.server import Viewer

        viewer = Viewer(source, host=host, port=port, max_size=max_size, fps=fps)
        # Ctrl-C (SIGINT) and SIGTERM end the wait, even where SIGINT was ignored (a shell's background job).
        # Installed before the address is printed: whoever reads it may signal at once.
        stop = threading.Event()
        old = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
        for sig in old:
            signal.signal(sig, lambda *_: stop.set())
        print(f"viewer of {source.title} at {viewer.url} (rendering on {source.device}); Ctrl-C to stop")
        if host not in ("127.0.0.1", "localhost", "::1"):
            print(
                f"note: --host {host} serves to other machines too; the viewer has no password",
                file=sys.stderr,
            )
        try:
            while not stop.wait(1.0):  # the server and render threads do the work
                pass
        finally:
            for sig, handler in old.items():
                signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
            viewer.stop()
        print("viewer stopped")
