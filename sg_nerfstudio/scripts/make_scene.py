"""`sg-make-scene`: generate a synthetic landmark scene with exact ground truth.

    sg-make-scene --preset tiny --output demo_scene
    sg-make-scene --preset default --output scenes/cathedral --seed 3 --occluder-rate 0.5
    sg-make-scene --preset benchmark --output bench            # a suite: bench/<scene>/ for each scene
    sg-make-scene --preset gap --output scenes/gap             # the paper's setting: a Google-Earth-like reference
    sg-make-scene --preset gap-benchmark --output gap-bench    # the benchmark's landmarks in that setting
    sg-make-scene --preset gap-benchmark --draw 1 --output gap-bench-1   # another draw of them
    sg-make-scene --from-photos photos/ --cameras cameras/ --output real/fountain   # from real photos
    sg-make-scene --from-photos photos/ --scene.reference-kind coarse-model --output gap-real/sceaux   # the paper's setting

`--preset` picks the starting settings (see `sg_nerfstudio.synthetic.PRESETS`); every other flag
overrides one of them (`sg-make-scene --preset tiny --help` lists them with the preset's values).
Every scene holds its photo/render pairs at the true pose (`<scene>/pairs/`, `sg-bench teacher`'s layout); the
builder prints their SIFT share and teacher identifiability beside the paper's own pairs' (bench/gap.py).
A suite preset (`sg_nerfstudio.synthetic.generator.SUITES`: `benchmark`, `gap-benchmark`, `tiny-benchmark`) writes several
scenes into `<output>/<scene name>/` plus `<output>/benchmark.json` naming them, the layout `sg-bench`
reads; it takes only --output, --overwrite and --draw N (another draw of the same landmarks: every scene's seed + N).
`--from-photos PHOTOS` builds a scene from real photographs instead (sg_nerfstudio/photos/scene.py: the
reference from part of the photos with a pseudo-synthetic look, meta-images from the others, each with its
own SfM, ground truth from --cameras (Strecha `.camera` files or a COLMAP model) or SfM on all photos).
With `--scene.reference-kind coarse-model` the reference images are renders of a coarse model of those photos
instead, the paper's setting (photos/coarse_reference.py); the scene then holds its photo/render pairs and the
builder prints their gap as for the gap presets.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Optional

import tyro
from rich.console import Console
from rich.text import Text
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from sg_nerfstudio import cli
from sg_nerfstudio.bench.gap import gap_sentence, measure_gap, pool
from sg_nerfstudio.atomic import atomic_directory, check_new_output_directory
from sg_nerfstudio.initialisers import set_colmap_verbosity
from sg_nerfstudio.photos.scene import RealSceneSettings, build_real_scene
from sg_nerfstudio.errors import cli_main
from sg_nerfstudio.synthetic import PRESETS, SceneConfig, generate_scene
from sg_nerfstudio.synthetic.generator import SUITES, SceneGenerationError


@dataclass
class MakeSceneArgs:
    """Generate a synthetic landmark scene (reference capture + meta-images) with ground truth."""

    output: Path
    """Directory to create; refused if it exists unless --overwrite."""
    scene: SceneConfig
    overwrite: bool = False
    """Replace an existing output directory."""


@dataclass
class SuiteArgs:
    """Generate a benchmark suite: several synthetic scenes in one directory (the layout sg-bench reads)."""

    output: Path
    """Directory to create (holding <scene>/ per scene and benchmark.json); refused if it exists unless --overwrite."""
    draw: int = 0
    """Another draw of the suite: added to every scene's seed, so the photos' and reference cameras, occluders, lighting
    and the landmarks' Gaussians change while each landmark's shape and palette stay (0: the suite as published)."""
    overwrite: bool = False


@dataclass
class FromPhotosArgs:
    """Build a benchmark scene from real photographs (see sg_nerfstudio/photos/scene.py)."""

    from_photos: Path
    """Folder of JPEG / PNG photos of one landmark (read only)."""
    output: Path
    """Scene directory to create (put it inside a benchmark directory for sg-bench); refused if it exists unless --overwrite."""
    cameras: Optional[Path] = None
    """Ground-truth cameras: a folder of Strecha `<photo>.camera` files or a COLMAP model; default: SfM on all photos."""
    scene: RealSceneSettings = RealSceneSettings()
    overwrite: bool = False
    verbose: bool = False
    """Show COLMAP's INFO log."""


def _truths_differ(meta: dict) -> str:
    """How far the meta-image's point-based ground truth is from the camera-based one (`photos.scene.point_truth`)."""
    if meta.get("point_truth_delta_R_deg") is None:
        return "no point-based truth"
    return f"point-based truth {meta['point_truth_delta_R_deg']:.2f} deg / {meta['point_truth_delta_T']:.3f} from it"


