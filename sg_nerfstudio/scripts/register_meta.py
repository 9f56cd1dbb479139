"""`ns-register-meta`: ground meta-images in a frozen sg-feature-splat reference model.

    ns-register-meta --load-config outputs/.../config.yml --meta-image scene/meta/front \\
        --output-dir registrations [--init identity|colmap|generalized|init.json] \\
        [--gt scene/meta/front/gt_transform.json] [--config configs/register/fast-cpu.yaml] [--steps 400 ...]

`--config` reads a YAML preset of the registration settings (configs/register/: paper.yaml, fast-cpu.yaml);
flags given after it override single settings. `--init` and `--gt` take one value per meta-image (a single
`--init` applies to all). Results go to `<output-dir>/<meta-image name>/` (see registration/outputs.py).

`--init colmap` / `--init generalized` compute the start with SIFT + pycolmap against the reference's own
COLMAP model and images (sg_nerfstudio/initialisers; by default the ones the trained config's dataparser
read, else --reference-colmap / --reference-images). When an initialiser fails for a meta-image, that is
reported in one sentence and no result directory is written for it; the other meta-images are still
registered, and the exit status is 1 only when no meta-image was registered.

Given several meta-images it also writes `<output-dir>/merged/` (registration/merge.py): one COLMAP model
with every registered meta-image in the reference frame (`--merge-reference` adds the reference's own
cameras); merge.json lists the meta-images that were not merged.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal, Optional

import numpy as np
import pycolmap
import tyro
import yaml
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table
from rich.text import Text

from sg_nerfstudio.errors import InputError
from sg_nerfstudio.initialisers import METHODS, Initialiser, InitialiserSettings, resolve_reference_source, rich_progress
from sg_nerfstudio.registration.merge import MergePart, aligned_reconstruction, write_merged
from sg_nerfstudio.registration.meta_image import load_meta_image
from sg_nerfstudio.registration.metrics import pose_errors
from sg_nerfstudio.registration.optimize import InitialisationError, RegistrationSettings, prepare_photos, register
from sg_nerfstudio.registration.outputs import write_outputs
from sg_nerfstudio.registration.reference import load_reference, read_trainer_config
from sg_nerfstudio.registration.sim3 import decompose


MERGED = "merged"


class ArgumentError(InputError):
    """Command-line arguments that do not fit together."""


@dataclass
class RegisterMetaArgs:
    """Register meta-images (COLMAP model + photos) to a trained sg-feature-splat reference model."""

    load_config: Path
    """config.yml of the trained sg-feature-splat reference model."""
    meta_image: Annotated[tuple[Path, ...], tyro.conf.UseAppendAction]
    """A meta-image directory (images/ + sparse/0 or sparse/); repeat the flag for several."""
    output_dir: Path
    """Results go to <output-dir>/<meta-image directory name>/."""
    init: Annotated[tuple[str, ...], tyro.conf.UseAppendAction] = ()
    """Initial transform meta -> reference world: 'identity' (the default), 'colmap' (photos registered into
    the reference COLMAP model, Sim(3) from their centres), 'generalized' (the meta-image as one
    generalized camera, our gDLS+++ analogue), or a JSON file with a 4x4 "matrix" (transform.json /
    gt_transform.json format); once for all meta-images or once per meta-image."""
    reference_colmap: Optional[Path] = None
    """For --init colmap/generalized: the reference's COLMAP model (default: the trained config's dataparser
    data / colmap_path)."""
    reference_images: Optional[Path] = None
    """For --init colmap/generalized: the reference's images (default: the dataparser's data / images_path)."""
    init_max_error: Optional[float] = None
    """For --init colmap: RANSAC inlier distance (reference world units) of the Sim(3) from camera centres;
    default 5% of the median distance of the reference cameras to their centroid."""
    init_cache_dir: Optional[Path] = None
    """Cache of SIFT features and the reference's SIFT triangulation (default: ~/.cache/sg_nerfstudio/initialisers)."""
    gt: Annotated[tuple[Path, ...], tyro.conf.UseAppendAction] = ()
    """Ground-truth transform (gt_transform.json) to report ΔR / ΔT; once per meta-image, in order."""
    settings: RegistrationSettings = field(default_factory=RegistrationSettings)
    merge_reference: bool = False
    """With several meta-images: also put the reference's own COLMAP cameras and points into merged/ (read
    from --reference-colmap or the trained config's dataparser)."""
    overwrite: bool = False
    """Replace existing result directories."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """Where the reference model is loaded and rendered."""


def read_initial_transform(value: str) -> Optional[np.ndarray]:
    """The matrix for 'identity' or a JSON file; None for an initialiser name (computed later)."""
    if value in METHODS:
        return None
    if value == "identity":
        return np.eye(4)
    path = Path(value)
    if not path.is_file():
        raise InitialisationError(f"Initial transform file {path} does not exist; expected 'identity', 'colmap', 'generalized' or a JSON file.")
    return read_transform_json(path, "Initial transform")


def read_transform_json(path: Path, what: str) -> np.ndarray:
    try:
        record = json.loads(Path(path).read_text())
        matrix = np.asarray(record["matrix"] if isinstance(record, dict) else record, dtype=np.float64)
    except Exception as error:
        raise InitialisationError(f"{what} {path} is not JSON with a 4x4 \"matrix\" ({type(error).__name__}).") from None
    try:
        decompose(matrix)
    except ValueError as error:
        raise InitialisationError(f"{what} {path} is not a valid similarity transform: {error}.") from None
    return matrix


def load_settings_preset(path: Path) -> RegistrationSettings:
    if not path.is_file():
        raise ArgumentError(f"Settings preset {path} does not exist.")
    values = yaml.safe_load(path.read_text()) or {}
    known = {f.name for f in dataclasses.fields(RegistrationSettings)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ArgumentError(f"Settings preset {path} has unknown keys {unknown}; expected some of {sorted(known)}.")
    return RegistrationSettings(**values)


def parse_args(argv: list[str]) -> RegisterMetaArgs:
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--config", type=Path, default=None)
    known, rest = pre.parse_known_args(argv)
    settings = load_settings_preset(known.config) if known.config else RegistrationSettings()
    return tyro.cli(
        RegisterMetaArgs,
        args=rest,
        default=RegisterMetaArgs(load_config=tyro.MISSING, meta_image=tyro.MISSING, output_dir=tyro.MISSING, settings=settings),
        prog="ns-register-meta",
        config=(tyro.conf.OmitArgPrefixes,),
    )


def per_meta_values(values: tuple, count: int, flag: str, allow_single: bool) -> list:
    if len(values) == count:
        return list(values)
    if allow_single and len(values) == 1:
        return list(values) * count
    expected = f"1 or {count}" if allow_single else f"0 or {count}"
    raise ArgumentError(f"{flag} was given {len(values)} times for {count} meta-images; expected {expected}.")


def run(args: RegisterMetaArgs, console: Console) -> list[dict]:
    read_trainer_config(args.load_config)  # fail fast on a wrong config, before heavy work
    metas = [load_meta_image(path) for path in args.meta_image]
    names = [meta.name for meta in metas]
    if len(set(names)) != len(names):
        raise ArgumentError(f"Meta-image directories must have distinct names (results go to <output-dir>/<name>), got {names}.")
    init_values = per_meta_values(args.init or ("identity",), len(metas), "--init", allow_single=True)
    inits = [read_initial_transform(v) for v in init_values]
    gts = [read_transform_json(p, "Ground truth") for p in per_meta_values(args.gt, len(metas), "--gt", allow_single=False)] if args.gt else [None] * len(metas)
    targets = [args.output_dir / meta.name for meta in metas] + ([args.output_dir / MERGED] if len(metas) > 1 else [])
    for target in targets:
        if target.exists() and not args.overwrite:
            raise ArgumentError(f"Result directory {target} exists; pass --overwrite to replace it.")
    if MERGED in names and len(metas) > 1:
        raise ArgumentError(f"A meta-image may not be named '{MERGED}' when several are registered (that is where they are merged).")
    if args.merge_reference and "reference" in names:
        raise ArgumentError("With --merge-reference no meta-image may be named 'reference' (the reference's images are named reference/<name> in merged/).")
    for meta in metas:
        if meta.unlisted:
            console.print(f"[yellow]{meta.name}: {len(meta.unlisted)} files in images/ are not in the COLMAP model and are ignored: {', '.join(meta.unlisted[:5])}[/yellow]")

    reference_part = read_reference_part(args) if args.merge_reference and len(metas) > 1 else None
    initialiser = None
    if any(value in METHODS for value in init_values):
        source = resolve_reference_source(args.load_config, args.reference_colmap, args.reference_images)
        initialiser = Initialiser(source, InitialiserSettings(alignment_max_error=args.init_max_error, cache_dir=args.init_cache_dir))
        initialiser.check_reference()

    device = "cuda" if args.device == "auto" and _cuda() else ("cpu" if args.device == "auto" else args.device)
    reference = load_reference(args.load_config, device=device)
    summaries = []
    for meta, initial, value, gt in zip(metas, inits, init_values, gts):
        if initial is None:
            initial = compute_initial_transform(initialiser, meta, value, console)
            if initial is None:
                summaries.append({"meta": meta, "result": None, "errors": None, "target": None})
                continue
        photos = prepare_photos(reference, meta, args.settings)
        with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), TimeRemainingColumn(), console=console, transient=True) as progress:
            task = progress.add_task(f"Registering {meta.name}", total=args.settings.steps)
            result = register(reference, meta, initial, args.settings, photos=photos, on_step=lambda *_: progress.advance(task))
        errors = None
        if gt is not None:
            poses = [p.cam_from_world for p in meta.photos]
            errors = {"before": pose_errors(poses, initial, gt), "after": pose_errors(poses, result.transform, gt)}
        target = write_outputs(args.output_dir / meta.name, reference, meta, result, errors, overwrite=args.overwrite)
        summaries.append({"meta": meta, "result": result, "errors": errors, "target": target})
    print_summary(summaries, console)
    if len(metas) > 1:
        write_merge(args.output_dir / MERGED, summaries, reference_part, args.overwrite, console)
    return summaries


def read_reference_part(args: RegisterMetaArgs) -> MergePart:
    """The reference's own COLMAP model (already in the reference world frame) for --merge-reference."""
    colmap_path = resolve_reference_source(args.load_config, args.reference_colmap, args.reference_images).colmap_path
    try:
        return MergePart("reference", pycolmap.Reconstruction(str(colmap_path)))
    except Exception as error:
        raise ArgumentError(f"--merge-reference could not read the reference COLMAP model {colmap_path} ({type(error).__name__}); pass --reference-colmap.") from None


