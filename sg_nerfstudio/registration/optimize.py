"""The registration loop: optimise one Sim(3) of a whole meta-image against the frozen reference model.

Per step: choose the photos of the step (`RetrimSchedule`, `BatchSchedule`), move their cameras by T = U(delta) o T0 in the
dataparser frame, render the model and compare with the photos (`objectives.PhotoLosses`), aggregate the
per-photo losses robustly (`robust.RobustAggregator`, LTS by default), take an Adam step on the 7
parameters delta (`robust_step`) and record what happened (`History`). At the end the result is probed
around for its verdict (`verdict.py`). Everything the caller passes in
and gets back is in the reference *world* frame.
"""

from __future__ import annotations

import math
import time
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field, replace
from typing import Callable, ContextManager, Optional

import numpy as np
import torch
from torch import Tensor

from sg_nerfstudio.errors import InputError
from sg_nerfstudio.geometry.alignment import align_cameras, camera_residuals
from sg_nerfstudio.geometry.meta_image import MetaImage
from sg_nerfstudio.geometry.sim3 import Sim3, rotation_angle_deg
from sg_nerfstudio.initialisers.estimate import PhotoKeypoints
from sg_nerfstudio.registration.depth_agreement import DepthAgreement, summarise
from sg_nerfstudio.registration.keypoints import SCALE_RESOLUTION, Anchoring, CameraFit, KeypointTerm, anchors_fix_scale
from sg_nerfstudio.features import teacher_input_size
from sg_nerfstudio.registration.objectives import (
    Objective, PhotoLosses, PreparedPhoto, build_objective, objective_teacher_config, prepare_photos, refine_settings, with_camera_changes,
)
from sg_nerfstudio.registration.reference import ReferenceModel
from sg_nerfstudio.registration.robust import RobustAggregator, TrimmingRule, check_robust_settings
from sg_nerfstudio.registration.settings import RegistrationSettings, check_ranges
from sg_nerfstudio.registration import other_minimum
from sg_nerfstudio.registration.verdict import Evidence, Verdict, decide, failure, gather_evidence, probe_sizes
from sg_nerfstudio.registration.visibility import MAX_ROTATION_DEG

Array = np.ndarray


class InitialisationError(InputError):
    """A start the optimisation cannot begin from."""


@dataclass
class RegistrationResult:
    transform: Sim3  # meta -> reference world
    initial_transform: Sim3
    final_losses: Array  # [P] per photo at the final transform
    initial_losses: Array
    final_trimmed_loss: float
    history: list[dict]  # per step and photo: step, image, loss, kept, weight
    ignored_fraction: Array  # [P] fraction of the steps in which each photo did not count (not rendered between re-decisions: ignored)
    steps: int
    wall_time_s: float
    timings: dict
    near_plane: float
    settings: dict
    photo_names: list[str]
    coverage: Array  # [P] fraction of rendered pixels covered by the model at the initial transform
    verdict: Verdict  # registered | uncertain | failed, with its evidence (verdict.py)
    hypotheses: list[dict] = field(default_factory=list)  # with settings.hypotheses: each optimised start and its end
    rendered_model: dict = field(default_factory=dict)
    """What the main stage rendered at its last cull (`rendered_model_record`): the reference's Gaussians, those
    rendered after culling and level of detail, the merge voxel (render pixels; 0: none) and the culls."""
    focal_scales: dict[str, float] = field(default_factory=dict)
    """With `settings.refine_focal`: photo name -> the scale of its SfM focal length the registration fitted and
    rendered with (photos not listed kept theirs)."""
    pose_corrections: dict[str, dict[str, float]] = field(default_factory=dict)
    """With `settings.refine_photo_poses`: photo name -> how far the registration moved its camera from where `transform`
    puts the meta-image's own camera: {"rotation_deg", "centre_shift" (reference world units)} (photos not listed were
    not moved)."""
    radial_k1: dict[int, float] = field(default_factory=dict)
    """With `settings.refine_distortion`: COLMAP camera id -> the first radial coefficient the registration fitted and
    undistorted its photos with (cameras not listed kept theirs)."""
    photo_poses: dict[str, Array] = field(default_factory=dict)
    """With `settings.refine_photo_poses`: photo name -> [3, 4] cam_from_world (OpenCV) in the reference world of each
    photo the registration moved, where its last stages rendered it (the others sit at `transform` applied to their own
    pose)."""
    scale_search: Optional[dict] = None
    """When the keypoint anchors left the scale free (`scale_the_anchors_leave_free`: one photo's, or those of photos
    taken from nearly one spot): the anchored photos, how far a 2% scale change moved their keypoints and their median
    error (pixels), the factor chosen about their mean camera centre and the objective there; None otherwise."""


