"""A registration session: several meta-images against one frozen reference, as `ns-register-meta` runs it.

`RegistrationJob` says what to do (its fields are ns-register-meta's flags); `run_job` does it:

1. check every input before heavy work (the trained config, each meta-image, --init / --gt files, result
   directories), one sentence per problem;
2. for each meta-image: its initial transform (identity, a JSON file, or an initialiser: `colmap`,
   `generalized`, `dense`, `auto`), the keypoint anchors or, without them, the dense start to optimise beside it where
   the settings ask (`hypotheses.dense_start`), then `register()` and the outputs (`outputs.write_outputs`);
3. print the summary table (with each result's verdict, `verdict.py`); with several meta-images, assemble
   `<output-dir>/merged/` (`merge.py`) from those whose verdict is not `failed`. `fails()` tells
   ns-register-meta which meta-images trip `--fail-on`.

An initialiser that fails for one meta-image is reported in one sentence and that meta-image gets no
result directory; the others are still registered.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal, Optional, Sequence

import numpy as np

import pycolmap
import tyro
from rich import box
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table
from rich.text import Text

from sg_nerfstudio.atomic import check_apart_from_inputs, check_output_path, output_lock
from sg_nerfstudio.errors import InputError
from sg_nerfstudio.geometry.meta_image import MetaImage, load_meta_image, radial_k1_index, sibling_models
from sg_nerfstudio.geometry.sim3 import Sim3
from sg_nerfstudio.initialisers import METHODS, Initialiser, InitialiserSettings, resolve_reference_source, rich_progress, set_colmap_verbosity
from sg_nerfstudio.initialisers.estimate import PhotoKeypoints
from sg_nerfstudio.initialisers.features import default_cache_dir as default_initialiser_cache
from sg_nerfstudio.registration.hypotheses import runs_dense_start
from sg_nerfstudio.registration.merge import MergePart, write_merged
from sg_nerfstudio.registration.metrics import PoseErrors, pose_errors
from sg_nerfstudio.registration.objectives import build_objective, check_objective_settings, prepare_photos
from sg_nerfstudio.registration.optimize import RegistrationResult, register, total_steps
from sg_nerfstudio.registration.outputs import registered_reconstruction, write_outputs
from sg_nerfstudio.registration.reference import load_reference
from sg_nerfstudio.registration.robust import check_robust_settings
from sg_nerfstudio.registration.settings import PRESETS, RegistrationSettings, check_ranges
from sg_nerfstudio.registration.verdict import SEVERITY
from sg_nerfstudio.render.threads import set_threads
from sg_nerfstudio.splat.trained import read_trainer_config, trained_run_inputs

MERGED = "merged"


class ArgumentError(InputError):
    """Command-line arguments that do not fit together."""


@dataclass
class RegistrationJob:
    """Register meta-images (COLMAP model + photos) to a trained sg-feature-splat reference model."""

    load_config: Path
    """config.yml of the trained sg-feature-splat reference model."""
    meta_image: Annotated[tuple[Path, ...], tyro.conf.UseAppendAction]
    """A meta-image directory (images/ + sparse/0 or sparse/); repeat the flag for several."""
    output_dir: Path
    """Results go to <output-dir>/<meta-image directory name>/."""
    config: Optional[str] = None
    """Registration preset: a name (paper, fast-cpu, fast-cpu-features) or a YAML file; the flags below override
    single values. Default by device: `paper` on CUDA (12000 steps); on a CPU `fast-cpu` for references trained
    with a weight-free teacher (offline, dense-sift), `fast-cpu-features` for DINOv2 ones."""
    init: Annotated[tuple[str, ...], tyro.conf.UseAppendAction] = ()
    """Initial transform meta -> reference world: 'identity' (the default), 'colmap' (photos registered into
    the reference COLMAP model, Sim(3) from their centres), 'generalized' (the meta-image as one
    generalized camera, our gDLS+++ analogue), 'dense' (no SIFT: the photos placed among the reference images by
    teacher maps, for references SIFT cannot match such as renders of a coarse model), 'auto' (colmap, then
    generalized, then dense: the first that gives a start, and it says which), or a JSON file with a 4x4 "matrix"
    (transform.json / gt_transform.json format); once for all meta-images or once per meta-image."""
    reference_colmap: Optional[Path] = None
    """For --init colmap/generalized/dense/auto: the reference's COLMAP model (default: the trained config's dataparser
    data / colmap_path)."""
    reference_images: Optional[Path] = None
    """For --init colmap/generalized/dense/auto: the reference's images (default: the dataparser's data / images_path)."""
    init_max_error: Optional[float] = None
    """For --init colmap: RANSAC inlier distance (reference world units) of the Sim(3) from camera centres;
    default 5% of the median distance of the reference cameras to their centroid."""
    init_cache_dir: Optional[Path] = None
    """Cache of SIFT features and the reference's SIFT triangulation (default: ~/.cache/sg_nerfstudio/initialisers)."""
    gt: Annotated[tuple[Path, ...], tyro.conf.UseAppendAction] = ()
    """Ground-truth transform (gt_transform.json) to report ΔR / ΔT; once per meta-image, in order."""
    settings: Annotated[RegistrationSettings, tyro.conf.arg(name="")] = field(default_factory=RegistrationSettings)
    """The registration settings, by group (--optimiser.*, --objective.*, ...); --config sets them all at once."""
    merge_reference: bool = False
    """With several meta-images: also put the reference's own COLMAP cameras and points into merged/ (read
    from --reference-colmap or the trained config's dataparser)."""
    overwrite: bool = False
    """Replace existing result directories."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """Where the reference model is loaded and rendered."""
    verbose: bool = False
    """Show COLMAP's INFO log while initialising (default: its warnings and errors only)."""
    threads: Optional[int] = None
    """CPU threads of torch and numba (default: the cores this process may use); give concurrent jobs a share each."""
    fail_on: Optional[Literal["uncertain", "failed"]] = None
    """Exit with status 2 when a meta-image's verdict is this or worse (`uncertain` also fails on `failed`); a
    meta-image whose initialisation failed counts as failed. Default: only bad inputs and no registration at all fail."""