def write_merge(target: Path, summaries: list[dict], reference_part: Optional[MergePart], overwrite: bool, console: Console) -> None:
    """merged/: every registered meta-image (and optionally the reference) in one COLMAP model."""
    parts = [reference_part] if reference_part is not None else []
    not_merged = {}
    for entry in summaries:
        meta, result = entry["meta"], entry["result"]
        if result is None:
            not_merged[meta.name] = "initialisation failed"
        else:
            parts.append(MergePart(meta.name, aligned_reconstruction(meta.reconstruction, result.transform), result.transform))
    if not any(part.transform is not None for part in parts):
        console.print(f"[yellow]No meta-image was registered, so {target} is not written.[/yellow]")
        return
    write_merged(target, parts, not_merged, overwrite=overwrite)
    skipped = f"; not merged: {', '.join(not_merged)}" if not_merged else ""
    console.print(f"Merged model of {len(parts)} reconstructions in the reference frame: {target}{skipped}", soft_wrap=True)


def compute_initial_transform(initialiser: Initialiser, meta, method: str, console: Console) -> Optional[np.ndarray]:
    """The initialiser's transform, or None after printing its one-sentence failure."""
    with rich_progress(console) as progress:
        initialiser.progress = progress
        outcome = initialiser(meta, method)
    if outcome.failure:
        Console(stderr=True).print(Text(outcome.failure.rstrip(".") + "; no result is written for it.", style="red"), soft_wrap=True)
        return None
    console.print(f"{meta.name}: '{method}' initialisation from {len(outcome.agreeing_photos)} agreeing photos in {outcome.wall_time_s:.1f} s.")
    return outcome.transform


