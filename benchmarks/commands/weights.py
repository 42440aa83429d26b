"""`wtbench weights`: Show, install or download the LPIPS weight files."""

from __future__ import annotations

from pathlib import Path

import typer


def register(app: typer.Typer) -> None:
    sub = typer.Typer(
        help="Show, install or download the LPIPS weight files.", no_args_is_help=True, add_completion=False
    )
    app.add_typer(sub, name="weights", help="Show, install or download the LPIPS weight files.")

    @sub.command("show", help="List where LPIPS weights are looked for, what is there, and its checksums.")
    def show(
        lpips_weights: Path | None = typer.Option(
            None, "--lpips-weights", help="Also look in this folder first."
        ),
    ) -> None:
        from benchmarks.evaluation import lpips_weights as lw
        from worldtree.infra.errors import UserError

        print("LPIPS weights are looked for in this order; eval uses the first folder listed:")
        for k, folder in enumerate(lw.search_folders(lpips_weights), 1):
            print(f"{k}. {folder.origin}: {folder.path}")
            for name, check in ((lw.ALEXNET_FILE, lw.check_alexnet), (lw.LIN_FILE, lw.check_lin)):
                path = folder.path / name
                if not path.is_file():
                    print(f"   {name:<26} missing")
                    continue
                try:
                    print(f"   {name:<26} ok  sha256 {check(path)[1]}")
                except UserError as e:
                    print(f"   {name:<26} BAD {e}")
        try:
            used = lw.locate(lpips_weights)
            print(f"eval uses: {used.path} ({used.origin})")
        except UserError as e:
            print(f"eval uses: no LPIPS - {e}")

    @sub.command("install", help="Check weight files in a local folder and copy them into the user cache.")
    def install(
        src: Path = typer.Option(
            ..., "--from", help="Folder holding alexnet-owt-7be5be79.pth and/or alex.pth."
        ),
        to: Path | None = typer.Option(None, "--to", help="Destination folder (default: the user cache)."),
    ) -> None:
        from benchmarks.evaluation import lpips_weights as lw

        dest = to or lw.default_folder()
        for name, digest in lw.install_from(src, dest).items():
            print(f"installed {dest / name}  sha256 {digest}")

    @sub.command("download", help="Download both weight files from their public URLs (needs internet).")
    def download(
        to: Path | None = typer.Option(None, "--to", help="Destination folder (default: the user cache)."),
        timeout: float = typer.Option(60.0, "--timeout", help="Seconds to wait for the server."),
    ) -> None:
        from benchmarks.evaluation import lpips_weights as lw

        dest = to or lw.default_folder()
        for name, digest in lw.download(dest, timeout=timeout).items():
            print(f"downloaded {dest / name}  sha256 {digest}")
