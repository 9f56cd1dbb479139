"""The runs of sg-bench: train (or reuse) each scene's reference, then initialise and register each meta-image.

Every run writes one JSON record, `<output>/runs/<scene>/<meta>/<run>.json`, atomically once it is done;
a run whose record exists is skipped, so an interrupted benchmark continues where it stopped. Trained
references are kept in `<output>/references/<scene>/` and reused the same way.

Runs per meta-image (`RunSpec.name`):
- `<initialiser>` for each of `--initialisers`: `colmap` / `generalized` (sg_nerfstudio.initialisers, the
  paper's baselines), `dense` / `auto` (the SIFT-free start, and the first start of the three) or `perturbed` (the ground truth moved by 5°, 0.1 and 10% in random directions about
  the cameras' centroid, the synthetic start of the accuracy benchmark); the record holds the start's
  errors (Table 1's baseline rows) and the registration's (the "ours (... init)" rows); `<initialiser>@<preset>`
  for each of `--compare-config` (the same start, computed once, another preset);
- `ablation-<row>` for each of `--ablations` (settings changed as in the registration benchmark), from the
  `perturbed` start;
- `noise-<deg>[-s<k>]` for each of `--noise-levels` (`--noise-samples` random directions each): the ground truth moved by <deg>° about a random axis, with
  translation and scale noise in proportion (`NOISE_PER_DEGREE`: 30° comes with 0.5 scene units and 30%, the
  wide-basin start), and `noise-<deg>@<preset>` for each of `--compare-config` (the same start, another preset);
- `size-<n>-<k>` for each of `--sizes` smaller than the meta-image: k-th random subset of n photos
  (`--size-samples` of them), from the `perturbed` start (the supplement's limitations figure).
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from sg_nerfstudio.bench.layout import BenchmarkMeta, BenchmarkScene
from sg_nerfstudio.errors import InputError
from sg_nerfstudio.features import TeacherConfig
from sg_nerfstudio.geometry.meta_image import MetaImage
from sg_nerfstudio.geometry.sim3 import Sim3, perturbed
from sg_nerfstudio.initialisers import METHODS, Initialiser, InitialiserSettings, ReferenceSource
from sg_nerfstudio.initialisers.estimate import PhotoKeypoints
from sg_nerfstudio.registration.hypotheses import runs_dense_start
from sg_nerfstudio.registration.metrics import pose_errors
from sg_nerfstudio.registration.optimize import register, total_steps
from sg_nerfstudio.registration.reference import ReferenceModel, load_reference
from sg_nerfstudio.registration.settings import RegistrationSettings

PERTURBED_START = (5.0, 0.1, 0.1)
"""Rotation (degrees), translation (scene units) and scale fraction of the `perturbed` start (also the
registration benchmark's and the demo's)."""
NOISE_PER_DEGREE = (1.0 / 60.0, 0.01)
"""Translation (scene units) and scale fraction per degree of a `noise-<deg>` start (30°: 0.5 and 30%)."""
ABLATIONS = {
    "full": {},
    "decoded-features": {"objective": {"kind": "features"}},
    "photometric": {"objective": {"kind": "photometric"}},
    "l2": {"objective": {"loss": "l2"}},
    "none": {"robust": {"rule": "none"}},
    "outlier-lts": {"robust": {"rule": "outlier-lts"}},
    "fixed-lts": {"robust": {"rule": "fixed-lts"}},
    "irls": {"robust": {"rule": "irls"}},
}
"""Ablation rows: registration settings changed from the preset (`RegistrationSettings.changed`)."""


@dataclass
class BenchOptions:
    settings: RegistrationSettings
    train_steps: int = 1500
    initialisers: tuple[str, ...] = ("colmap", "generalized")
    ablations: tuple[str, ...] = ()
    noise_levels: tuple[float, ...] = ()
    sizes: tuple[int, ...] = ()
    size_samples: int = 1
    seed: int = 0
    noise_samples: int = 1
    alternatives: dict[str, RegistrationSettings] = field(default_factory=dict)
    """Other presets (name -> settings) the noise runs are repeated with."""
    preset: str = "fast-cpu"
    """Name of `settings` (the `--config` preset), recorded in every run it refines."""
    anchored_photos: int = 0
    """Keypoint anchors of only this many photos per meta-image, those with the most correspondences (0: all)."""


@dataclass
class RunSpec:
    """One registration of one meta-image: where it starts and what is changed."""

    name: str
    family: str  # table1 | ablation | noise | size
    start: str  # colmap | generalized | perturbed | noise
    label: str = ""
    overrides: dict = field(default_factory=dict)
    rotation_noise_deg: float = 0.0
    subset_size: int = 0
    sample: int = 0
    mode: str = ""  # an entry of BenchOptions.alternatives; "" = the main preset


def planned_runs(options: BenchOptions, n_photos: int) -> list[RunSpec]:
    """Every run for one meta-image of `n_photos` photos, in execution order."""
    runs = [RunSpec(init, "table1", init, init) for init in options.initialisers]
    runs += [RunSpec(f"{init}@{mode}", "table1", init, init, mode=mode) for init in options.initialisers for mode in options.alternatives]
    runs += [RunSpec(f"ablation-{name}", "ablation", "perturbed", name, ABLATIONS[name]) for name in options.ablations]
    runs += [
        RunSpec(f"noise-{level:g}" + (f"-s{sample}" if sample else "") + (f"@{mode}" if mode else ""), "noise", "noise", f"{level:g}",
                rotation_noise_deg=level, sample=sample, mode=mode)
        for level in options.noise_levels for sample in range(options.noise_samples) for mode in ["", *options.alternatives]
    ]
    runs += [
        RunSpec(f"size-{size}-{sample}", "size", "perturbed", str(size), subset_size=size, sample=sample)
        for size in options.sizes if 3 <= size < n_photos for sample in range(options.size_samples)
    ]
    return runs


def record_path(output: Path, scene: str, meta: str, run: str) -> Path:
    return output / "runs" / scene / meta / f"{run}.json"


def write_json_atomically(path: Path, record: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    staging = path.with_name(f".{path.name}.tmp")
    staging.write_text(json.dumps(record, indent=2, default=float))
    os.replace(staging, path)


def trained_reference(output: Path, scene: str) -> Optional[tuple[Path, float]]:
    """(config.yml, training seconds) of the scene's reference an earlier run trained into `output`, if any."""
    marker = output / "references" / scene / "reference.json"
    if not marker.is_file():
        return None
    record = json.loads(marker.read_text())
    # The config is named relative to the marker's folder, so that an output folder run again from another directory,
    # or moved, keeps its references; markers of earlier versions named it relative to the working directory.
    config = next((path for path in (marker.parent / record["config"], Path(record["config"])) if path.is_file()), None)
    return (config, float(record["train_s"])) if config is not None else None


