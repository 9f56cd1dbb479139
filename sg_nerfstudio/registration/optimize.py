"""The registration loop: optimise one Sim(3) of a whole meta-image against the frozen reference model.

Per step: choose the photos of the step (`BatchSchedule`), move their cameras by T = U(delta) o T0 in the
dataparser frame, render the model and compare with the photos (`objectives.PhotoLosses`), aggregate the
per-photo losses robustly (`robust.RobustAggregator`, LTS by default), take an Adam step on the 7
parameters delta (`robust_step`) and record what happened (`History`). Everything the caller passes in
and gets back is in the reference *world* frame.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import Callable, Optional

import numpy as np
import torch
from torch import Tensor

from sg_nerfstudio.errors import InputError
from sg_nerfstudio.geometry.meta_image import MetaImage
from sg_nerfstudio.geometry.sim3 import Sim3
from sg_nerfstudio.registration.objectives import Objective, PhotoLosses, PreparedPhoto, build_objective, prepare_photos
from sg_nerfstudio.registration.reference import ReferenceModel
from sg_nerfstudio.registration.robust import RobustAggregator
from sg_nerfstudio.registration.settings import RegistrationSettings

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
    ignored_fraction: Array  # [P] fraction of its evaluations in which each photo was ignored
    steps: int
    wall_time_s: float
    timings: dict
    near_plane: float
    settings: dict
    photo_names: list[str]
    coverage: Array  # [P] fraction of rendered pixels covered by the model at the initial transform


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


class History:
    """Per step and photo: loss, whether the robust loss kept it, its weight; and how often each was ignored."""

    def __init__(self, names: list[str]):
        self.names = names
        self.rows: list[dict] = []
        self.ignored = np.zeros(len(names))
        self.evaluated = np.zeros(len(names))

    def record(self, step: int, batch: list[int], losses: list[Tensor], kept: Array, weights: Array) -> None:
        for index, loss, keep, weight in zip(batch, [float(loss.detach()) for loss in losses], kept, weights):
            self.rows.append({"step": step, "image": self.names[index], "loss": loss, "kept": bool(keep), "weight": float(weight)})
            self.ignored[index] += not keep
            self.evaluated[index] += 1

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
    optimizer: torch.optim.Optimizer, scheduler: torch.optim.lr_scheduler.LRScheduler,
) -> tuple[list[Tensor], Array, Array]:
    """One Adam step on the robust objective of `batch` under `transform`; returns (losses, kept, weights)."""
    values, _ = losses(transform, batch)
    objective, kept, weights = aggregator(values, np.asarray(batch))
    start = time.perf_counter()
    optimizer.zero_grad()
    objective.backward()
    optimizer.step()
    scheduler.step()
    losses.timings["backward"] += time.perf_counter() - start
    return values, kept, weights


def final_evaluation(losses: PhotoLosses, final_ns: Sim3, settings: RegistrationSettings) -> tuple[Array, float]:
    """[P] losses at the final transform and their trimmed mean (the kept percentile, or all without LTS)."""
    with torch.no_grad():
        values, _ = losses(final_ns.to_torch(), list(range(len(losses.photos))))
    final = torch.stack(values).double().numpy()
    trimmed = final[final <= np.percentile(final, settings.lts_percentile)] if settings.robust != "none" else final
    return final, float(trimmed.mean())


def register(
    reference: ReferenceModel,
    meta: MetaImage,
    initial_world: Sim3,
    settings: RegistrationSettings,
    photos: Optional[list[PreparedPhoto]] = None,
    on_step: Optional[Callable[[int, Sim3], None]] = None,
    objective: Optional[Objective] = None,
) -> RegistrationResult:
    """Estimate the Sim(3) meta -> reference world starting from `initial_world`.

    `photos` and `objective` may come prepared (`prepare_photos`, `build_objective`: the teacher is built once).
    `on_step(step, transform)` is called after every step with the current estimate (meta -> world).
    """
    started = time.perf_counter()
    objective = objective or build_objective(reference, settings)
    photos = photos if photos is not None else prepare_photos(reference, meta, settings, objective)
    world_to_ns = reference.world_to_dataparser
    ns_to_world = world_to_ns.inverse()
    initial_ns = world_to_ns @ initial_world
    near_plane = effective_near_plane(meta, initial_ns, settings.near_plane)
    losses = PhotoLosses(reference, photos, objective, settings, near_plane)
    initial_losses, coverage = evaluate_start(losses, initial_ns, meta.name)
    aggregator = RobustAggregator(settings.robust, settings.lts_percentile, initial_losses)

    start = initial_ns.to_torch()
    centre = torch.from_numpy(meta.centroid_under(initial_ns))
    delta = torch.zeros(7, dtype=torch.float64, requires_grad=True)
    optimizer = torch.optim.Adam([delta], lr=settings.lr, eps=settings.adam_eps)
    gamma = (settings.lr_final / settings.lr) ** (1.0 / max(settings.steps, 1)) if settings.lr_final else 1.0
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=gamma)
    batches = BatchSchedule(len(photos), settings.images_per_step, settings.seed)
    history = History([p.name for p in photos])
    for step in range(settings.steps):
        batch = batches.next()
        values, kept, weights = robust_step(losses, aggregator, Sim3.update(delta, centre) @ start, batch, optimizer, scheduler)
        if not torch.isfinite(delta).all():
            raise FloatingPointError(f"The registration of '{meta.name}' diverged to NaN at step {step}.")
        history.record(step, batch, values, kept, weights)
        if on_step is not None:
            on_step(step, ns_to_world @ current_estimate(delta, centre, start))

    final_ns = current_estimate(delta, centre, start)
    final_losses, trimmed = final_evaluation(losses, final_ns, settings)
    return RegistrationResult(
        transform=ns_to_world @ final_ns,
        initial_transform=initial_world.numpy(),
        final_losses=final_losses,
        initial_losses=initial_losses,
        final_trimmed_loss=trimmed,
        history=history.rows,
        ignored_fraction=history.ignored_fraction(),
        steps=settings.steps,
        wall_time_s=time.perf_counter() - started,
        timings=dict(losses.timings),
        near_plane=near_plane,
        settings=asdict(settings),
        photo_names=[p.name for p in photos],
        coverage=coverage,
    )


def current_estimate(delta: Tensor, centre: Tensor, start: Sim3) -> Sim3:
    """U(delta) o T0 as a detached numpy Sim3 (meta -> dataparser)."""
    with torch.no_grad():
        return (Sim3.update(delta, centre) @ start).numpy()
