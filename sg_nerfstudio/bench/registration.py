"""Registration accuracy, robustness ablations and speed on synthetic scenes (CPU, offline teacher).

    python -m sg_nerfstudio.bench.registration --load-config <sg-feature-splat config.yml> \\
        --scene <sg-make-scene dir the model was trained on> [--trials 20] [--ablation-trials 4]

The reference model must have been trained on `<scene>/reference` (e.g. by
`python -m sg_nerfstudio.bench.feature_splat`). Variants of the scene with the same seed share the
reference capture exactly (the generator draws the reference first), so the benchmark builds them next to
it without retraining:

1. accuracy: `--trials` seeded starts, each the ground truth perturbed by 5°, 0.1 scene units and 10% scale
   in random directions (about the cameras' centroid), alternating meta-images; success = ΔR < 1° and ΔT < 0.05;
2. ablations: a variant whose meta-images have 30% heavily occluded photos (occluders over 40-60% of the
   frame) and strong appearance change; rows full, photometric, l2, none, outlier-lts, fixed-lts, irls; columns ΔR, ΔT,
   MTA, O% over `--ablation-trials` starts per meta-image (`--ablation-start`: their noise, default as in 1.);
3. speed: a 20-photo meta-image against the model pruned to its 20k most opaque Gaussians, fast preset, from
   one 5° start, registered twice: as `ns-register-meta` registers it (with the keypoint anchors of the SIFT
   initialiser of the run's own reference; their extraction and matching timed apart, as they are computed once per
   meta-image for every start) and with the dense objective alone (what runs where SIFT finds no correspondence):
   wall time, steps per second, and the split between render, loss and backward.
"""

from __future__ import annotations

import dataclasses
import json
import statistics
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from rich.console import Console
from rich.table import Table

from sg_nerfstudio import cli
from sg_nerfstudio.errors import cli_main
from sg_nerfstudio.render.threads import set_threads
from sg_nerfstudio.bench.runs import ABLATIONS, PERTURBED_START
from sg_nerfstudio.geometry.meta_image import MetaImage, load_meta_image
from sg_nerfstudio.geometry.sim3 import Sim3, perturbed
from sg_nerfstudio.initialisers.estimate import PhotoKeypoints
from sg_nerfstudio.initialisers.pipeline import reference_keypoints
from sg_nerfstudio.registration.metrics import pose_errors
from sg_nerfstudio.registration.objectives import prepare_photos
from sg_nerfstudio.registration.optimize import register
from sg_nerfstudio.registration.reference import ReferenceModel, load_reference
from sg_nerfstudio.registration.settings import RegistrationSettings, load_preset
from sg_nerfstudio.synthetic import generate_scene
from sg_nerfstudio.synthetic.generator import read_scene_config

ACCURACY_START = PERTURBED_START
"""Start noise of the accuracy trials: 5° rotation, 0.1 scene units translation, 10% scale."""


@dataclass
class Args:
    load_config: Path
    scene: Path
    """The sg-make-scene directory whose reference capture the model was trained on."""
    config: str = "fast-cpu"
    """Registration preset: a name (paper, fast-cpu, fast-cpu-features) or a YAML file."""
    trials: int = 20
    ablation_trials: int = 4
    """Starts per meta-image and ablation row."""
    ablation_rows: tuple[str, ...] = tuple(ABLATIONS)
    """Ablation rows to run (e.g. `full none` for the trimming comparison alone)."""
    ablation_start: tuple[float, float, float] = ACCURACY_START
    """Noise of the ablation starts: rotation (degrees), translation (scene units), scale (fraction)."""
    skip: tuple[str, ...] = ()
    """Parts to skip: accuracy, ablations, speed."""
    output: Path = Path("benchmark_registration.json")
    threads: Optional[int] = None


def scene_variant(scene: Path, name: str, **changes) -> Path:
    """The scene regenerated with the same seed and reference capture but other meta-image settings."""
    config = read_scene_config(scene)
    target = scene.parent / f"{scene.name}-{name}"
    if not target.exists():
        generate_scene(replace(config, **changes), target)
    return target