def make_from_photos(args: FromPhotosArgs, console: Console) -> int:
    set_colmap_verbosity(args.verbose)
    with console.status("building the scene") as status:
        manifest = build_real_scene(
            args.from_photos, args.output, args.scene, args.cameras, args.overwrite, lambda text: status.update(text), measure_pairs=measure_gap,
        )
    written = [m for m in manifest["meta_images"] if m["written"]]
    reference = manifest["reference"]
    what = "photos" if reference["kind"] == "filtered-photos" else (
        f"renders of a coarse model ({reference['coarse_model']['gaussians']} Gaussians, trained in {reference['coarse_model']['train_s']:.0f} s)"
    )
    console.print(
        f"Wrote {args.output}: reference of {len(reference['images'])} {what} ({reference['n_points3D']} "
        f"triangulated points), meta-images " + ", ".join(
            f"{m['name']} ({m['n_photos']} photos, ground-truth residual <= {m['gt_residual_rotation_deg_max']:.2f} deg, "
            f"{_truths_differ(m)})" for m in written
        ) + f"; solution: {manifest['solution']}; {manifest['wall_time_s']} s.",
        soft_wrap=True, markup=False,
    )
    for meta in manifest["meta_images"]:
        if not meta["written"]:
            console.print(f"Meta-image {meta['name']} was left out: its own SfM formed no model ({meta['why']}).", soft_wrap=True, markup=False)
    if manifest["left_out"]:
        console.print(f"Photos the solution could not place (left out): {', '.join(manifest['left_out'])}.", soft_wrap=True, markup=False)
    if reference["kind"] == "coarse-model":
        console.print(gap_sentence(manifest["gap"]), soft_wrap=True, markup=False)
    return 0


def make_suite(name: str, args: SuiteArgs, console: Console) -> int:
    """Write every scene of the suite `name` into args.output, atomically as a whole."""
    check_new_output_directory(args.output, args.overwrite)
    if args.draw < 0:
        raise SceneGenerationError(f"--draw must be 0 or more, got {args.draw}.")
    manifest, gaps = {"suite": name, "draw": args.draw, "scenes": []}, {}
    with atomic_directory(args.output, overwrite=args.overwrite) as staging, scene_progress(console) as progress:
        for scene_name, config in SUITES[name].items():
            config = replace(config, seed=config.seed + args.draw)
            scene = generate_scene(config, staging / scene_name, progress=progress, measure_pairs=partial(measure_gap, progress=progress))
            manifest["scenes"].append({"name": scene_name, "meta_images": [m["name"] for m in scene["meta_images"]]})
            console.print(f"{scene_name}: " + ", ".join(f"{m['name']} ({m['n_photos']} photos)" for m in scene["meta_images"])
                          + f"; {gap_sentence(scene['gap'])}", soft_wrap=True, markup=False)
            gaps[scene_name] = scene["gap"]
        manifest["gap"] = pool(gaps)
        (staging / "benchmark.json").write_text(json.dumps(manifest, indent=2))
    console.print(f"Wrote the '{name}' suite of {len(manifest['scenes'])} scenes to {args.output}; all its photos: "
                  f"{gap_sentence(manifest['gap'])}", soft_wrap=True, markup=False)
    return 0


def scene_progress(console: Console) -> Progress:
    return Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), console=console, transient=True)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--preset", default="default")
    known, rest = pre.parse_known_args(argv)
    console = Console(stderr=True)
    if any(arg == "--from-photos" or arg.startswith("--from-photos=") for arg in argv):
        photo_args = cli.parse(FromPhotosArgs, args=argv, prog="sg-make-scene --from-photos")
        return cli_main(lambda: make_from_photos(photo_args, console))
    if known.preset in SUITES:
        suite_args = cli.parse(SuiteArgs, args=rest, prog=f"sg-make-scene --preset {known.preset}")
        return cli_main(lambda: make_suite(known.preset, suite_args, console))
    if known.preset not in PRESETS:
        names = ", ".join([*PRESETS, *SUITES])
        console.print(Text(f"Unknown --preset {known.preset!r}; expected one of: {names}.", style="red"), soft_wrap=True)
        return 2
    args = cli.parse(
        MakeSceneArgs,
        args=rest,
        default=MakeSceneArgs(output=Path("scene"), scene=PRESETS[known.preset]),
        prog=f"sg-make-scene --preset {known.preset}",
        config=(tyro.conf.OmitArgPrefixes,),
    )
    return cli_main(lambda: make_scene(args, console))


def make_scene(args: MakeSceneArgs, console: Console) -> int:
    with scene_progress(console) as progress:
        manifest = generate_scene(args.scene, args.output, overwrite=args.overwrite, progress=progress, measure_pairs=partial(measure_gap, progress=progress))
    metas = ", ".join(f"{m['name']} ({m['n_photos']} photos)" for m in manifest["meta_images"])
    console.print(
        f"Wrote {args.output}: reference capture of {manifest['reference']['n_images']} views, "
        f"meta-images {metas}, {manifest['reference']['n_points3D']} reference SfM points, in {manifest['wall_time_s']} s; "
        + gap_sentence(manifest["gap"]),
        soft_wrap=True,
        markup=False,
    )
    return 0


def entrypoint() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
