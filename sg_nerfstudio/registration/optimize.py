"""The registration of one meta-image: one Sim(3) against the frozen reference model (`register`, the entry point).

Phases:
1. `anchored_start.start_from_anchors`: with keypoint anchors, the render-free pre-alignment, the camera fit and the
   scale the anchors leave free; without them, the start as given.
2. `run_stages`: the coarse-to-fine stages (several starts at the first with hypotheses or other starts, such as the
   dense initialiser's: hypotheses.py), the main stage, the last stage; each Adam on delta over its per-photo losses
   (stages.py).
3. `assess`: the final evaluation and the verdict's evidence, probed around the result (verdict.py, other_minimum.py).

Everything the caller passes in and gets back is in the reference *world* frame; the phases work in nerfstudio's
dataparser frame (`ReferenceModel.world_to_dataparser`), transforms meta -> dataparser.
"""

from __future__ import annotations

import math
import time
from contextlib import nullcontext
from dataclasses import dataclass, field
from typing import Callable, ContextManager, Optional, Sequence

import numpy as np
import torch

from sg_nerfstudio.errors import InputError
from sg_nerfstudio.geometry.meta_image import MetaImage
from sg_nerfstudio.geometry.sim3 import Sim3
from sg_nerfstudio.initialisers.estimate import PhotoKeypoints
from sg_nerfstudio.registration import other_minimum
from sg_nerfstudio.registration.depth_agreement import DepthAgreement, summarise
from sg_nerfstudio.registration.hypotheses import best_hypothesis
from sg_nerfstudio.registration.anchored_start import AnchoredStart, Anchoring, prealigns, start_from_anchors
from sg_nerfstudio.registration.objectives import Objective, PhotoLosses, PreparedPhoto, build_objective, prepare_photos
from sg_nerfstudio.registration.reference import ReferenceModel
from sg_nerfstudio.registration.robust import TrimmingRule, check_robust_settings
from sg_nerfstudio.registration.schedules import History
from sg_nerfstudio.registration.settings import RegistrationSettings, as_record, check_ranges
from sg_nerfstudio.registration.stages import (
    Stage, coarse_stages, objective_with_anchors, optimise_stage, refine_stages, refines, uses_anchors,
)
from sg_nerfstudio.registration.verdict import Evidence, Verdict, decide, failure, gather_evidence, orbit_rise, probe_sizes
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
    hypotheses: list[dict] = field(default_factory=list)  # with settings.hypotheses.count: each optimised start and its end
    rendered_model: dict = field(default_factory=dict)
    """What the main stage rendered at its last cull (`rendered_model_record`): the reference's Gaussians, those
    rendered after culling and level of detail, the merge voxel (render pixels; 0: none) and the culls."""
    focal_scales: dict[str, float] = field(default_factory=dict)
    """With `settings.camera_fit.focal`: photo name -> the scale of its SfM focal length the registration fitted and
    rendered with (photos not listed kept theirs)."""
    pose_corrections: dict[str, dict[str, float]] = field(default_factory=dict)
    """With `settings.camera_fit.photo_poses`: photo name -> how far the registration moved its camera from where `transform`
    puts the meta-image's own camera: {"rotation_deg", "centre_shift" (reference world units)} (photos not listed were
    not moved)."""
    radial_k1: dict[int, float] = field(default_factory=dict)
    """With `settings.camera_fit.distortion`: COLMAP camera id -> the first radial coefficient the registration fitted and
    undistorted its photos with (cameras not listed kept theirs)."""
    photo_poses: dict[str, Array] = field(default_factory=dict)
    """With `settings.camera_fit.photo_poses`: photo name -> [3, 4] cam_from_world (OpenCV) in the reference world of each
    photo the registration moved, where its last stages rendered it (the others sit at `transform` applied to their own
    pose)."""
    scale_search: Optional[dict] = None
    """When the keypoint anchors left the scale free (`scale_the_anchors_leave_free`: one photo's, or those of photos
    taken from nearly one spot): the anchored photos, how far a 2% scale change moved their keypoints and their median
    error (pixels), the factor chosen about their mean camera centre and the objective there; None otherwise."""

    @property
    def start_won(self) -> str:
        """The start whose end won: "given" (also when only one ran), "around" (a rotation of it) or another start's
        label (e.g. "dense")."""
        return next((h["start"] for h in self.hypotheses if h["won"]), "given")