def print_summary(summaries: list[dict], console: Console) -> None:
    table = Table(title="ns-register-meta")
    for column in ("meta-image", "photos", "ΔR before (°)", "ΔT before", "ΔR after (°)", "ΔT after", "accurate", "outlier", "trimmed loss", "time (s)"):
        table.add_column(column, justify="right")
    for entry in summaries:
        meta, result, errors = entry["meta"], entry["result"], entry["errors"]
        if result is None:
            table.add_row(meta.name, str(len(meta.photos)), "initialisation failed", *[""] * 7)
            continue
        if errors:
            before, after = errors["before"], errors["after"]
            cells = [f"{before.rotation_deg:.2f}", f"{before.translation:.3f}", f"{after.rotation_deg:.2f}", f"{after.translation:.3f}",
                     f"{before.accurate()} -> {after.accurate()}", f"{before.outlier()} -> {after.outlier()}"]
        else:
            cells = ["-"] * 6
        table.add_row(meta.name, str(len(meta.photos)), *cells, f"{result.final_trimmed_loss:.4f}", f"{result.wall_time_s:.1f}")
    console.print(table)
    for entry in summaries:
        if entry["target"] is not None:
            console.print(f"{entry['meta'].name}: transform, aligned model and report in {entry['target']}", soft_wrap=True)


def _cuda() -> bool:
    import torch

    return torch.cuda.is_available()


def main(argv: Optional[list[str]] = None) -> int:
    console = Console()
    try:
        args = parse_args(list(sys.argv[1:] if argv is None else argv))
        summaries = run(args, console)
    except (InputError, FloatingPointError) as error:
        Console(stderr=True).print(Text(str(error), style="red"), soft_wrap=True)
        return 1
    return 0 if any(entry["result"] is not None for entry in summaries) else 1


def entrypoint() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