def trial(
    reference: ReferenceModel, meta: MetaImage, truth: Sim3, seed: int, settings: RegistrationSettings,
    photos=None, start_noise: tuple[float, float, float] = ACCURACY_START, keypoints: Optional[list[PhotoKeypoints]] = None,
) -> dict:
    """One registration from the truth perturbed by `start_noise` (seeded); with `keypoints` (the anchors), as
    `ns-register-meta` registers, else the dense objective alone."""
    start = perturbed(truth, meta.centres, np.random.default_rng(seed), *start_noise)
    result = register(reference, meta, start, settings.changed(seed=seed), photos=photos, keypoints=keypoints)
    poses = meta.poses
    before, after = pose_errors(poses, start, truth), pose_errors(poses, result.transform, truth)
    return {
        "meta": meta.name, "seed": seed, "dR_before": before.rotation_deg, "dT_before": before.translation,
        "dR": after.rotation_deg, "dT": after.translation, "accurate": after.accurate(), "outlier": after.outlier(),
        "time_s": result.wall_time_s, "timings": result.timings, "steps": result.steps, "verdict": result.verdict.label,
    }


def load_metas(scene: Path) -> list[tuple[MetaImage, Sim3]]:
    return [
        (load_meta_image(directory), Sim3.read_json(directory / "gt_transform.json", "Ground truth"))
        for directory in sorted((scene / "meta").iterdir())
    ]


def accuracy(reference, scene, settings, trials, console) -> dict:
    metas = load_metas(scene)
    cache = {}
    rows = []
    for seed in range(trials):
        meta, truth = metas[seed % len(metas)]
        if meta.name not in cache:
            cache[meta.name] = prepare_photos(reference, meta, settings)
        rows.append(trial(reference, meta, truth, seed, settings, cache[meta.name]))
        r = rows[-1]
        console.print(f"trial {seed} ({r['meta']}): ΔR {r['dR_before']:.2f}° -> {r['dR']:.3f}°, ΔT {r['dT_before']:.3f} -> {r['dT']:.4f}, {r['time_s']:.1f} s")
    success = [r["dR"] < 1.0 and r["dT"] < 0.05 for r in rows]
    table = Table(title=f"Accuracy: {trials} starts at 5° / 0.1 / 10% (fast preset)")
    for column in ("trials", "success (ΔR<1°, ΔT<0.05)", "median ΔR after", "median ΔT after", "worst ΔR", "worst ΔT", "mean time (s)"):
        table.add_column(column, justify="right")
    table.add_row(
        str(trials), f"{sum(success)}/{trials} ({100 * sum(success) / trials:.0f}%)",
        f"{statistics.median(r['dR'] for r in rows):.3f}", f"{statistics.median(r['dT'] for r in rows):.4f}",
        f"{max(r['dR'] for r in rows):.3f}", f"{max(r['dT'] for r in rows):.4f}", f"{statistics.mean(r['time_s'] for r in rows):.1f}",
    )
    console.print(table)
    return {"rows": rows, "success_rate": sum(success) / trials}


def ablations(reference, scene, settings, trials, rows_to_run, start_noise, console) -> dict:
    metas = load_metas(scene)
    rotation, translation, scale = start_noise
    table = Table(title=f"Ablations on {scene.name} ({trials} starts per meta-image at {rotation:g}° / {translation:g} / {100 * scale:g}%, 30% heavily occluded photos)")
    for column in ("method", "ΔR (°)", "ΔT", "MTA (%)", "O (%)", "runs"):
        table.add_column(column, justify="right")
    results = {}
    for name in rows_to_run:
        variant = settings.changed(**ABLATIONS[name])
        rows = []
        for meta, truth in metas:
            photos = prepare_photos(reference, meta, variant)
            rows += [trial(reference, meta, truth, seed, variant, photos, start_noise) for seed in range(100, 100 + trials)]
        results[name] = rows
        table.add_row(
            name, f"{statistics.mean(r['dR'] for r in rows):.3f}", f"{statistics.mean(r['dT'] for r in rows):.4f}",
            f"{100 * statistics.mean(r['accurate'] for r in rows):.0f}", f"{100 * statistics.mean(r['outlier'] for r in rows):.0f}", str(len(rows)),
        )
        console.print(f"{name}: mean ΔR {statistics.mean(r['dR'] for r in rows):.3f}°, mean ΔT {statistics.mean(r['dT'] for r in rows):.4f}")
    console.print(table)
    return results