def register(
    reference: ReferenceModel,
    meta: MetaImage,
    initial_world: Sim3,
    settings: RegistrationSettings,
    photos: Optional[list[PreparedPhoto]] = None,
    on_step: Optional[Callable[[int, Sim3], None]] = None,
    objective: Optional[Objective] = None,
    keypoints: Optional[list[PhotoKeypoints]] = None,
    other_starts: Sequence[tuple[str, Sim3]] = (),
) -> RegistrationResult:
    """Estimate the Sim(3) meta -> reference world starting from `initial_world` (the three phases of the module docstring).

    Stages: the coarse-to-fine stages of the settings (if any; hypotheses around the start at the
    coarsest), then the main stage at the settings' teacher size, then the last stage (if any). The
    verdict and the final losses are the main stage's objective (the one its thresholds were calibrated on).
    `photos` and `objective` may come prepared for the main stage (`prepare_photos`, `build_objective`: the
    teacher is built once). `on_step(step, transform)` is called after every step of every stage
    (`total_steps(settings, anchored)` in all) with the current estimate (meta -> world). `keypoints`: the photos'
    verified SIFT correspondences with the reference (`Initialiser.keypoints`); with `settings.anchors.weight > 0`
    every stage adds their reprojection term (registration/anchored_start), and with `settings.camera_fit.focal` / `settings.camera_fit.photo_poses` the photos' focal
    lengths / poses fitted to them before the first render are used by every stage (`RegistrationResult.focal_scales`,
    `pose_corrections`); with moved poses the returned transform is the final one composed with the Sim(3) that maps
    the given cameras onto the moved ones (`geometry.alignment.align_cameras`). `other_starts`: (label, meta -> world)
    starts optimised over the first stage beside `initial_world` where no keypoint anchors hold the meta-image (e.g.
    ("dense", the dense initialiser's start): `hypotheses.best_hypothesis`); the end the main stage's objective scores
    lowest wins and `RegistrationResult.hypotheses` says which.
    """
    started = time.perf_counter()
    check_ranges(settings)
    check_robust_settings(settings)
    objective = objective or build_objective(reference, settings)
    ns_to_world = reference.world_to_dataparser.inverse()
    initial_ns = reference.world_to_dataparser @ initial_world
    near_plane = effective_near_plane(meta, initial_ns, settings.objective.near_plane)

    def main_losses(meta: MetaImage, prepared: Optional[list[PreparedPhoto]]) -> PhotoLosses:
        prepared = prepared if prepared is not None else prepare_photos(reference, meta, settings, objective)
        return PhotoLosses(reference, prepared, objective, settings, near_plane)

    start = start_from_anchors(meta, photos, initial_ns, settings, reference.world_to_dataparser, keypoints, objective.teacher.grid_size, main_losses)
    meta, photos, current, scale_search = start.meta, start.losses.photos, start.transform, start.scale_search
    main_steps, main_lr = main_schedule(settings, start.prealigned)
    main = Stage("main", start.losses, main_steps, main_lr, settings.optimiser.lr_final)
    initial_losses, coverage = evaluate_start(main.losses, initial_ns @ start.camera_shift.inverse(), meta.name)  # the given cameras at the start

    history = History([p.name for p in photos])
    report = (lambda step, estimate: on_step(step, ns_to_world @ estimate)) if on_step is not None else None
    stages = coarse_stages(reference, meta, settings, near_plane) + [main] + refine_stages(reference, meta, settings, near_plane, bool(start.anchor), main)
    others = [] if uses_anchors(settings, bool(start.anchor)) else [(label, reference.world_to_dataparser @ t) for label, t in other_starts]
    current, hypotheses, step = run_stages(stages, main, meta, current, initial_ns, initial_losses, settings, history, report, start.anchor, others)

    final_losses, trimmed, evidence, verdict_s = assess(main, meta, current, initial_losses, settings, start, scale_search)
    evidence.hypothesis_margin, evidence.hypothesis_elsewhere_deg = hypothesis_margin(hypotheses)
    distinct = {id(stage.losses): stage.losses for stage in stages}.values()  # a refine stage may share the main stage's
    timings = {key: sum(losses.timings[key] for losses in distinct) for key in main.losses.timings}
    timings["verdict"] = verdict_s  # the probes' renders (also counted in "render" and "loss")
    return RegistrationResult(
        transform=ns_to_world @ current @ start.camera_shift,
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
        settings=as_record(settings),
        photo_names=[p.name for p in photos],
        coverage=coverage,
        verdict=decide(evidence),
        hypotheses=hypotheses,
        rendered_model=rendered_model_record(reference, main.losses),
        focal_scales=start.fit.focal_scales,
        radial_k1=start.fit.radial_k1,
        pose_corrections=start.pose_corrections(current.scale * ns_to_world.scale),
        photo_poses={photo.name: (ns_to_world @ current).move_camera(photo.cam_from_world) for photo in meta.photos if photo.name in start.fit.poses},
        scale_search=scale_search,
    )