class BatchSchedule:
    """Which photos each step renders: all of them, or `per_step` drawn without replacement from seeded
    permutations (every photo once per epoch)."""

    def __init__(self, count: int, per_step: int, seed: int):
        self.count, self.per_step = count, per_step or count
        self.rng = np.random.default_rng(seed)
        self.queue: list[int] = []

    def next(self) -> list[int]:
        if self.per_step >= self.count:
            return list(range(self.count))
        while len(self.queue) < self.per_step:
            self.queue.extend(self.rng.permutation(self.count).tolist())
        batch, self.queue = self.queue[: self.per_step], self.queue[self.per_step :]
        return batch


class RetrimSchedule:
    """Which photos each step renders when the robust rule may be re-decided only every `retrim_every` steps.

    A step that re-decides (every `retrim_every`-th step after the stage's robust warm-up, and every warm-up step)
    renders the `BatchSchedule`'s photos; the steps between render only the photos the rule counted at the last
    one that re-decided (a trimmed photo's loss only decides whether it is trimmed). `retrim_every` 1: every step
    re-decides (the paper's rule, which renders every photo every step)."""

    def __init__(self, count: int, settings: RegistrationSettings, warmup_steps: int):
        self.batches = BatchSchedule(count, settings.images_per_step, settings.seed)
        self.every, self.warmup_steps, self.calls = settings.retrim_every, warmup_steps, 0
        self.decided: list[int] = []  # the photos of the last step that re-decided
        self.counted_there: Optional[list[int]] = None  # those of them the rule counted; None: this step re-decides
        self.between = False  # whether this step is one between re-decisions

    def next(self) -> list[int]:
        after_warmup = self.calls - self.warmup_steps
        self.calls += 1
        self.between = bool(self.every > 1 and self.counted_there and after_warmup > 0 and after_warmup % self.every)
        if self.between:
            return list(self.counted_there)
        self.counted_there = None
        self.decided = self.batches.next()
        return self.decided

    def counted(self, batch: list[int], kept: Array) -> None:
        """Remember the photos the rule counted, if `batch` was a step that re-decided."""
        if self.counted_there is None:
            self.counted_there = [index for index, keep in zip(batch, kept) if keep]

    def left_out(self, batch: list[int]) -> list[int]:
        """Photos of the last re-decision that a step between re-decisions did not render (ignored there)."""
        if not self.between:
            return []
        rendered = set(batch)
        return [index for index in self.decided if index not in rendered]


class History:
    """Per step and photo: loss, whether the robust loss kept it, its weight; and how often each was ignored."""

    def __init__(self, names: list[str]):
        self.names = names
        self.rows: list[dict] = []
        self.ignored = np.zeros(len(names))
        self.evaluated = np.zeros(len(names))

    def record(self, step: int, batch: list[int], losses: list[Tensor], kept: Array, weights: Array, stage: str = "main") -> None:
        for index, loss, keep, weight in zip(batch, [float(loss.detach()) for loss in losses], kept, weights):
            self.rows.append({"step": step, "image": self.names[index], "loss": loss, "kept": bool(keep), "weight": float(weight), "stage": stage})
            self.ignored[index] += not keep
            self.evaluated[index] += 1

    def skip(self, indices: list[int]) -> None:
        """Photos a step did not render because the robust rule had trimmed them: ignored in that step."""
        for index in indices:
            self.ignored[index] += 1
            self.evaluated[index] += 1

    def extend(self, other: "History") -> None:
        """Append the rows and counts of another history of the same photos."""
        self.rows.extend(other.rows)
        self.ignored += other.ignored
        self.evaluated += other.evaluated

    def ignored_fraction(self) -> Array:
        return self.ignored / np.maximum(self.evaluated, 1)


def effective_near_plane(meta: MetaImage, initial_ns: Sim3, requested: float) -> float:
    """min(requested, half the 5th-percentile depth of the sparse points seen by the photos, in dataparser units)."""
    depths = np.concatenate([p.point_depths for p in meta.photos]) if meta.photos else np.zeros(0)
    depths = depths[depths > 0]
    if len(depths) == 0:
        return requested
    return float(min(requested, 0.5 * initial_ns.scale * np.percentile(depths, 5)))


def evaluate_start(losses: PhotoLosses, initial_ns: Sim3, meta_name: str) -> tuple[Array, Array]:
    """[P] losses and [P] coverage at the start; InitialisationError when no photo sees the model."""
    with torch.no_grad():
        values, coverage = losses(initial_ns.to_torch(), list(range(len(losses.photos))))
    if float(coverage.max()) < 1e-3:
        raise InitialisationError(
            f"From the initial transform the reference model renders nothing for any photo of meta-image '{meta_name}' "
            "(every camera sees empty space); expected a start near the answer (see --init)."
        )
    return torch.stack(values).double().numpy(), coverage.double().numpy()


def robust_step(
    losses: PhotoLosses, aggregator: RobustAggregator, transform: Sim3, batch: list[int],
    optimizer: torch.optim.Optimizer, scheduler: torch.optim.lr_scheduler.LRScheduler, anchors: Optional[KeypointTerm] = None,
) -> tuple[list[Tensor], Array, Array]:
    """One Adam step on the robust objective of `batch` under `transform` (plus the keypoint term when there are
    `anchors`); returns (losses, kept, weights)."""
    values, _ = losses(transform, batch)
    objective, kept, weights = aggregator(values, np.asarray(batch))
    start = time.perf_counter()
    if anchors:
        objective = objective + anchors(transform)
    optimizer.zero_grad()
    objective.backward()
    optimizer.step()
    scheduler.step()
    losses.timings["backward"] += time.perf_counter() - start
    return values, kept, weights