@dataclass
class MetaOutcome:
    """What became of one meta-image: its result (None when its initialisation failed), errors with --gt, and its
    model where the registration put it (aligned/, `outputs.registered_reconstruction`)."""

    meta: MetaImage
    result: Optional[RegistrationResult] = None
    errors: Optional[dict[str, PoseErrors]] = None
    target: Optional[Path] = None
    aligned: Optional[pycolmap.Reconstruction] = None


def read_initial_transform(value: str) -> Optional[Sim3]:
    """The transform for 'identity' or a JSON file; None for an initialiser name (computed later)."""
    if value in METHODS:
        return None
    if value == "identity":
        return Sim3.identity()
    if not Path(value).is_file():
        raise ArgumentError(f"Initial transform file {value} does not exist; expected 'identity', 'colmap', 'generalized', 'dense', 'auto' or a JSON file.")
    return Sim3.read_json(Path(value), "Initial transform")


def per_meta_values(values: tuple, count: int, flag: str, allow_single: bool) -> list:
    """One value per meta-image: as given, or one given value repeated (`allow_single`)."""
    if len(values) == count:
        return list(values)
    if allow_single and len(values) == 1:
        return list(values) * count
    expected = f"1 or {count}" if allow_single else f"0 or {count}"
    raise ArgumentError(f"{flag} was given {len(values)} times for {count} meta-images; expected {expected}.")


def read_ground_truths(paths: tuple[Path, ...], count: int) -> list[Optional[Sim3]]:
    """--gt per meta-image (None for all when not given)."""
    if not paths:
        return [None] * count
    return [Sim3.read_json(p, "Ground truth") for p in per_meta_values(paths, count, "--gt", allow_single=False)]


