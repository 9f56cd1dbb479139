"""`sg-make-scene`: generate a synthetic landmark scene with exact ground truth.

    sg-make-scene --preset tiny --output demo_scene
    sg-make-scene --preset default --output scenes/cathedral --seed 3 --occluder-rate 0.5

`--preset` picks the starting settings (see `sg_nerfstudio.synthetic.PRESETS`); every other flag
overrides one of them (`sg-make-scene --preset tiny --help` lists them with the preset's values).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import tyro
from rich.console import Console
from rich.text import Text
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from sg_nerfstudio.synthetic import PRESETS, SceneConfig, SceneGenerationError, generate_scene


@dataclass
class MakeSceneArgs:
    """Generate a synthetic landmark scene (reference capture + meta-images) with ground truth."""

    output: Path
    """Directory to create; refused if it exists unless --overwrite."""
    scene: SceneConfig
    overwrite: bool = False
    """Replace an existing output directory."""


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--preset", default="default")
    known, rest = pre.parse_known_args(argv)
    console = Console(stderr=True)
    if known.preset not in PRESETS:
        console.print(Text(f"Unknown --preset {known.preset!r}; expected one of: {', '.join(PRESETS)}.", style="red"), soft_wrap=True)
        return 2
    args = tyro.cli(
        MakeSceneArgs,
        args=rest,
        default=MakeSceneArgs(output=Path("scene"), scene=PRESETS[known.preset]),
        prog=f"sg-make-scene --preset {known.preset}",
        config=(tyro.conf.OmitArgPrefixes,),
    )
    try:
        with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), console=console, transient=True) as progress:
            manifest = generate_scene(args.scene, args.output, overwrite=args.overwrite, progress=progress)
    except SceneGenerationError as error:
        console.print(Text(str(error), style="red"), soft_wrap=True)
        return 1
    metas = ", ".join(f"{m['name']} ({m['n_photos']} photos)" for m in manifest["meta_images"])
    console.print(
        f"Wrote {args.output}: reference capture of {manifest['reference']['n_images']} views, "
        f"meta-images {metas}, {manifest['n_gaussians']} Gaussians, in {manifest['wall_time_s']} s.",
        soft_wrap=True,
        markup=False,
    )
    return 0


def entrypoint() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