def final_evaluation(losses: PhotoLosses, final_ns: Sim3, settings: RegistrationSettings) -> tuple[Array, Array, float, DepthAgreement]:
    """[P] losses and [P] coverage at the final transform, the losses' trimmed mean (those the robust rule
    counts) and the depth agreement of the photos' sparse points there (one render for all)."""
    with torch.no_grad():
        values, coverage, ratios = losses.evaluate(final_ns.to_torch(), list(range(len(losses.photos))), with_depth=True)
    final = torch.stack(values).double().numpy()
    return final, coverage.double().numpy(), TrimmingRule.of(settings).trimmed_mean(final), summarise(ratios)


def register(
    reference: ReferenceModel,
    meta: MetaImage,
    initial_world: Sim3,
    settings: RegistrationSettings,
    photos: Optional[list[PreparedPhoto]] = None,
    on_step: Optional[Callable[[int, Sim3], None]] = None,
    objective: Optional[Objective] = None,
    keypoints: Optional[list[PhotoKeypoints]] = None,
) -> RegistrationResult:
    """Estimate the Sim(3) meta -> reference world starting from `initial_world`.

    Stages: the coarse-to-fine `pyramid` stages of the settings (if any; hypotheses around the start at the
    coarsest), then the main stage at the settings' teacher size, then the `refine_steps` stage (if any). The
    verdict and the final losses are the main stage's objective (the one its thresholds were calibrated on).
    `photos` and `objective` may come prepared for the main stage (`prepare_photos`, `build_objective`: the
    teacher is built once). `on_step(step,
    transform)` is called after every step of every stage (`total_steps(settings, anchored)` in all) with the current
    estimate (meta -> world). `keypoints`: the photos' verified SIFT correspondences with the reference
    (`Initialiser.keypoints`); with `settings.keypoint_weight > 0` every stage adds their reprojection term
    (registration/keypoints.py), and with `settings.refine_focal` / `settings.refine_photo_poses` the photos' focal
    lengths / poses fitted to them before the first render are used by every stage (`RegistrationResult.focal_scales`,
    `pose_corrections`); with moved poses the returned transform is the final one composed with the Sim(3) that maps
    the given cameras onto the moved ones (`geometry.alignment.align_cameras`).
    """
    started = time.perf_counter()
    check_ranges(settings)
    check_robust_settings(settings)
    objective = objective or build_objective(reference, settings)
    world_to_ns = reference.world_to_dataparser
    ns_to_world = world_to_ns.inverse()
    initial_ns = world_to_ns @ initial_world
    near_plane = effective_near_plane(meta, initial_ns, settings.near_plane)
    anchor = Anchoring(meta, keypoints or [], world_to_ns, settings.keypoint_weight)
    prealigned = prealigns(settings, bool(anchor))
    current, fit, given, scale_search = initial_ns, CameraFit(initial_ns), meta, None
    if prealigned:
        fit = keypoint_prealignment(anchor, meta, initial_ns, settings, objective.teacher.grid_size)
        current = fit.transform
        meta, photos = with_fitted_cameras(meta, photos, fit)
        anchor = anchor.for_meta(meta, narrow=True if fit.poses else None)  # the moved photos fit their keypoints under the narrow kernel
    camera_shift = align_cameras(np.stack(given.poses), np.stack(meta.poses)).transform if fit.poses else Sim3.identity()
    photos = photos if photos is not None else prepare_photos(reference, meta, settings, objective)
    main_steps, main_lr = main_schedule(settings, prealigned)
    main = Stage("main", PhotoLosses(reference, photos, objective, settings, near_plane), main_steps, main_lr, settings.lr_final)
    if prealigned:
        current, scale_search = scale_the_anchors_leave_free(main.losses, anchor, meta, current, settings)
    initial_losses, coverage = evaluate_start(main.losses, initial_ns @ camera_shift.inverse(), meta.name)  # the given cameras at the start

    history = History([p.name for p in photos])
    report = (lambda step, estimate: on_step(step, ns_to_world @ estimate)) if on_step is not None else None
    stages = coarse_stages(reference, meta, settings, near_plane) + [main] + refine_stages(reference, meta, settings, near_plane, bool(anchor), main)
    step, hypotheses = 0, []
    for index, stage in enumerate(stages):
        if index == 0 and settings.hypotheses > 0:
            current, hypotheses, step = best_hypothesis(stage, main.losses, meta, current, settings, history, step, report, anchor)
        else:
            seed = initial_losses if stage is main and index == 0 and current is initial_ns else None  # the start's losses, if still the start
            current, step = optimise_stage(stage, meta, current, settings, history, step, report, seed, anchor)

    with held_for_probes(main.losses, meta, current):
        final_losses, final_coverage, trimmed, depth = final_evaluation(main.losses, current, settings)
        probing = time.perf_counter()
        evidence = gather_evidence(
            main.losses, meta, current, final_losses, final_coverage, initial_losses, TrimmingRule.of(settings), depth,
            scale_search["photos"] if scale_search else None,
        )
    evidence.camera_fit_refused = fit.refused or None
    final_anchors = anchor.term(main.losses.objective.teacher.grid_size, 1.0)
    if final_anchors is not None:
        evidence.keypoint_error_cells, evidence.keypoint_photos = final_anchors.median_error_cells(current), final_anchors.photos
        evidence.keypoint_scale_motion_px, evidence.keypoint_error_px = final_anchors.scale_motion_px(current)
    if not uses_anchors(settings, bool(anchor)) and failure(evidence) is None:  # a failed result needs no second look
        record_other_minimum(evidence, main, meta, current, final_losses, settings)
    elsewhere = [h["final_objective"] for h in hypotheses if not h["agrees_with_winner"]]
    if elsewhere:
        evidence.hypothesis_margin = min(elsewhere) / max(min(h["final_objective"] for h in hypotheses), 1e-12) - 1.0
    distinct = {id(stage.losses): stage.losses for stage in stages}.values()  # a refine stage may share the main stage's
    timings = {key: sum(losses.timings[key] for losses in distinct) for key in main.losses.timings}
    timings["verdict"] = time.perf_counter() - probing  # the probes' renders (also counted in "render" and "loss")
    return RegistrationResult(
        transform=ns_to_world @ current @ camera_shift,
        initial_transform=initial_world.numpy(),
        final_losses=final_losses,
        initial_losses=initial_losses,
        final_trimmed_loss=trimmed,
        history=history.rows,
        ignored_fraction=history.ignored_fraction(),
        steps=step,
        wall_time_s=time.perf_counter() - started,
        timings=timings,
        near_plane=near_plane,
        settings=asdict(settings),
        photo_names=[p.name for p in photos],
        coverage=coverage,
        verdict=decide(evidence),
        hypotheses=hypotheses,
        rendered_model=rendered_model_record(reference, main.losses),
        focal_scales=fit.focal_scales,
        radial_k1=fit.radial_k1,
        pose_corrections=pose_corrections(given, meta, camera_shift, current.scale * ns_to_world.scale, set(fit.poses)),
        photo_poses={photo.name: (ns_to_world @ current).move_camera(photo.cam_from_world) for photo in meta.photos if photo.name in fit.poses},
        scale_search=scale_search,
    )


