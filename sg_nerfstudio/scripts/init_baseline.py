"""`sg-init-baseline`: the initialisers alone, as the baselines of the paper's Table 1.

    sg-init-baseline --load-config outputs/.../config.yml --meta-image scene/meta/front \\
        --meta-image scene/meta/rear --output-dir baseline-colmap --init colmap \\
        --gt scene/meta/front/gt_transform.json --gt scene/meta/rear/gt_transform.json

    sg-init-baseline --reference-colmap scene/reference/colmap/sparse/0 --reference-images scene/reference/images ...

Writes, into a directory that appears complete or not at all:

    <output-dir>/<meta name>/init_transform.json   Sim(3) meta -> reference world (transform.json's format)
                                                   plus the initialiser's per-photo record
    <output-dir>/metrics.json                      per meta-image: success or the failure sentence,
                                                   with --gt ΔR / ΔT / accurate / outlier; the
                                                   failure count (Table 1's #Failures)

A meta-image the initialiser cannot align is a *failure*: listed, with no init_transform.json. The exit
status is 1 for bad inputs and when no meta-image could be initialised, else 0. Feed an
init_transform.json to `ns-register-meta --init` for the "ours (baseline init)" rows.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal, Optional

import tyro
from rich.console import Console
from rich.table import Table
from rich.text import Text

from sg_nerfstudio import cli
from sg_nerfstudio.atomic import atomic_directory, check_new_output_directory, output_lock
from sg_nerfstudio.geometry.meta_image import load_meta_image
from sg_nerfstudio.initialisers import Initialiser, InitialiserSettings, InitResult, resolve_reference_source, rich_progress, set_colmap_verbosity
from sg_nerfstudio.registration.metrics import PoseErrors, pose_errors
from sg_nerfstudio.registration.session import ArgumentError, read_ground_truths
from sg_nerfstudio.errors import cli_main
from sg_nerfstudio.splat.trained import trained_run_inputs


@dataclass
class InitBaselineArgs:
    """Initialise meta-images against a reference with SIFT + pycolmap and report the transforms."""

    meta_image: Annotated[tuple[Path, ...], tyro.conf.UseAppendAction]
    """A meta-image directory (images/ + sparse/0 or sparse/); repeat the flag for several."""
    output_dir: Path
    """Created (atomically) with <meta name>/init_transform.json and metrics.json."""
    load_config: Optional[Path] = None
    """config.yml of a trained sg-feature-splat; its dataparser names the reference COLMAP model and images."""
    reference_colmap: Optional[Path] = None
    """The reference's COLMAP model (overrides the config's)."""
    reference_images: Optional[Path] = None
    """The reference's images (overrides the config's)."""
    init: Literal["colmap", "generalized", "dense", "auto"] = "colmap"
    """'colmap': photos registered one by one, Sim(3) from their centres; 'generalized': the meta-image as one
    generalized camera (our analogue of gDLS+++); 'dense': no SIFT, the photos placed among the reference images by
    teacher maps; 'auto': colmap, generalized, then dense, the first that gives a start."""
    gt: Annotated[tuple[Path, ...], tyro.conf.UseAppendAction] = ()
    """Ground-truth transform (gt_transform.json) per meta-image, in order, to report ΔR / ΔT."""
    overwrite: bool = False
    """Replace an existing output directory."""
    initialiser: InitialiserSettings = field(default_factory=InitialiserSettings)
    verbose: bool = False
    """Show COLMAP's INFO log (default: its warnings and errors only)."""


def run(args: InitBaselineArgs, console: Console) -> list[dict]:
    """Initialise every meta-image and write the output directory, under its lock (`atomic.output_lock`)."""
    with output_lock(args.output_dir):
        return initialised(args, console)