def train_reference(scene: BenchmarkScene, output: Path, steps: int, on_step: Callable[[int], None]) -> tuple[Path, float]:
    """config.yml of the scene's reference model (trained now or reused) and the training wall time."""
    from sg_nerfstudio.splat.training import cpu_config, save, short_cpu_schedule, train

    directory = output / "references" / scene.name
    marker = directory / "reference.json"
    trained = trained_reference(output, scene.name)
    if trained is not None:
        return trained
    teacher = TeacherConfig(name="offline", input_size=256, cache_dir=directory / "feature_cache")
    config = short_cpu_schedule(cpu_config(scene.reference, directory / "runs", steps, teacher, experiment_name=scene.name))
    config.pipeline.datamanager.dataparser.colmap_path = scene.reference_model
    started = time.perf_counter()
    trainer = train(config, lambda step, *_: on_step(step))
    path = save(trainer, config)
    elapsed = time.perf_counter() - started
    model = trainer.pipeline.model
    write_json_atomically(marker, {"config": os.path.relpath(path, directory), "train_s": elapsed, "steps": steps, "gaussians": model.num_points, "densified": model.densifies})
    return path, elapsed


class SceneRunner:
    """Runs every planned registration of one scene against its reference model."""

    def __init__(self, scene: BenchmarkScene, config_path: Path, options: BenchOptions, output: Path):
        self.scene, self.options, self.output = scene, options, output
        self.reference: ReferenceModel = load_reference(config_path)
        self.initialiser = Initialiser(ReferenceSource(scene.reference / scene.reference_model, scene.reference / "images"), InitialiserSettings())
        self.reference_unusable: Optional[str] = None  # why the initialisers cannot use this reference, once known
        self.initial: dict[tuple[str, str], tuple[Optional[Sim3], Optional[str]]] = {}
        """(meta-image, initialiser) -> its start, so the `--compare-config` runs start where the main one did."""
        self.notes: dict[tuple[str, str], Optional[str]] = {}
        """(meta-image, initialiser) -> its note (for `auto`: which start it took)."""

    def pending(self, meta: BenchmarkMeta, n_photos: int) -> list[RunSpec]:
        return [run for run in planned_runs(self.options, n_photos) if not record_path(self.output, self.scene.name, meta.name, run.name).is_file()]

    def run(self, meta: BenchmarkMeta, loaded: MetaImage, spec: RunSpec, on_step: Callable[[int, int], None]) -> dict:
        """Execute one run and write its record; `on_step(step, total steps)` after every optimisation step."""
        seed = self.options.seed + spec.sample
        meta_key = sum(map(ord, meta.name))
        subject = loaded
        if spec.subset_size:
            subset_rng = np.random.default_rng([seed, meta_key, spec.subset_size])
            chosen = sorted(subset_rng.choice(len(loaded.photos), spec.subset_size, replace=False).tolist())
            subject = replace(loaded, photos=[loaded.photos[i] for i in chosen])
        # The same random direction for every run of a meta-image with the same kind of start, so ablation rows
        # start from one transform and noise levels differ only in magnitude.
        start_rng = np.random.default_rng([seed, meta_key, sum(map(ord, spec.start))])
        started = time.perf_counter()
        start, failure = self.start(meta, subject, spec, start_rng)
        record = {
            "scene": self.scene.name, "meta": meta.name, "photos": len(subject.photos), "run": spec.name, "family": spec.family,
            "start": spec.start, "label": spec.label, "init_failure": failure, "init_time_s": time.perf_counter() - started,
            "init_note": self.notes.get((meta.name, spec.start)),
            "before": None, "after": None, "refine_failure": None, "refine_time_s": 0.0, "mode": spec.mode,
            "preset": spec.mode or self.options.preset, "verdict": None,
            "truth_residual": meta.truth_residual if not spec.subset_size else None,
            "truth_disagreement": meta.truth_disagreement if not spec.subset_size else None,
        }
        poses = subject.poses
        if start is not None:
            record["before"] = summary(pose_errors(poses, start, meta.ground_truth))
            record["start_transform"] = start.as_record()
            base = self.options.alternatives[spec.mode] if spec.mode else self.options.settings
            settings = base.changed(seed=seed, **spec.overrides)
            keypoints = self.keypoints(subject, settings)
            record["anchored_photos"] = len(keypoints)
            others = self.dense_start_beside(meta, subject, start, settings, keypoints)
            record["other_starts"] = [label for label, _ in others]
            total = total_steps(settings, anchored=bool(keypoints), other_starts=len(others))
            try:
                result = register(
                    self.reference, subject, start, settings, on_step=lambda step, _: on_step(step, total), keypoints=keypoints, other_starts=others,
                )
            except (InputError, FloatingPointError) as error:
                record["refine_failure"] = str(error)
            else:
                record["after"] = summary(pose_errors(poses, result.transform, meta.ground_truth))
                record["transform"] = result.transform.as_record()
                record["refine_time_s"] = result.wall_time_s
                record["verdict"], record["verdict_reasons"] = result.verdict.label, result.verdict.reasons
                record["verdict_evidence"] = result.verdict.as_record()["evidence"]
                record["start_won"] = result.start_won
                record["hypotheses"] = result.hypotheses
        write_json_atomically(record_path(self.output, self.scene.name, meta.name, spec.name), record)
        return record

    def keypoints(self, subject: MetaImage, settings: RegistrationSettings) -> list[PhotoKeypoints]:
        """The keypoint anchors of a run whose settings weigh them: the same for every start of a meta-image
        (the correspondences do not depend on it), of the `anchored_photos` photos with the most correspondences when
        that is set; none when the reference's SIFT cloud cannot be built."""
        if settings.anchors.weight <= 0 or self.reference_unusable is not None:
            return []
        try:
            keypoints = self.initialiser.keypoints(subject)
        except InputError as error:
            self.reference_unusable = str(error)
            return []
        if self.options.anchored_photos > 0:
            keypoints = sorted(keypoints, key=lambda photo: -len(photo.points2D))[: self.options.anchored_photos]
        return keypoints

    def dense_start_beside(
        self, meta: BenchmarkMeta, subject: MetaImage, start: Sim3, settings: RegistrationSettings, keypoints: list[PhotoKeypoints],
    ) -> list[tuple[str, Sim3]]:
        """[("dense", the dense initialiser's start)] for a run whose settings ask for it (`hypotheses.dense_start`) and
        whose meta-image no keypoint anchors hold, as ns-register-meta does; the same for every run of a meta-image."""
        if not runs_dense_start(settings, bool(keypoints)):
            return []
        key = (meta.name, "dense")
        if key not in self.initial:
            try:
                outcome = self.initialiser(subject, "dense")
                self.initial[key] = (outcome.transform, outcome.failure)
            except InputError as error:
                self.initial[key] = (None, str(error))
        dense = self.initial[key][0]
        return [] if dense is None or np.allclose(dense.matrix, start.matrix) else [("dense", dense)]

    def start(self, meta: BenchmarkMeta, subject: MetaImage, spec: RunSpec, rng: np.random.Generator) -> tuple[Optional[Sim3], Optional[str]]:
        """The initial transform of a run, or (None, the initialiser's failure sentence)."""
        truth = meta.ground_truth
        if spec.start in METHODS:
            key = (meta.name, spec.start)
            if key not in self.initial:
                self.initial[key], self.notes[key] = self.initialised(subject, spec.start)
            return self.initial[key]
        degrees = spec.rotation_noise_deg
        noise = (degrees, degrees * NOISE_PER_DEGREE[0], degrees * NOISE_PER_DEGREE[1]) if spec.start == "noise" else PERTURBED_START
        return perturbed(truth, subject.centres, rng, *noise), None

    def initialised(self, subject: MetaImage, method: str) -> tuple[tuple[Optional[Sim3], Optional[str]], Optional[str]]:
        """((the initialiser's transform or None, its failure sentence), its note)."""
        if self.reference_unusable is None:
            try:
                outcome = self.initialiser(subject, method)
                return (outcome.transform, outcome.failure), outcome.note
            except InputError as error:  # e.g. the reference images share too few SIFT matches
                self.reference_unusable = str(error)
        return (None, self.reference_unusable), None


def summary(errors) -> dict:
    return {"dR": errors.rotation_deg, "dT": errors.translation, "accurate": errors.accurate(), "outlier": errors.outlier()}


def read_records(output: Path) -> list[dict]:
    """Every finished run record under `<output>/runs`."""
    root = output / "runs"
    return [json.loads(path.read_text()) for path in sorted(root.glob("*/*/*.json"))] if root.is_dir() else []