def speed(reference: ReferenceModel, load_config: Path, scene: Path, settings: RegistrationSettings, console) -> dict:
    """The 20-photo speed case (module docstring, 3.): one row with the keypoint anchors, one without."""
    pruned = prune(reference, 20_000)
    meta, truth = load_metas(scene)[0]
    photos = prepare_photos(pruned, meta, settings)
    began = time.perf_counter()
    keypoints = reference_keypoints(load_config, meta)
    anchors_s = time.perf_counter() - began
    table = Table(title=f"Speed: {len(meta.photos)}-photo meta-image, {pruned.means.shape[0]} Gaussians, fast preset, one 5° start "
                        "(SIFT: the anchors' extraction and matching, once per meta-image; wall: the registration)")
    for column in ("path", "SIFT s", "wall s", "steps/s", "render s", "loss s", "backward s", "verdict s", "ΔR ° / ΔT", "verdict", "SIFT + wall <= 60 s"):
        table.add_column(column, justify="right")
    report = {"anchors_s": anchors_s, "anchored_photos": len(keypoints)}
    paths = (("anchored", f"anchored ({len(keypoints)} photos)", keypoints), ("dense", "dense alone", None))
    for name, label, anchors in paths:
        start = time.perf_counter()
        row = trial(pruned, meta, truth, 0, settings, photos, keypoints=anchors)
        total = time.perf_counter() - start
        timings = row["timings"]  # the verdict's renders are also in render and loss
        table.add_row(
            label, f"{anchors_s:.1f}" if anchors else "-", f"{total:.1f}", f"{row['steps'] / row['time_s']:.2f}", f"{timings['render']:.1f}",
            f"{timings['loss']:.1f}", f"{timings['backward']:.1f}", f"{timings['verdict']:.1f}", f"{row['dR']:.2f} / {row['dT']:.3f}", row["verdict"],
            "met" if total + (anchors_s if anchors else 0.0) <= 60 else "MISSED",
        )
        report[name] = {"wall_time_s": total, **row}
    console.print(table)
    return report


def prune(reference: ReferenceModel, count: int) -> ReferenceModel:
    """The reference model restricted to its `count` most opaque Gaussians (for a fixed-size speed test)."""
    if reference.means.shape[0] <= count:
        return reference
    return reference.subset(torch.argsort(reference.opacities, descending=True)[:count])


def main(args: Args) -> None:
    unknown = [name for name in args.ablation_rows if name not in ABLATIONS]
    if unknown:
        raise SystemExit(f"Unknown ablation row(s) {', '.join(unknown)}; expected some of {', '.join(ABLATIONS)}.")
    args.threads = set_threads(args.threads)
    console = Console(width=140)
    settings = load_preset(args.config)
    reference = load_reference(args.load_config)
    console.print(f"Reference model: {reference.means.shape[0]} Gaussians from {args.load_config}")
    report = {"settings": dataclasses.asdict(settings), "gaussians": int(reference.means.shape[0])}
    if "accuracy" not in args.skip:
        report["accuracy"] = accuracy(reference, args.scene, settings, args.trials, console)
    if "ablations" not in args.skip:
        heavy = scene_variant(args.scene, "occluded", occluder_rate=0.3, occluder_coverage=(0.4, 0.6), appearance_strength=1.0)
        report["ablations"] = ablations(reference, heavy, settings, args.ablation_trials, args.ablation_rows, args.ablation_start, console)
    if "speed" not in args.skip:
        twenty = scene_variant(args.scene, "front20", meta_images=("front:20",))
        report["speed"] = speed(reference, args.load_config, twenty, settings, console)
    args.output.write_text(json.dumps(report, indent=2, default=float))
    console.print(f"Raw results: {args.output}")


if __name__ == "__main__":
    sys.exit(cli_main(lambda: main(cli.parse(Args)) or 0))