def check_targets(job: RegistrationJob, names: list[str]) -> None:
    """Result directories are free (or --overwrite) and no meta-image name collides with merged/ or reference/."""
    check_output_path(job.output_dir)
    if len(set(names)) != len(names):
        raise ArgumentError(f"Meta-image directories must have distinct names (results go to <output-dir>/<name>), got {names}.")
    targets = [job.output_dir / name for name in names] + ([job.output_dir / MERGED] if len(names) > 1 else [])
    init_files = [Path(value) for value in job.init if value not in METHODS and value != "identity"]
    inputs = [
        *job.meta_image, *job.gt, *init_files, *trained_run_inputs(job.load_config), job.reference_colmap, job.reference_images,
        job.init_cache_dir or default_initialiser_cache(), *([Path(job.config)] if job.config and job.config not in PRESETS else []),
    ]
    for target in targets:
        check_apart_from_inputs(target, inputs)
        if target.exists() and not job.overwrite:
            raise ArgumentError(f"Result directory {target} exists; pass --overwrite to replace it.")
    if MERGED in names and len(names) > 1:
        raise ArgumentError(f"A meta-image may not be named '{MERGED}' when several are registered (that is where they are merged).")
    if job.merge_reference and "reference" in names:
        raise ArgumentError("With --merge-reference no meta-image may be named 'reference' (the reference's images are named reference/<name> in merged/).")


def run_job(job: RegistrationJob, console: Console) -> list[MetaOutcome]:
    """Register every meta-image of the job, write its outputs and (for several) merged/; see the module docstring. A
    second job writing the same --output-dir meanwhile stops at once (`atomic.output_lock`)."""
    with output_lock(job.output_dir):
        return registered_job(job, console)


def registered_job(job: RegistrationJob, console: Console) -> list[MetaOutcome]:
    """`run_job` under the output directory's lock."""
    read_trainer_config(job.load_config)  # fail fast on a wrong config, before heavy work
    check_ranges(job.settings)
    check_robust_settings(job.settings)
    check_objective_settings(job.settings)
    set_threads(job.threads)
    metas = [load_meta_image(path) for path in job.meta_image]
    check_targets(job, [meta.name for meta in metas])
    init_values = per_meta_values(job.init or ("identity",), len(metas), "--init", allow_single=True)
    inits = [read_initial_transform(v) for v in init_values]
    gts = read_ground_truths(job.gt, len(metas))
    for meta in metas:
        if meta.unlisted:
            console.print(f"[yellow]{meta.name}: {len(meta.unlisted)} files in images/ are not in the COLMAP model and are ignored: {', '.join(meta.unlisted[:5])}[/yellow]")
        others = sibling_models(meta.model_path)
        if others:
            console.print(
                f"[yellow]{meta.name}: registering {meta.model_path} only; {meta.model_path.parent} also holds "
                f"model{'s' if len(others) > 1 else ''} {', '.join(p.name for p in others)} (give each its own directory, images/ + sparse/0, to register it; "
                "sg-meta-images writes that layout).[/yellow]",
                soft_wrap=True,
            )

    reference_part = read_reference_part(job) if job.merge_reference and len(metas) > 1 else None
    initialiser = None
    if any(value in METHODS for value in init_values):
        initialiser = build_initialiser(job)
        initialiser.check_reference()
    elif job.settings.anchors.weight > 0 or job.settings.hypotheses.dense_start:
        initialiser = keypoint_initialiser(job, console)

    reference = load_reference(job.load_config, device=resolve_device(job.device))
    outcomes = []
    for meta, initial, value, gt in zip(metas, inits, init_values, gts):
        if initial is None:
            initial = compute_initial_transform(initialiser, meta, value, console)
            if initial is None:
                outcomes.append(MetaOutcome(meta))
                continue
        keypoints = anchors_for(initialiser, meta, job.settings, console)
        others = dense_start_beside(initialiser, meta, initial, job.settings, keypoints, console)
        outcomes.append(register_one(job, reference, meta, initial, gt, console, keypoints, others))
    print_summary(outcomes, console)
    if len(metas) > 1:
        write_merge(job.output_dir / MERGED, outcomes, reference_part, job.overwrite, console)
    return outcomes


def build_initialiser(job: RegistrationJob) -> Initialiser:
    """The SIFT + pycolmap initialiser of the job's reference (InputError when its source cannot be found)."""
    set_colmap_verbosity(job.verbose)
    source = resolve_reference_source(job.load_config, job.reference_colmap, job.reference_images)
    return Initialiser(source, InitialiserSettings(alignment_max_error=job.init_max_error, cache_dir=job.init_cache_dir))