def run_stages(
    stages: list[Stage], main: Stage, meta: MetaImage, start_ns: Sim3, initial_ns: Sim3, initial_losses: Array, settings: RegistrationSettings,
    history: History, on_step: Optional[Callable[[int, Sim3], None]], anchor: Anchoring, other_starts: Sequence[tuple[str, Sim3]] = (),
) -> tuple[Sim3, list[dict], int]:
    """Phase 2 of `register`: the stages in order from `start_ns` (meta -> dataparser), the first from several starts with
    `settings.hypotheses.count` or `other_starts` ((label, meta -> dataparser)); (the result, the starts' records, the
    number of steps). `initial_losses` [P]: the main stage's losses at `initial_ns`, which seed its robust rule when it
    runs first from there."""
    current, step, hypotheses = start_ns, 0, []
    for index, stage in enumerate(stages):
        if index == 0 and (settings.hypotheses.count > 0 or other_starts):
            current, hypotheses, step = best_hypothesis(stage, main.losses, meta, current, settings, history, step, on_step, anchor, other_starts)
        else:
            seed = initial_losses if stage is main and index == 0 and current is initial_ns else None  # the start's losses, if still the start
            current, step = optimise_stage(stage, meta, current, settings, history, step, on_step, seed, anchor)
    return current, hypotheses, step


def assess(
    main: Stage, meta: MetaImage, result: Sim3, initial_losses: Array, settings: RegistrationSettings, start: AnchoredStart,
    scale_search: Optional[dict],
) -> tuple[Array, float, Evidence, float]:
    """Phase 3 of `register`: the main stage's [P] losses at `result` (meta -> dataparser), their trimmed mean, the
    verdict's evidence (`verdict.gather_evidence`; the anchors' errors where there are anchors, the orbit probes and the
    look for another minimum where there are none) and the seconds its probes took."""
    with held_for_probes(main.losses, meta, result):
        final_losses, final_coverage, trimmed, depth = final_evaluation(main.losses, result, settings)
        probing = time.perf_counter()
        evidence = gather_evidence(
            main.losses, meta, result, final_losses, final_coverage, initial_losses, TrimmingRule.of(settings), depth,
            scale_search["photos"] if scale_search else None,
        )
    evidence.camera_fit_refused = start.fit.refused or None
    final_anchors = start.anchor.term(main.losses.objective.teacher.grid_size, 1.0)
    if final_anchors is not None:
        evidence.keypoint_error_cells, evidence.keypoint_photos = final_anchors.median_error_cells(result), final_anchors.photos
        evidence.keypoint_scale_motion_px, evidence.keypoint_error_px = final_anchors.scale_motion_px(result)
    if not uses_anchors(settings, bool(start.anchor)) and failure(evidence) is None:  # a failed result needs no second look
        evidence.orbit_rise = orbit_rise(main.losses, meta, result, final_losses, TrimmingRule.of(settings))  # culled per pose
        record_other_minimum(evidence, main, meta, result, final_losses, settings)
    return final_losses, trimmed, evidence, time.perf_counter() - probing