def initialised(args: InitBaselineArgs, console: Console) -> list[dict]:
    inputs = [*args.meta_image, *args.gt, args.reference_colmap, args.reference_images, args.initialiser.resolved_cache_dir()]
    inputs += trained_run_inputs(args.load_config) if args.load_config is not None else []
    check_new_output_directory(args.output_dir, args.overwrite, inputs)
    source = resolve_reference_source(args.load_config, args.reference_colmap, args.reference_images)
    metas = [load_meta_image(path) for path in args.meta_image]
    names = [meta.name for meta in metas]
    if len(set(names)) != len(names):
        raise ArgumentError(f"Meta-image directories must have distinct names (outputs go to <output-dir>/<name>), got {names}.")
    gts = read_ground_truths(args.gt, len(metas))
    set_colmap_verbosity(args.verbose)
    initialiser = Initialiser(source, args.initialiser)
    initialiser.check_reference()

    entries = []
    with rich_progress(console) as progress:
        initialiser.progress = progress
        for meta, gt in zip(metas, gts):
            outcome = initialiser(meta, args.init)
            errors = None
            if outcome.succeeded and gt is not None:
                errors = pose_errors(meta.poses, outcome.transform, gt)
            entries.append({"meta": meta, "outcome": outcome, "errors": errors})
    write_outputs(args.output_dir, args, entries)
    print_table(entries, args.init, console)
    for entry in entries:
        if entry["outcome"].failure:
            Console(stderr=True).print(Text(entry["outcome"].failure, style="red"), soft_wrap=True)
        elif entry["outcome"].note:
            console.print(f"[yellow]{entry['meta'].name}: {entry['outcome'].note}.[/yellow]", soft_wrap=True)
    return entries


def write_outputs(target: Path, args: InitBaselineArgs, entries: list[dict]) -> None:
    with atomic_directory(target, overwrite=args.overwrite) as staging:
        for entry in entries:
            outcome: InitResult = entry["outcome"]
            if not outcome.succeeded:
                continue
            record = outcome.transform.as_record() | {"meta_image": str(entry["meta"].directory), "initialiser": outcome.as_record()}
            (staging / entry["meta"].name).mkdir()
            (staging / entry["meta"].name / "init_transform.json").write_text(json.dumps(record, indent=2))
        summary = {
            "initialiser": args.init,
            "failures": sum(not e["outcome"].succeeded for e in entries),
            "meta_images": {
                e["meta"].name: {
                    "succeeded": e["outcome"].succeeded,
                    "failure": e["outcome"].failure,
                    "wall_time_s": round(e["outcome"].wall_time_s, 3),
                    "agreeing_photos": len(e["outcome"].agreeing_photos),
                    "note": e["outcome"].note,
                    "photos": len(e["meta"].photos),
                    **({"errors": e["errors"].as_dict()} if e["errors"] is not None else {}),
                }
                for e in entries
            },
        }
        (staging / "metrics.json").write_text(json.dumps(summary, indent=2))


def print_table(entries: list[dict], method: str, console: Console) -> None:
    table = Table(title=f"sg-init-baseline --init {method}")
    for column in ("meta-image", "photos", "result", "agreeing photos", "ΔR (°)", "ΔT", "accurate", "outlier", "time (s)"):
        table.add_column(column, justify="right")
    for entry in entries:
        outcome: InitResult = entry["outcome"]
        errors: Optional[PoseErrors] = entry["errors"]
        metrics = [f"{errors.rotation_deg:.2f}", f"{errors.translation:.3f}", str(errors.accurate()), str(errors.outlier())] if errors else ["-"] * 4
        table.add_row(entry["meta"].name, str(len(entry["meta"].photos)), "ok" if outcome.succeeded else "FAILED",
                      str(len(outcome.agreeing_photos)), *metrics, f"{outcome.wall_time_s:.1f}")
    console.print(table)


def main(argv: Optional[list[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)

    def body() -> int:
        console = Console()
        args = cli.parse(InitBaselineArgs, args=argv, prog="sg-init-baseline")
        entries = run(args, console)
        console.print(f"Initial transforms and metrics.json in {args.output_dir}", soft_wrap=True)
        return 0 if any(e["outcome"].succeeded for e in entries) else 1

    return cli_main(body)


def entrypoint() -> None:
    sys.exit(main())


if __name__ == "__main__":
    entrypoint()