def keypoint_initialiser(job: RegistrationJob, console: Console) -> Optional[Initialiser]:
    """For keypoint anchors or the dense start beside the given one, without an initialiser start: the initialiser
    when the reference's COLMAP model and images can be used, else None after one line saying that the given start
    and the dense objective run alone."""
    try:
        initialiser = build_initialiser(job)
        initialiser.check_reference()
        return initialiser
    except InputError as error:
        console.print(f"[yellow]Keypoint anchors and the dense start are off (the given start and the dense objective alone): {error}[/yellow]", soft_wrap=True)
        return None


def anchors_for(initialiser: Optional[Initialiser], meta: MetaImage, settings: RegistrationSettings, console: Console) -> list[PhotoKeypoints]:
    """The meta-image's keypoint anchors when the settings weigh them (empty otherwise or when the reference's
    SIFT cloud cannot be built, which is said in one line)."""
    if initialiser is None or settings.anchors.weight <= 0:
        return []
    try:
        with rich_progress(console) as progress:
            initialiser.progress = progress
            keypoints = initialiser.keypoints(meta)
    except InputError as error:
        console.print(f"[yellow]{meta.name}: keypoint anchors are off (the dense objective alone): {error}[/yellow]", soft_wrap=True)
        return []
    count = sum(len(k.points2D) for k in keypoints)
    console.print(f"{meta.name}: keypoint anchors from {len(keypoints)} of {len(meta.photos)} photos ({count} correspondences).")
    return keypoints


def dense_start_beside(
    initialiser: Optional[Initialiser], meta: MetaImage, initial: Sim3, settings: RegistrationSettings, keypoints: list[PhotoKeypoints], console: Console,
) -> list[tuple[str, Sim3]]:
    """[("dense", its start)] where `settings.hypotheses.dense_start` asks for it, no keypoint anchors hold the meta-image
    and the dense initialiser finds a start other than `initial`; else empty, with one line saying why where it failed."""
    if initialiser is None or not runs_dense_start(settings, bool(keypoints)):
        return []
    try:
        with rich_progress(console) as progress:
            initialiser.progress = progress
            outcome = initialiser(meta, "dense")
    except InputError as error:
        console.print(f"[yellow]{meta.name}: no dense start beside the given one: {error}[/yellow]", soft_wrap=True)
        return []
    if outcome.failure:
        console.print(f"[yellow]{meta.name}: no dense start beside the given one: {outcome.failure}[/yellow]", soft_wrap=True)
        return []
    if np.allclose(outcome.transform.matrix, initial.matrix):  # --init dense: the given start is the dense one
        return []
    console.print(f"{meta.name}: the dense start ({outcome.note}) is optimised beside the given one; the lower end wins.", soft_wrap=True)
    return [("dense", outcome.transform)]


