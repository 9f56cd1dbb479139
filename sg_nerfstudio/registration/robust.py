"""Per-image losses and their robust aggregation (the paper's least trimmed squares and its ablations).

`lts`: keep the images whose loss is at most the `percentile` (default 50: the median) of the *previous*
iteration's per-image losses, average the kept ones (the paper's rule). `outlier-lts`: keep the images whose
previous loss is at most m + z * s, with m the median of the previous losses and s their robust scale
(1.4826 x MAD, at least `SCALE_FLOOR` x m); only photos that stand out from the others are dropped.
`fixed-lts`: the kept set is decided once, from the losses at the initial transform. `irls`: Cauchy weights
1 / (1 + (L / m)^2) with m the previous median, held fixed within a step (iteratively reweighted least
squares). `none`: the plain mean. With `trim_after` > 0 every rule is the plain mean for that fraction of
each stage's steps first (trimming once the pose has settled).

Why `outlier-lts`: away from the answer every photo's loss sits near the same floor, so the median rule drops a photo
that is no worse than the others (a third of the evidence of a 3-photo meta-image), and a different one each step;
only near the answer do occluded photos separate (docs/measurements.md, "The robust loss").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from sg_nerfstudio.errors import InputError
from sg_nerfstudio.registration.settings import LossKind, RegistrationSettings, RobustRule

MAD_TO_SIGMA = 1.4826
"""MAD of a normal distribution x this = its standard deviation."""
SCALE_FLOOR = 0.1
"""`outlier-lts`: the robust scale is at least this fraction of the median loss, so that photos whose losses
happen to agree closely (MAD near 0, e.g. two of three) do not make every other photo an outlier."""


class RobustSettingsError(InputError):
    """A robust-loss setting outside its range."""


def check_robust_settings(settings: RegistrationSettings) -> None:
    """RobustSettingsError naming the first robust-loss setting outside its range."""
    if not 0.0 < settings.robust.lts_percentile <= 100.0:
        raise RobustSettingsError(f"--robust.lts-percentile must be in (0, 100], got {settings.robust.lts_percentile}.")
    if not settings.robust.outlier_z > 0.0:
        raise RobustSettingsError(f"--robust.outlier-z must be positive (robust scales above the median), got {settings.robust.outlier_z}.")
    if not 0.0 <= settings.robust.trim_after < 1.0:
        raise RobustSettingsError(f"--robust.trim-after must be in [0, 1) (a fraction of each stage's steps), got {settings.robust.trim_after}.")


def per_image_loss(rendered: Tensor, target: Tensor, kind: LossKind) -> Tensor:
    """[C, h, w, D] rendered vs target -> [C] mean absolute (l1) or squared (l2) error."""
    difference = rendered - target
    values = difference.abs() if kind == "l1" else difference.square()
    return values.flatten(1).mean(1)


@dataclass(frozen=True)
class TrimmingRule:
    """Which photos a robust objective counts, from a set of per-photo losses (see the module docstring)."""

    robust: RobustRule
    percentile: float = 50.0  # lts, fixed-lts
    z: float = 3.0  # outlier-lts

    def __post_init__(self):
        if not 0.0 < self.percentile <= 100.0:
            raise ValueError(f"LTS percentile must be in (0, 100], got {self.percentile}.")

    @classmethod
    def of(cls, settings: RegistrationSettings) -> "TrimmingRule":
        return cls(settings.robust.rule, settings.robust.lts_percentile, settings.robust.outlier_z)

    def threshold(self, losses: np.ndarray) -> float:
        """The largest loss that still counts among [P] per-photo `losses` (inf: every photo counts). irls weighs
        rather than trims; its reported trimmed loss (and the verdict's objective) uses the percentile."""
        losses = np.asarray(losses, dtype=np.float64)
        if self.robust in ("lts", "fixed-lts", "irls"):
            return float(np.percentile(losses, self.percentile))
        if self.robust == "outlier-lts":
            median = float(np.median(losses))
            scale = max(MAD_TO_SIGMA * float(np.median(np.abs(losses - median))), SCALE_FLOOR * median)
            return median + self.z * scale
        return float("inf")

    def trimmed_mean(self, losses: np.ndarray) -> float:
        """The rule's aggregate of [P] per-photo losses judged among themselves: mean of those that count."""
        losses = np.asarray(losses, dtype=np.float64)
        return float(losses[losses <= self.threshold(losses)].mean())


class RobustAggregator:
    """Turns the per-image losses of a batch into the scalar to minimise, remembering what it did."""

    def __init__(self, rule: TrimmingRule, initial_losses: np.ndarray, warmup_steps: int = 0):
        """initial_losses: [n_images] losses at the initial transform (seed the "previous iteration").
        warmup_steps: calls in which every image counts (the plain mean) before the rule applies."""
        if warmup_steps < 0:
            raise ValueError(f"Robust warm-up steps must be >= 0, got {warmup_steps}.")
        self.rule, self.warmup_steps, self.calls = rule, warmup_steps, 0
        self.previous = np.asarray(initial_losses, dtype=np.float64).copy()
        self.fixed_keep = self.previous <= rule.threshold(self.previous)

    def threshold(self) -> float:
        return self.rule.threshold(self.previous)

    def __call__(self, losses: list[Tensor], indices: np.ndarray) -> tuple[Tensor, np.ndarray, np.ndarray]:
        """Aggregate the batch.

        Args:
            losses: B per-image scalar losses (with gradients), kept apart so that the objective's graph
                reaches only the images that count: an ignored image costs no backward pass.
            indices: [B] which images of the meta-image they belong to.

        Returns:
            the scalar objective, kept [B] bool (whether each image counted), weights [B].
        """
        values = torch.stack([loss.detach() for loss in losses]).double().cpu().numpy()
        robust = self.rule.robust if self.calls >= self.warmup_steps else "none"
        self.calls += 1
        if robust in ("lts", "outlier-lts"):
            kept = values <= self.threshold()
        elif robust == "fixed-lts":
            kept = self.fixed_keep[indices]
        else:
            kept = np.ones_like(values, dtype=bool)
        if not kept.any():  # every image of this batch is above the threshold: follow the best one
            kept = values == values.min()
        if robust == "irls":
            scale = max(float(np.median(self.previous)), 1e-12)
            weights = 1.0 / (1.0 + (values / scale) ** 2)
        else:
            weights = kept.astype(np.float64)
        counted = np.flatnonzero(weights > 0)
        objective = sum(losses[i] * float(weights[i]) for i in counted) / float(weights[counted].sum())
        self.previous[indices] = values
        return objective, kept, weights