def held_for_probes(losses: PhotoLosses, meta: MetaImage, result: Sim3) -> ContextManager:
    """Render the final evaluation and the verdict's probes (`verdict.gather_evidence`) with the model culled at the
    result (`VisibleSubset.held_at`) when a rotation probe is within the re-cull rotation (one fast-cpu cell: 1.8°).
    Its shift probe, that angle times the median depth (3% of it at 1.8°, 7% at 4°), turns the view of a point at the
    median depth by the same angle, within the widened frusta's margin (at least 7°) as the re-cull bounds are; a test
    compares probes of 3-4° with the whole model. Coarser probes cull for their own poses as the optimisation does."""
    if losses.visible is None:
        return nullcontext()
    rotation, _ = probe_sizes(meta, losses.photos, losses.objective.teacher.grid_size, result)
    return losses.visible.held_at(result) if math.degrees(rotation) <= MAX_ROTATION_DEG else nullcontext()


def record_other_minimum(evidence: Evidence, main: Stage, meta: MetaImage, result: Sim3, final_losses: Array, settings: RegistrationSettings) -> None:
    """Fill `evidence.other_minimum_rise` / `other_minimum_cells` by `other_minimum.look_for_other_minimum` around
    `result` (meta -> dataparser; `final_losses` [P] the main stage's per-photo losses there): on the main stage's
    objective restricted to the `other_minimum.PHOTOS` photos the model covers most at the result, the descent by
    `optimise_stage` on them (a stage of its own, off the registration's history)."""
    rule = TrimmingRule.of(settings)
    coverage = -np.asarray(evidence.per_photo_coverage)
    chosen = sorted(np.argsort(coverage, kind="stable")[: other_minimum.PHOTOS].tolist())
    losses = main.losses
    subset = PhotoLosses(losses.reference, [losses.photos[i] for i in chosen], losses.objective, losses.settings, losses.near_plane)
    descent = Stage("other-minimum", subset, other_minimum.REFINE_STEPS, other_minimum.REFINE_LR, other_minimum.REFINE_LR / 6)
    found = other_minimum.look_for_other_minimum(
        objective=objective_with_anchors(subset, result, settings, None),
        refine=lambda start: optimise_stage(descent, meta, start, settings, History([p.name for p in subset.photos]), 0, None)[0],
        meta=meta, result=result, result_value=rule.trimmed_mean(final_losses[chosen]),
        rotation_probe=np.radians(evidence.probe_rotation_deg), translation_probe=evidence.probe_translation, sharpness=evidence.sharpness,
    )
    for key in losses.timings:  # the look's renders count with the registration's (and in its verdict time)
        losses.timings[key] += subset.timings[key]
    if found is not None:
        evidence.other_minimum_rise, evidence.other_minimum_cells = found.rise, found.distance_cells