def register_one(
    job: RegistrationJob, reference, meta: MetaImage, initial: Sim3, gt: Optional[Sim3], console: Console,
    keypoints: Optional[list[PhotoKeypoints]] = None, other_starts: Sequence[tuple[str, Sim3]] = (),
) -> MetaOutcome:
    """Register one meta-image with a progress bar and write its result directory."""
    objective = build_objective(reference, job.settings)
    photos = prepare_photos(reference, meta, job.settings, objective)
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), TimeRemainingColumn())
    with Progress(*columns, console=console, transient=True) as progress:
        total = total_steps(job.settings, anchored=bool(keypoints), other_starts=len(other_starts))
        task = progress.add_task(f"Registering {meta.name}", total=total)
        result = register(
            reference, meta, initial, job.settings, photos=photos, on_step=lambda *_: progress.advance(task), objective=objective,
            keypoints=keypoints, other_starts=other_starts,
        )
    if result.start_won not in ("given", "around"):  # a start beside the given one (e.g. the dense start)
        console.print(f"{meta.name}: the {result.start_won} start ended lower than the given one and was kept (transform.json: hypotheses).")
    rendered = result.rendered_model
    if rendered.get("voxel_pixels", 0.0) > job.settings.level_of_detail.voxel_pixels:
        console.print(
            f"{meta.name}: rendered {rendered['rendered']:,} of the reference's {rendered['gaussians']:,} Gaussians, merged at "
            f"{rendered['voxel_pixels']:g} render pixels (--level-of-detail.render-budget {job.settings.level_of_detail.render_budget:,}).", soft_wrap=True,
        )
    if result.focal_scales:
        scales = sorted(result.focal_scales.values())
        console.print(f"{meta.name}: focal lengths of {len(scales)} photos refined by x{scales[0]:.3f} to x{scales[-1]:.3f} (transform.json, aligned/).")
    if result.radial_k1:
        before = {int(p.camera.camera_id): p.camera for p in meta.photos}
        changes = sorted(value - float(before[camera_id].params[radial_k1_index(before[camera_id])]) for camera_id, value in result.radial_k1.items())
        console.print(f"{meta.name}: radial distortion k1 of {len(changes)} cameras refined by {changes[0]:+.3f} to {changes[-1]:+.3f} (transform.json, aligned/).")
    if result.pose_corrections:
        turns = sorted(c["rotation_deg"] for c in result.pose_corrections.values())
        console.print(f"{meta.name}: cameras of {len(turns)} photos moved within the meta-image by {turns[0]:.2f}° to {turns[-1]:.2f}° (transform.json, aligned/).")
    if result.scale_search:
        search = result.scale_search
        console.print(
            f"{meta.name}: the anchors of {', '.join(search['photos'])} leave the scale free (a 2% change moves them "
            f"{search['anchor_motion_px']:.2f} px, their error is {search['anchor_error_px']:.2f} px): scaled x{search['factor']:.3f} "
            "about their cameras, as the other photos prefer (transform.json: scale_search).", soft_wrap=True,
        )
    errors = None
    if gt is not None:
        errors = {"before": pose_errors(meta.poses, initial, gt), "after": pose_errors(meta.poses, result.transform, gt)}
    aligned = registered_reconstruction(meta, result)
    target = write_outputs(job.output_dir / meta.name, reference, meta, result, errors, overwrite=job.overwrite, aligned=aligned)
    return MetaOutcome(meta, result, errors, target, aligned)


def default_preset(load_config: Path, device: str) -> str:
    """The preset for a job without --config: the paper's on CUDA, a CPU preset that suits the reference's teacher
    otherwise (the paper's 12000 steps take hours on a CPU)."""
    if resolve_device(device) == "cuda":
        return "paper"
    teacher = read_trainer_config(load_config).pipeline.datamanager.teacher.name
    return "fast-cpu-features" if teacher == "dinov2" else "fast-cpu"  # weight-free teachers run on the renders


def resolve_device(device: str) -> str:
    """'auto' -> cuda when available, else cpu; 'cuda' where torch sees no CUDA device is an ArgumentError."""
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cuda" and not torch.cuda.is_available():
        raise ArgumentError("--device cuda was given, but torch sees no CUDA device on this machine; expected --device cpu or auto.")
    return device


def read_reference_part(job: RegistrationJob) -> MergePart:
    """The reference's own COLMAP model (already in the reference world frame) for --merge-reference."""
    colmap_path = resolve_reference_source(job.load_config, job.reference_colmap, job.reference_images).colmap_path
    try:
        return MergePart("reference", pycolmap.Reconstruction(str(colmap_path)))
    except Exception as error:
        raise ArgumentError(f"--merge-reference could not read the reference COLMAP model {colmap_path} ({type(error).__name__}); pass --reference-colmap.") from None


def write_merge(target: Path, outcomes: list[MetaOutcome], reference_part: Optional[MergePart], overwrite: bool, console: Console) -> None:
    """merged/: every registered meta-image whose verdict is not `failed` (and optionally the reference) in one
    COLMAP model; merge.json gives each merged one's verdict (an `uncertain` one is merged, and says so) and lists
    the others with the reason."""
    parts = [reference_part] if reference_part is not None else []
    not_merged = {}
    for outcome in outcomes:
        if outcome.result is None:
            not_merged[outcome.meta.name] = "initialisation failed"
        elif outcome.result.verdict.label == "failed":
            not_merged[outcome.meta.name] = "verdict failed: " + "; ".join(outcome.result.verdict.reasons)
        else:
            verdict = outcome.result.verdict
            parts.append(MergePart(outcome.meta.name, outcome.aligned, outcome.result.transform, verdict.label, verdict.reasons))
    if not any(part.transform is not None for part in parts):
        console.print(f"[yellow]No meta-image was registered with a verdict other than failed, so {target} is not written.[/yellow]")
        return
    write_merged(target, parts, not_merged, overwrite=overwrite)
    skipped = f"; not merged: {', '.join(not_merged)}" if not_merged else ""
    console.print(f"Merged model of {len(parts)} reconstructions in the reference frame: {target}{skipped}", soft_wrap=True)


