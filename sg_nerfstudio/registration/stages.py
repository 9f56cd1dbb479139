"""One optimisation stage: Adam on the 7 parameters delta of U(delta) o T0 over a stage's per-photo losses.

Per step: choose the photos of the step (`schedules.RetrimSchedule`), move their cameras by T = U(delta) o T0 in the
dataparser frame (about `update_centre`), render the model and compare with the photos (`objectives.PhotoLosses`),
aggregate the per-photo losses robustly (`robust.RobustAggregator`, LTS by default), add the keypoint anchors' term
where there are anchors, take an Adam step (`robust_step`) and record what happened (`schedules.History`).

The stages a registration runs (`optimize.register`): the coarse-to-fine stages (`coarse_stages`), the main stage,
and the refine stage with its own descriptor (`refine_stages`). Transforms are numpy Sim3s meta -> dataparser.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Optional

import numpy as np
import torch
from torch import Tensor

from sg_nerfstudio.features import teacher_input_size
from sg_nerfstudio.geometry.meta_image import MetaImage
from sg_nerfstudio.geometry.sim3 import Sim3
from sg_nerfstudio.registration.objectives import PhotoLosses, build_objective, objective_teacher_config, prepare_photos, refine_settings
from sg_nerfstudio.registration.reference import ReferenceModel
from sg_nerfstudio.registration.robust import RobustAggregator, TrimmingRule
from sg_nerfstudio.registration.schedules import History, RetrimSchedule
from sg_nerfstudio.registration.settings import RegistrationSettings

if TYPE_CHECKING:  # the anchored start builds on the stages; they only take its anchors
    from sg_nerfstudio.registration.anchored_start import Anchoring, KeypointTerm

Array = np.ndarray


@dataclass
class Stage:
    """One optimisation stage: the per-photo losses it minimises (teacher size, render size) and its schedule."""

    name: str  # "coarse-<teacher input size>", "main", "refine-<teacher>" (the history's stage column)
    losses: PhotoLosses
    steps: int
    lr: float
    lr_final: Optional[float]


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
    optimizer = torch.optim.Adam([delta], lr=stage.lr, eps=settings.optimiser.adam_eps)
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


def warmup_steps(settings: RegistrationSettings, steps: int) -> int:
    """Steps of a `steps`-step stage in which every photo counts before the robust rule trims (`trim_after`)."""
    return int(round(settings.robust.trim_after * steps))


def update_centre(meta: MetaImage, transform: Sim3, settings: RegistrationSettings) -> Array:
    """[3] the point (dataparser frame) the update rotates and scales about (`settings.optimiser.update_centre`)."""
    return meta.look_at_under(transform) if settings.optimiser.update_centre == "look-at" else meta.centroid_under(transform)


def current_estimate(delta: Tensor, centre: Tensor, start: Sim3) -> Sim3:
    """U(delta) o T0 as a detached numpy Sim3 (meta -> dataparser)."""
    with torch.no_grad():
        return (Sim3.update(delta, centre) @ start).numpy()


def objective_at(losses: PhotoLosses, meta_to_dataparser: Sim3, indices: Optional[list[int]] = None) -> Array:
    """[P] per-photo losses of every photo (or [len(indices)] of those photos) under a numpy Sim3 (meta -> dataparser),
    without gradients."""
    with torch.no_grad():
        indices = list(range(len(losses.photos))) if indices is None else indices
        return torch.stack(losses(meta_to_dataparser.to_torch(), indices)[0]).double().numpy()


def objective_with_anchors(losses: PhotoLosses, start_ns: Sim3, settings: RegistrationSettings, anchor: Optional[Anchoring]) -> Callable[[Sim3], float]:
    """numpy Sim3 (meta -> dataparser) -> the trimmed mean of `losses` plus the keypoint term (weighted by the
    trimmed mean at `start_ns`, as a stage starting there would weigh it)."""
    rule = TrimmingRule.of(settings)
    dense = lambda transform: rule.trimmed_mean(objective_at(losses, transform))
    if not anchor:
        return dense
    term = anchor.term(losses.objective.teacher.grid_size, dense(start_ns))
    return lambda transform: dense(transform) + anchor.cost(term, transform)


def uses_anchors(settings: RegistrationSettings, anchored: bool) -> bool:
    """Whether keypoint anchors hold the pose: the meta-image has them (`anchored`) and the settings weigh them."""
    return anchored and settings.anchors.weight > 0


def refines(settings: RegistrationSettings, anchored: bool) -> bool:
    """Whether the refine stage runs: `last_stage.steps` > 0, and the meta-image has no keypoint anchors unless
    `last_stage.with_anchors`."""
    return settings.last_stage.steps > 0 and (settings.last_stage.with_anchors or not uses_anchors(settings, anchored))


def refine_stages(reference: ReferenceModel, meta: MetaImage, settings: RegistrationSettings, near_plane: float, anchored: bool, main: Stage) -> list[Stage]:
    """[] or the refine stage: `refine_settings` (its own teacher and photo targets unless it is the main stage's),
    `last_stage.steps` from `last_stage.lr` decaying to `optimiser.lr_final`."""
    if not refines(settings, anchored):
        return []
    own = refine_settings(settings)
    if own == settings:  # the main stage's objective: its photos and targets serve
        losses = main.losses
    else:
        objective = build_objective(reference, own)
        losses = PhotoLosses(reference, prepare_photos(reference, meta, own, objective), objective, own, near_plane)
    return [Stage(f"refine-{losses.objective.teacher_config.name}", losses, settings.last_stage.steps, settings.last_stage.lr, settings.optimiser.lr_final)]


MIN_COARSE_GRID = 8
"""Coarse stages whose teacher grid would have fewer cells on the long side are skipped (a 4-cell descriptor
of a photo matches almost any pose: on the tiny test scene such a stage sent a start at the truth 15° away)."""


def coarse_stages(reference: ReferenceModel, meta: MetaImage, settings: RegistrationSettings, near_plane: float) -> list[Stage]:
    """The coarse-to-fine stages, coarsest first: the teacher at its input size divided by each factor (cells that
    many times larger in the photo), the learning rate multiplied by it and decaying tenfold within the stage."""
    stages = []
    main_size = teacher_input_size(objective_teacher_config(reference, settings))
    for factor in sorted(settings.coarse_to_fine.factors, reverse=True):  # each >= 2 (settings.check_ranges, run by `register`)
        stage_settings = settings.changed(objective={"teacher_input_size": main_size // factor})
        objective = build_objective(reference, stage_settings)
        if objective.teacher.grid_size < MIN_COARSE_GRID:
            continue
        photos = prepare_photos(reference, meta, stage_settings, objective)
        lr = settings.optimiser.lr * factor
        stages.append(Stage(f"coarse-{main_size // factor}", PhotoLosses(reference, photos, objective, stage_settings, near_plane), settings.coarse_to_fine.steps, lr, lr / 10))
    return stages