def keypoint_prealignment(anchor: Anchoring, meta: MetaImage, start_ns: Sim3, settings: RegistrationSettings, grid_size: int) -> CameraFit:
    """The render-free stage before the first render: the keypoint term alone from `start_ns` (meta -> dataparser)
    and, with `settings.refine_focal` or `settings.refine_photo_poses`, then jointly with the photos' focal lengths and
    / or poses (`Anchoring.fit_cameras`; nothing fitted without them)."""
    steps = settings.keypoint_prealign_steps
    current = anchor.prealign(start_ns, update_centre(meta, start_ns, settings), grid_size, steps)
    if not (settings.refine_focal or settings.refine_photo_poses or settings.refine_distortion):
        return CameraFit(current)
    pose_prior = settings.photo_pose_prior_scale if settings.refine_photo_poses else None
    return anchor.fit_cameras(
        current, update_centre(meta, current, settings), grid_size, settings.camera_fit_iterations, settings.refine_focal, pose_prior,
        settings.refine_distortion, settings.camera_fit == "adjustment",
    )


def with_fitted_cameras(meta: MetaImage, photos: Optional[list[PreparedPhoto]], fit: CameraFit) -> tuple[MetaImage, Optional[list[PreparedPhoto]]]:
    """`meta` and its prepared `photos` (if any) with the focal lengths, poses and radial distortion of `fit`; with a new
    distortion the photos are not returned (None): they must be undistorted again (`prepare_photos`)."""
    factors = {photo.name: fit.focal_scales[photo.name] / photo.focal_scale for photo in meta.photos if photo.name in fit.focal_scales}
    meta = meta.with_focal_scales(fit.focal_scales).with_poses(fit.poses).with_radial_distortion(fit.radial_k1)
    if photos is None or fit.radial_k1:
        return meta, None
    return meta, with_camera_changes(photos, factors, fit.poses)


def pose_corrections(given: MetaImage, moved: MetaImage, camera_shift: Sim3, world_per_meta: float, names: set[str]) -> dict[str, dict[str, float]]:
    """Per photo in `names` (the moved ones), how far its moved camera (`moved`) sits from its given one carried by
    `camera_shift` (the Sim(3) that maps the given cameras onto the moved ones): rotation (degrees) and centre distance
    in reference world units (`world_per_meta`: meta units to world)."""
    if not names:
        return {}
    rotation, centre = camera_residuals(camera_shift, np.stack(given.poses), np.stack(moved.poses))
    return {
        photo.name: {"rotation_deg": round(float(r), 4), "centre_shift": round(float(c) * world_per_meta, 6)}
        for photo, r, c in zip(given.photos, rotation, centre) if photo.name in names
    }


def rendered_model_record(reference: ReferenceModel, losses: PhotoLosses) -> dict:
    """{gaussians, rendered, voxel_pixels, culls} of a stage's losses at its last cull (every Gaussian, no cull,
    when it does not cull)."""
    visible = losses.visible
    if visible is None:
        return {"gaussians": reference.count, "rendered": reference.count, "voxel_pixels": 0.0, "culls": 0}
    return {"gaussians": reference.count, "rendered": visible.subset.count, "voxel_pixels": visible.voxel_pixels, "culls": visible.culls}


@dataclass
class Stage:
    """One optimisation stage: the per-photo losses it minimises (teacher size, render size) and its schedule."""

    name: str  # "main" or "coarse-<teacher input size>"
    losses: PhotoLosses
    steps: int
    lr: float
    lr_final: Optional[float]


def uses_anchors(settings: RegistrationSettings, anchored: bool) -> bool:
    """Whether keypoint anchors hold the pose: the meta-image has them (`anchored`) and the settings weigh them."""
    return anchored and settings.keypoint_weight > 0


def prealigns(settings: RegistrationSettings, anchored: bool) -> bool:
    """Whether the keypoint pre-alignment runs: keypoint anchors hold the pose and the settings ask for it."""
    return uses_anchors(settings, anchored) and settings.keypoint_prealign_steps > 0


def main_schedule(settings: RegistrationSettings, prealigned: bool) -> tuple[int, float]:
    """(steps, initial learning rate) of the main stage: `prealigned_steps` / `prealigned_lr` after the keypoint
    pre-alignment where the settings give them, else `steps` / `lr`."""
    if not prealigned:
        return settings.steps, settings.lr
    steps = settings.prealigned_steps if settings.prealigned_steps is not None else settings.steps
    return steps, settings.prealigned_lr if settings.prealigned_lr is not None else settings.lr