def compute_initial_transform(initialiser: Initialiser, meta: MetaImage, method: str, console: Console) -> Optional[Sim3]:
    """The initialiser's transform, or None after printing its one-sentence failure."""
    with rich_progress(console) as progress:
        initialiser.progress = progress
        outcome = initialiser(meta, method)
    if outcome.failure:
        Console(stderr=True).print(Text(outcome.failure.rstrip(".") + "; no result is written for it.", style="red"), soft_wrap=True)
        return None
    console.print(f"{meta.name}: '{method}' initialisation from {len(outcome.agreeing_photos)} agreeing photos in {outcome.wall_time_s:.1f} s.")
    if outcome.note:
        console.print(f"[yellow]{meta.name}: {outcome.note}.[/yellow]", soft_wrap=True)
    return outcome.transform


def summary_table(outcomes: list[MetaOutcome]) -> Table:
    """One row per meta-image, readable at 80 columns: errors as before→after (with --gt), the verdict, seconds."""
    caption = "ΔR, ΔT, accurate, outlier: before→after (with --gt); verdict: without ground truth (transform.json says why)"
    table = Table(title="ns-register-meta", box=box.SIMPLE_HEAD, pad_edge=False, collapse_padding=True, caption=caption)
    for column in ("meta-image", "photos", "ΔR (°)", "ΔT", "accurate", "outlier", "verdict", "s"):
        if column == "meta-image":
            table.add_column(column, overflow="fold", min_width=10)
        else:
            table.add_column(column, justify="right", no_wrap=True)
    yes_no = {True: "yes", False: "no"}
    for outcome in outcomes:
        meta, result, errors = outcome.meta, outcome.result, outcome.errors
        if result is None:
            table.add_row(meta.name, str(len(meta.photos)), "init failed", *[""] * 5)
            continue
        if errors:
            before, after = errors["before"], errors["after"]
            cells = [f"{before.rotation_deg:.2f}→{after.rotation_deg:.2f}", f"{before.translation:.3f}→{after.translation:.3f}",
                     f"{yes_no[before.accurate()]}→{yes_no[after.accurate()]}", f"{yes_no[before.outlier()]}→{yes_no[after.outlier()]}"]
        else:
            cells = ["-"] * 4
        table.add_row(meta.name, str(len(meta.photos)), *cells, VERDICT_STYLE[result.verdict.label], f"{result.wall_time_s:.0f}")
    return table


VERDICT_STYLE = {"registered": "[green]registered[/green]", "uncertain": "[yellow]uncertain[/yellow]", "failed": "[red]failed[/red]"}


def verdict_of(outcome: MetaOutcome) -> str:
    """The outcome's verdict; an initialisation that failed counts as `failed`."""
    return outcome.result.verdict.label if outcome.result is not None else "failed"


def fails(outcomes: list[MetaOutcome], fail_on: Optional[str]) -> list[str]:
    """Names of the meta-images whose verdict is `fail_on` or worse (none without `fail_on`)."""
    if fail_on is None:
        return []
    return [outcome.meta.name for outcome in outcomes if SEVERITY[verdict_of(outcome)] >= SEVERITY[fail_on]]


def print_summary(outcomes: list[MetaOutcome], console: Console) -> None:
    console.print(summary_table(outcomes))
    for outcome in outcomes:
        if outcome.target is not None:
            console.print(f"{outcome.meta.name}: transform, aligned model and report in {outcome.target}", soft_wrap=True)
        if outcome.result is not None and outcome.result.verdict.label != "registered":
            console.print(f"{outcome.meta.name}: {outcome.result.verdict.label} ({'; '.join(outcome.result.verdict.reasons)})", soft_wrap=True)
