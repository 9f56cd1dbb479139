"""Which photos each step of a stage renders, and what happened to each photo: the bookkeeping of `stages.optimise_stage`.

- `BatchSchedule`: every photo each step (the paper), or seeded batches that see every photo once per epoch.
- `RetrimSchedule`: with `retrim_every` k > 1, the robust rule re-decides which photos count only every k-th step; the
  steps between render only the photos it counted.
- `History`: per step and photo the loss, whether the robust rule kept it and its weight (losses.csv, the loss curve).
"""

from __future__ import annotations

from typing import Optional

import numpy as np
from torch import Tensor

from sg_nerfstudio.registration.settings import RegistrationSettings

Array = np.ndarray


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
        self.batches = BatchSchedule(count, settings.optimiser.photos_per_step, settings.seed)
        self.every, self.warmup_steps, self.calls = settings.robust.retrim_every, warmup_steps, 0
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