def hypothesis_margin(hypotheses: list[dict]) -> tuple[Optional[float], Optional[float]]:
    """(how much higher, relative to the winner, the best optimised hypothesis that ended elsewhere scored, how far
    from the winner it ended in degrees); (None, None) when every one agrees with the winner (or there were none)."""
    elsewhere = [h for h in hypotheses if not h["agrees_with_winner"]]
    if not elsewhere:
        return None, None
    best = min(elsewhere, key=lambda h: h["final_objective"])
    winner = min(h["final_objective"] for h in hypotheses)
    return best["final_objective"] / max(winner, 1e-12) - 1.0, best["rotation_from_winner_deg"]


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


def final_evaluation(losses: PhotoLosses, final_ns: Sim3, settings: RegistrationSettings) -> tuple[Array, Array, float, DepthAgreement]:
    """[P] losses and [P] coverage at the final transform, the losses' trimmed mean (those the robust rule
    counts) and the depth agreement of the photos' sparse points there (one render for all)."""
    with torch.no_grad():
        values, coverage, ratios = losses.evaluate(final_ns.to_torch(), list(range(len(losses.photos))), with_depth=True)
    final = torch.stack(values).double().numpy()
    return final, coverage.double().numpy(), TrimmingRule.of(settings).trimmed_mean(final), summarise(ratios)


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


def rendered_model_record(reference: ReferenceModel, losses: PhotoLosses) -> dict:
    """{gaussians, rendered, voxel_pixels, culls} of a stage's losses at its last cull (every Gaussian, no cull,
    when it does not cull)."""
    visible = losses.visible
    if visible is None:
        return {"gaussians": reference.count, "rendered": reference.count, "voxel_pixels": 0.0, "culls": 0}
    return {"gaussians": reference.count, "rendered": visible.subset.count, "voxel_pixels": visible.voxel_pixels, "culls": visible.culls}


def main_schedule(settings: RegistrationSettings, prealigned: bool) -> tuple[int, float]:
    """(steps, initial learning rate) of the main stage: `anchors.main_steps` / `anchors.main_lr` after the keypoint
    pre-alignment where the settings give them, else `steps` / `lr`."""
    if not prealigned:
        return settings.optimiser.steps, settings.optimiser.lr
    steps = settings.anchors.main_steps if settings.anchors.main_steps is not None else settings.optimiser.steps
    return steps, settings.anchors.main_lr if settings.anchors.main_lr is not None else settings.optimiser.lr


def total_steps(settings: RegistrationSettings, anchored: bool = False, other_starts: int = 0) -> int:
    """Steps of all stages (what `on_step` counts up to) for a meta-image with (`anchored`) or without keypoint
    anchors and with `other_starts` starts beside the given one (ignored when anchored): each optimised start runs the
    first stage."""
    main = main_schedule(settings, prealigns(settings, anchored))[0]
    first = settings.coarse_to_fine.steps if settings.coarse_to_fine.factors else main
    runs = min(settings.hypotheses.count + 1, max(1, settings.hypotheses.kept)) if settings.hypotheses.count else 1
    runs += 0 if uses_anchors(settings, anchored) else other_starts
    refine = settings.last_stage.steps if refines(settings, anchored) else 0
    return main + len(settings.coarse_to_fine.factors) * settings.coarse_to_fine.steps + (runs - 1) * first + refine