def total_steps(settings: RegistrationSettings, anchored: bool = False) -> int:
    """Steps of all stages (what `on_step` counts up to) for a meta-image with (`anchored`) or without keypoint
    anchors: each optimised hypothesis runs the first stage."""
    main = main_schedule(settings, prealigns(settings, anchored))[0]
    first = settings.pyramid_steps if settings.pyramid else main
    runs = min(settings.hypotheses + 1, max(1, settings.hypotheses_kept)) if settings.hypotheses else 1
    refine = settings.refine_steps if refines(settings, anchored) else 0
    return main + len(settings.pyramid) * settings.pyramid_steps + (runs - 1) * first + refine


def refines(settings: RegistrationSettings, anchored: bool) -> bool:
    """Whether the refine stage runs: `refine_steps` > 0, and the meta-image has no keypoint anchors unless
    `refine_anchored`."""
    return settings.refine_steps > 0 and (settings.refine_anchored or not uses_anchors(settings, anchored))


def refine_stages(reference: ReferenceModel, meta: MetaImage, settings: RegistrationSettings, near_plane: float, anchored: bool, main: Stage) -> list[Stage]:
    """[] or the refine stage: `refine_settings` (its own teacher and photo targets unless it is the main stage's),
    `refine_steps` from `refine_lr` decaying to `lr_final`."""
    if not refines(settings, anchored):
        return []
    own = refine_settings(settings)
    if own == settings:  # the main stage's objective: its photos and targets serve
        losses = main.losses
    else:
        objective = build_objective(reference, own)
        losses = PhotoLosses(reference, prepare_photos(reference, meta, own, objective), objective, own, near_plane)
    return [Stage(f"refine-{losses.objective.teacher_config.name}", losses, settings.refine_steps, settings.refine_lr, settings.lr_final)]


MIN_COARSE_GRID = 8
"""Coarse stages whose teacher grid would have fewer cells on the long side are skipped (a 4-cell descriptor
of a photo matches almost any pose: on the tiny test scene such a stage sent a start at the truth 15° away)."""


def coarse_stages(reference: ReferenceModel, meta: MetaImage, settings: RegistrationSettings, near_plane: float) -> list[Stage]:
    """The `pyramid` stages, coarsest first: the teacher at its input size divided by each factor (cells that
    many times larger in the photo), the learning rate multiplied by it and decaying tenfold within the stage."""
    stages = []
    main_size = teacher_input_size(objective_teacher_config(reference, settings))
    for factor in sorted(settings.pyramid, reverse=True):  # each >= 2 (settings.check_ranges, run by `register`)
        stage_settings = replace(settings, teacher_input_size=main_size // factor)
        objective = build_objective(reference, stage_settings)
        if objective.teacher.grid_size < MIN_COARSE_GRID:
            continue
        photos = prepare_photos(reference, meta, stage_settings, objective)
        lr = settings.lr * factor
        stages.append(Stage(f"coarse-{main_size // factor}", PhotoLosses(reference, photos, objective, stage_settings, near_plane), settings.pyramid_steps, lr, lr / 10))
    return stages


def optimise_stage(
    stage: Stage, meta: MetaImage, start_ns: Sim3, settings: RegistrationSettings, history: History, first_step: int,
    on_step: Optional[Callable[[int, Sim3], None]], start_losses: Optional[Array] = None, anchor: Optional[Anchoring] = None,
) -> tuple[Sim3, int]:
    """Adam on delta for `stage.steps` steps from `start_ns` (meta -> dataparser), recorded in `history` from
    step `first_step` on; (the estimate at the end, the next step number). `start_losses`: [P] the stage's
    per-photo losses at `start_ns` if known (they seed the robust loss), else computed. `anchor` adds the
    keypoint term, weighted by the stage's objective at its start."""
    losses = stage.losses
    seed = start_losses if start_losses is not None else objective_at(losses, start_ns)
    rule = TrimmingRule.of(settings)
    aggregator = RobustAggregator(rule, seed, warmup_steps(settings, stage.steps))
    anchors = anchor.term(losses.objective.teacher.grid_size, rule.trimmed_mean(seed)) if anchor is not None else None
    start = start_ns.to_torch()
    centre = torch.from_numpy(update_centre(meta, start_ns, settings))
    delta = torch.zeros(7, dtype=torch.float64, requires_grad=True)
    optimizer = torch.optim.Adam([delta], lr=stage.lr, eps=settings.adam_eps)
    gamma = (stage.lr_final / stage.lr) ** (1.0 / max(stage.steps, 1)) if stage.lr_final else 1.0
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=gamma)
    batches = RetrimSchedule(len(losses.photos), settings, aggregator.warmup_steps)
    for step in range(first_step, first_step + stage.steps):
        batch = batches.next()
        values, kept, weights = robust_step(losses, aggregator, Sim3.update(delta, centre) @ start, batch, optimizer, scheduler, anchors)
        if not torch.isfinite(delta).all():
            raise FloatingPointError(f"The registration of '{meta.name}' diverged to NaN at step {step} ({stage.name}).")
        batches.counted(batch, kept)
        history.record(step, batch, values, kept, weights, stage.name)
        history.skip(batches.left_out(batch))
        if on_step is not None:
            on_step(step, current_estimate(delta, centre, start))
    return current_estimate(delta, centre, start), first_step + stage.steps


