"""Do occluded photos stand out? Per-photo losses near and away from the answer, and what each trimming rule drops.

    python -m sg_nerfstudio.bench.photo_losses BENCHMARK --output SG_BENCH_OUTPUT [--offsets 0 2 5 15]

For every meta-image of a benchmark whose reference `sg-bench --output` has trained, each photo's loss under
the preset's objective (fast-cpu: teacher-on-render) at the ground truth moved by each offset (degrees about a
seeded random axis, translation and scale in proportion as sg-bench's noise starts: 30° = 0.5 / 30%), as a ratio
to its meta-image's median. Photos are split by the occluded fraction the scene generator recorded
(`scene.json`: synthetic scenes and `sg-make-scene --from-photos` looks); a scene without it is skipped. Prints
per offset the ratios of occluded and clean photos (10/50/90th percentiles), the probability that an occluded
photo's ratio exceeds a clean one's (AUC; 0.5 = no separation) and how many occluded photos each rule drops and
clean photos it keeps: the paper's median rule (`lts`) and `outlier-lts` at several z.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np
import tyro
from rich.console import Console
from rich.table import Table

from sg_nerfstudio import cli
from sg_nerfstudio.bench.layout import BenchmarkScene, read_benchmark
from sg_nerfstudio.bench.runs import trained_reference
from sg_nerfstudio.errors import cli_main
from sg_nerfstudio.geometry.meta_image import load_meta_image
from sg_nerfstudio.geometry.sim3 import perturbed
from sg_nerfstudio.registration.objectives import PhotoLosses, build_objective, prepare_photos
from sg_nerfstudio.registration.optimize import effective_near_plane
from sg_nerfstudio.registration.reference import load_reference
from sg_nerfstudio.registration.robust import TrimmingRule
from sg_nerfstudio.registration.settings import RegistrationSettings, load_preset
from sg_nerfstudio.registration.stages import objective_at
from sg_nerfstudio.render.threads import set_threads


@dataclass
class Args:
    benchmark: tyro.conf.Positional[Path]
    """Benchmark directory (as `sg-bench` reads it)."""
    output: Path
    """The `sg-bench --output` whose references/ hold the trained reference of each scene."""
    offsets: list[float] = field(default_factory=lambda: [0.0, 2.0, 5.0, 15.0])
    """Rotation offsets from the ground truth (degrees)."""
    config: str = "fast-cpu"
    """Registration preset whose objective is evaluated."""
    z: list[float] = field(default_factory=lambda: [1.5, 3.0])
    """outlier-lts rules to compare with the median rule."""
    occluded: float = 0.1
    """Photos with at least this occluded fraction count as occluded; below half of it, as clean."""
    seed: int = 7
    threads: Optional[int] = None


def occlusion_of(scene: BenchmarkScene) -> dict[str, dict[str, float]]:
    """{meta-image: {photo name: occluded fraction}} from the scene's scene.json ({} when it records none)."""
    path = scene.directory / "scene.json"
    record = json.loads(path.read_text()) if path.is_file() else {}
    fractions = {}
    for meta in record.get("meta_images", []):
        if "looks" in meta:  # sg-make-scene --from-photos
            fractions[meta["name"]] = {name: look["occluded_fraction"] for name, look in meta["looks"].items()}
        elif meta.get("photos") and "occluded_fraction" in meta["photos"][0]:  # synthetic scenes
            fractions[meta["name"]] = {photo["name"]: photo["occluded_fraction"] for photo in meta["photos"]}
    return fractions


def photo_ratios(scene: BenchmarkScene, config: Path, settings: RegistrationSettings, offsets: list[float], seed: int) -> list[dict]:
    """One row per (meta-image, offset, photo): its loss / the meta-image's median loss there, and the losses."""
    reference = load_reference(config)
    objective = build_objective(reference, settings)
    rows = []
    for bench_meta in scene.metas:
        meta = load_meta_image(bench_meta.directory)
        photos = prepare_photos(reference, meta, settings, objective)
        truth_ns = reference.world_to_dataparser @ bench_meta.ground_truth
        losses = PhotoLosses(reference, photos, objective, settings, effective_near_plane(meta, truth_ns, settings.objective.near_plane))
        for offset in offsets:
            rng = np.random.default_rng([seed, int(round(offset * 10))])
            start = perturbed(bench_meta.ground_truth, meta.centres, rng, offset, offset / 30 * 0.5, offset / 30 * 0.3) if offset else bench_meta.ground_truth
            values = objective_at(losses, reference.world_to_dataparser @ start)
            rows += [{"meta": f"{scene.name}/{meta.name}", "offset": offset, "photo": photo.name, "losses": values, "index": i}
                     for i, photo in enumerate(photos)]
    return rows


def separation(occluded: np.ndarray, clean: np.ndarray) -> float:
    """P(an occluded photo's ratio > a clean one's), ties half (the AUC of the ratio as an occlusion detector)."""
    greater = (occluded[:, None] > clean[None, :]).mean()
    ties = (occluded[:, None] == clean[None, :]).mean()
    return float(greater + 0.5 * ties)


def run(args: Args) -> None:
    console = Console(width=160)
    set_threads(args.threads)
    settings = load_preset(args.config)
    rules = {"lts": TrimmingRule("lts"), **{f"outlier-lts z={z:g}": TrimmingRule("outlier-lts", z=z) for z in args.z}}
    rows = []
    for scene in read_benchmark(args.benchmark):
        fractions, trained = occlusion_of(scene), trained_reference(args.output, scene.name)
        if not fractions or trained is None:
            console.print(f"{scene.name}: skipped ({'no occlusion record in scene.json' if not fractions else 'no trained reference in ' + str(args.output)})")
            continue
        for row in photo_ratios(scene, trained[0], settings, args.offsets, args.seed):
            values = row["losses"]
            row["ratio"] = float(values[row["index"]] / np.median(values))
            row["occluded"] = fractions[row["meta"].split("/", 1)[1]].get(row["photo"], float("nan"))
            row["kept"] = {name: bool(values[row["index"]] <= rule.threshold(values)) for name, rule in rules.items()}
            rows.append(row)
    table = Table(title=f"Per-photo loss / its meta-image's median ({args.config} objective), occluded >= {args.occluded:g} vs clean < {args.occluded / 2:g}")
    for column in ("offset (°)", "occluded photos", "ratio occluded q10/50/90", "clean photos", "ratio clean q10/50/90", "AUC", *[f"{name}: drops occluded / keeps clean" for name in rules]):
        table.add_column(column, justify="right")
    for offset in args.offsets:
        here = [r for r in rows if r["offset"] == offset]
        occluded = [r for r in here if r["occluded"] >= args.occluded]
        clean = [r for r in here if r["occluded"] < args.occluded / 2]
        if not occluded or not clean:
            continue
        ratio_o, ratio_c = (np.array([r["ratio"] for r in group]) for group in (occluded, clean))
        quantiles = lambda ratios: "/".join(f"{q:.2f}" for q in np.percentile(ratios, [10, 50, 90]))
        table.add_row(f"{offset:g}", str(len(occluded)), quantiles(ratio_o), str(len(clean)), quantiles(ratio_c), f"{separation(ratio_o, ratio_c):.2f}",
                      *[f"{sum(not r['kept'][name] for r in occluded)} / {sum(r['kept'][name] for r in clean)}" for name in rules])
    console.print(table)


def entrypoint() -> None:
    sys.exit(cli_main(lambda: run(cli.parse(Args)) or 0))


if __name__ == "__main__":
    entrypoint()
