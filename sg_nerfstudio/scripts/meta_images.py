"""`sg-meta-images`: a folder of photos of one landmark -> meta-images (pycolmap SfM, every model kept).

    sg-meta-images photos/ --output metas/
    ns-register-meta --load-config ... --meta-image metas/meta-00 --meta-image metas/meta-01 --init colmap

Reads JPEG / PNG photos (mixed sizes, EXIF orientation applied, grey or colour), caps their long side at
--max-size, runs SIFT, matching (exhaustive up to --exhaustive-limit photos, retrieval-based pairs above)
and incremental mapping, and writes each model of at least 3 photos as `<output>/meta-NN/` (images/ +
sparse/0). Prints one table of the models and one of the photos no model holds, with the reason. See
sg_nerfstudio/photos/meta_images.py for the layout.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Optional

import tyro
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from sg_nerfstudio import cli
from sg_nerfstudio.initialisers import set_colmap_verbosity
from sg_nerfstudio.photos.meta_images import build_meta_images
from sg_nerfstudio.photos.collection import PhotoFolderError, files_not_read
from sg_nerfstudio.photos.sfm import SfmSettings
from sg_nerfstudio.render.threads import available_cores, check_thread_count
from sg_nerfstudio.errors import cli_main


@dataclass
class MetaImagesArgs:
    """Reconstruct a photo folder with pycolmap and write every model of >= 3 photos as a meta-image."""

    photos: Annotated[Path, tyro.conf.Positional]
    """Folder of JPEG / PNG photos (read only)."""
    output: Path
    """Directory to create: <output>/meta-NN/ per model, meta_images.json; refused if it exists unless --overwrite, and
    always where it is the photo folder or a folder above it (--overwrite would replace the photos)."""
    max_size: int = 1024
    """Working resolution: long side of the photos SfM (and later registration) sees, in pixels (0: as they are)."""
    exhaustive_limit: int = 60
    """Match exhaustively up to this many photos; above, each photo with its most similar ones."""
    retrieval_neighbours: int = 20
    """Above the limit: photos each photo is matched with."""
    camera_model: str = "SIMPLE_RADIAL"
    """COLMAP camera model, one camera per photo. Models of a few photos under RADIAL or OPENCV (more lens terms than
    k1) formed less often and were broken more often than under SIMPLE_RADIAL (photos/sfm.py, SfmSettings)."""
    threads: Optional[int] = None
    """pycolmap threads (default: the cores this process may use)."""
    seed: int = 0
    overwrite: bool = False
    verbose: bool = False
    """Show COLMAP's INFO log (default: warnings and errors only)."""


def run(args: MetaImagesArgs, console: Console) -> int:
    if args.max_size < 0:
        raise PhotoFolderError(f"--max-size must be 0 (photos as they are) or a long side in pixels, got {args.max_size}.")
    check_thread_count(args.threads)
    set_colmap_verbosity(args.verbose)
    settings = SfmSettings(
        camera_model=args.camera_model, exhaustive_limit=args.exhaustive_limit, retrieval_neighbours=args.retrieval_neighbours,
        threads=args.threads or available_cores(), seed=args.seed,
    )
    progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), console=console, transient=True)
    with progress:
        photos_task = progress.add_task("reading photos", total=None)
        stage_task = None

        def stage(description: str) -> None:
            nonlocal stage_task
            if stage_task is not None:
                progress.update(stage_task, completed=1)
            stage_task = progress.add_task(description, total=1)

        summaries, result = build_meta_images(
            args.photos, args.output, args.max_size, settings, args.overwrite, stage, lambda: progress.advance(photos_task),
        )
    table = Table(title=f"{len(summaries)} meta-image(s) in {args.output} ({result.pairing} matching)")
    for column in ("meta-image", "photos", "points", "reproj. px", "track len."):
        table.add_column(column, justify="left" if column == "meta-image" else "right")
    for s in summaries:
        table.add_row(s.name, str(s.photos), str(s.points), f"{s.reprojection_error_px:.2f}", f"{s.mean_track_length:.1f}")
    console.print(table)
    missing = result.unregistered()
    if missing:
        left_out = Table(title=f"{len(missing)} photo(s) in no meta-image")
        left_out.add_column("photo")
        left_out.add_column("why", overflow="fold")
        for name, reason in missing:
            left_out.add_row(name, reason)
        console.print(left_out)
    not_read = files_not_read(args.photos)
    if not_read:
        console.print(
            f"[yellow]{len(not_read)} file(s) in {args.photos} are not JPEG or PNG and were not read: {', '.join(not_read[:5])}"
            + (" ..." if len(not_read) > 5 else "") + " (convert photos among them to JPEG to include them).[/yellow]",
            soft_wrap=True,
        )
    return 0


def main(argv: Optional[list[str]] = None) -> int:
    args = cli.parse(MetaImagesArgs, args=argv, prog="sg-meta-images")
    console = Console(stderr=True)
    return cli_main(lambda: run(args, console))


def entrypoint() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