def warmup_steps(settings: RegistrationSettings, steps: int) -> int:
    """Steps of a `steps`-step stage in which every photo counts before the robust rule trims (`trim_after`)."""
    return int(round(settings.trim_after * steps))


def update_centre(meta: MetaImage, transform: Sim3, settings: RegistrationSettings) -> Array:
    """[3] the point (dataparser frame) the update rotates and scales about (`settings.update_centre`)."""
    return meta.look_at_under(transform) if settings.update_centre == "look-at" else meta.centroid_under(transform)


def objective_at(losses: PhotoLosses, meta_to_dataparser: Sim3, indices: Optional[list[int]] = None) -> Array:
    """[P] per-photo losses of every photo (or [len(indices)] of those photos) under a numpy Sim3 (meta -> dataparser),
    without gradients."""
    with torch.no_grad():
        indices = list(range(len(losses.photos))) if indices is None else indices
        return torch.stack(losses(meta_to_dataparser.to_torch(), indices)[0]).double().numpy()


def best_hypothesis(
    stage: Stage, judge: PhotoLosses, meta: MetaImage, start_ns: Sim3, settings: RegistrationSettings, history: History, first_step: int,
    on_step: Optional[Callable[[int, Sim3], None]], anchor: Optional[Anchoring] = None,
) -> tuple[Sim3, list[dict], int]:
    """Several starts around `start_ns`: the start and `settings.hypotheses` rotations of `hypothesis_deg` about
    axes spread over the sphere (about the cameras' centroid), each also scaled by every `hypothesis_scales`
    factor. The `hypotheses_kept` with the lowest robust objective are each optimised over the stage; the one whose end scores lowest under `judge` (the main
    stage's finer objective, which tells apart ends the coarse one cannot) wins and its steps go to `history`.

    Scores are the robust objective plus, with an `anchor`, the keypoint term weighted as in `optimise_stage`.

    Returns (winner, one record per optimised hypothesis, the next step number)."""
    rotated = [(None, start_ns)] + hypotheses_around(start_ns, meta, settings.hypotheses, settings.hypothesis_deg)
    candidates = [((axis, factor), scaled_about_centroid(transform, meta, factor)) for factor in (1.0, *settings.hypothesis_scales) for axis, transform in rotated]
    coarse_score, judge_score = (objective_with_anchors(losses, start_ns, settings, anchor) for losses in (stage.losses, judge))
    scores = [coarse_score(transform) for _, transform in candidates]
    runs = []
    for index in np.argsort(scores, kind="stable")[: max(1, settings.hypotheses_kept)]:
        own = History(history.names)
        final, _ = optimise_stage(stage, meta, candidates[index][1], settings, own, first_step, on_step, anchor=anchor)
        runs.append((final, judge_score(final), own, candidates[index][0], scores[index]))
    winner, _, winner_history, _, _ = min(runs, key=lambda run: run[1])
    history.extend(winner_history)
    records = [
        {"axis": axis, "scale": factor, "start_objective_coarse": start_score, "final_objective": final_score,
         "agrees_with_winner": bool(rotation_between_deg(final, winner) < HYPOTHESIS_AGREEMENT_DEG)}
        for final, final_score, _, (axis, factor), start_score in runs
    ]
    return winner, records, first_step + stage.steps


def objective_with_anchors(losses: PhotoLosses, start_ns: Sim3, settings: RegistrationSettings, anchor: Optional[Anchoring]) -> Callable[[Sim3], float]:
    """numpy Sim3 (meta -> dataparser) -> the trimmed mean of `losses` plus the keypoint term (weighted by the
    trimmed mean at `start_ns`, as a stage starting there would weigh it)."""
    rule = TrimmingRule.of(settings)
    dense = lambda transform: rule.trimmed_mean(objective_at(losses, transform))
    if not anchor:
        return dense
    term = anchor.term(losses.objective.teacher.grid_size, dense(start_ns))
    return lambda transform: dense(transform) + anchor.cost(term, transform)


SCALE_SEARCH = (2.0, 17, 4 * SCALE_RESOLUTION, 9)
"""The 1-D scale search of `scale_the_anchors_leave_free`: factors from 1/2 to 2 (17, log-spaced: 9% apart), then 9
around the best, 0.08 of a log unit on either side (SCALE_RESOLUTION, 2%, apart)."""


def scale_the_anchors_leave_free(
    losses: PhotoLosses, anchor: Anchoring, meta: MetaImage, transform: Sim3, settings: RegistrationSettings,
) -> tuple[Sim3, Optional[dict]]:
    """When the keypoint anchors do not fix the Sim(3)'s scale (`keypoints.anchors_fix_scale`: the anchors of one photo,
    or of photos taken from nearly one spot) and some photos have none, the Sim(3) (meta -> dataparser) scaled about
    the anchored photos' mean camera centre by the factor the main stage's objective prefers; otherwise `transform`.

    Scaling the world about a camera's centre leaves that camera's image unchanged, so one photo's anchors fix 6 of the
    Sim(3)'s 7 degrees of freedom and leave the scale where the start put it (measured on 19 real 3-5-photo meta-images
    with the anchors of one photo kept: ΔT grew with the start's scale error, median 0.033 / 0.096 / 0.186 scene units
    from 5% / 15% / 30% scale errors, while ΔR stayed at 0.1-0.6°); so do the anchors of a photo and its zoomed twin
    taken from the same spot. The other photos do see the scale: their cameras move along the rays from the anchored
    ones. The search scores factors (SCALE_SEARCH) by the robust objective of those photos plus the keypoint term,
    weighted as a stage weighs it (about one photo's centre that term does not change). The anchored photos' own losses
    do not change either, and counted with the others they would fill the trimmed mean's kept half (their renders fit
    best) and hide the scale from it: the anchors of a photo and its zoomed twin in a 4-photo meta-image left the
    search flat. Returns the best, with a record of the search."""
    term = anchor.term(losses.objective.teacher.grid_size, 1.0) if anchor else None
    if not term or term.photos >= len(meta.photos):
        return transform, None
    motion, error = term.scale_motion_px(transform)
    if anchors_fix_scale(motion, error):
        return transform, None
    centre = transform.apply(term.centres.mean(0).numpy())
    unanchored = [index for index, photo in enumerate(losses.photos) if photo.name not in set(term.names)]
    rule = TrimmingRule.of(settings)
    dense = lambda candidate: rule.trimmed_mean(objective_at(losses, candidate, unanchored))
    weight = dense(transform)  # the term's weight, as a stage starting here would set it (its cost is linear in it)
    score = lambda candidate: dense(candidate) + weight * anchor.cost(term, candidate)

    def scaled(log_factor: float) -> Sim3:
        return Sim3.scaling_about(np.exp(log_factor), centre) @ transform

    def best(log_factors: Array) -> tuple[float, float]:
        scores = [score(scaled(value)) for value in log_factors]
        index = min(range(len(scores)), key=lambda i: (scores[i], abs(log_factors[i])))  # ties: the smallest change
        return float(log_factors[index]), float(scores[index])

    widest, coarse, step, fine = SCALE_SEARCH
    chosen, _ = best(np.linspace(-np.log(widest), np.log(widest), coarse))
    chosen, value = best(chosen + np.linspace(-step, step, fine))
    record = {"photos": term.names, "anchor_motion_px": round(motion, 3), "anchor_error_px": round(error, 3)}
    return scaled(chosen), record | {"factor": round(float(np.exp(chosen)), 4), "objective": value}


HYPOTHESIS_AGREEMENT_DEG = 2.0
"""Optimised hypotheses that end within this rotation of the winner agree with it."""


def hypotheses_around(start_ns: Sim3, meta: MetaImage, count: int, angle_deg: float) -> list[tuple[list[float], Sim3]]:
    """`count` (axis, Sim3): `start_ns` rotated by `angle_deg` about the cameras' centroid, axes on a Fibonacci sphere."""
    golden = np.pi * (3.0 - np.sqrt(5.0))
    hypotheses = []
    for k in range(count):
        z = 1.0 - 2.0 * (k + 0.5) / count
        axis = np.array([np.sqrt(1 - z * z) * np.cos(golden * k), np.sqrt(1 - z * z) * np.sin(golden * k), z])
        delta = torch.zeros(7, dtype=torch.float64)
        delta[:3] = torch.from_numpy(axis * np.radians(angle_deg))
        hypotheses.append((axis.round(4).tolist(), moved_about_centroid(start_ns, meta, delta)))
    return hypotheses


def scaled_about_centroid(transform: Sim3, meta: MetaImage, factor: float) -> Sim3:
    """`transform` (meta -> dataparser) followed by a scaling by `factor` about the moved cameras' centroid."""
    if factor == 1.0:
        return transform
    delta = torch.zeros(7, dtype=torch.float64)
    delta[6] = float(np.log(factor))
    return moved_about_centroid(transform, meta, delta)


def moved_about_centroid(transform: Sim3, meta: MetaImage, delta: Tensor) -> Sim3:
    """U(delta) about the centroid of the cameras moved by `transform`, then `transform` (numpy Sim3s,
    meta -> dataparser; delta [7] = (omega, nu, log s))."""
    return (Sim3.update(delta, torch.from_numpy(meta.centroid_under(transform))) @ transform.to_torch()).numpy()


def rotation_between_deg(a: Sim3, b: Sim3) -> float:
    """Angle of the rotation between two similarities (degrees)."""
    return rotation_angle_deg(np.asarray(a.rotation) @ np.asarray(b.rotation).T)


def current_estimate(delta: Tensor, centre: Tensor, start: Sim3) -> Sim3:
    """U(delta) o T0 as a detached numpy Sim3 (meta -> dataparser)."""
    with torch.no_grad():
        return (Sim3.update(delta, centre) @ start).numpy()
