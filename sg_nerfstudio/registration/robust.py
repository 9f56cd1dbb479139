"""Per-image losses and their robust aggregation (the paper's least trimmed squares and its ablations).

`lts`: keep the images whose loss is at most the `percentile` (default 50: the median) of the *previous*
iteration's per-image losses, average the kept ones. `fixed-lts`: the kept set is decided once, from the
losses at the initial transform. `irls`: Cauchy weights 1 / (1 + (L / m)^2) with m the previous median,
held fixed within a step (iteratively reweighted least squares). `none`: the plain mean.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from sg_nerfstudio.registration.settings import LossKind, Robust


def per_image_loss(rendered: Tensor, target: Tensor, kind: LossKind) -> Tensor:
    """[C, h, w, D] rendered vs target -> [C] mean absolute (l1) or squared (l2) error."""
    difference = rendered - target
    values = difference.abs() if kind == "l1" else difference.square()
    return values.flatten(1).mean(1)


class RobustAggregator:
    """Turns the per-image losses of a batch into the scalar to minimise, remembering what it did."""

    def __init__(self, robust: Robust, percentile: float, initial_losses: np.ndarray):
        """initial_losses: [n_images] losses at the initial transform (seed the "previous iteration")."""
        if not 0.0 < percentile <= 100.0:
            raise ValueError(f"LTS percentile must be in (0, 100], got {percentile}.")
        self.robust = robust
        self.percentile = percentile
        self.previous = np.asarray(initial_losses, dtype=np.float64).copy()
        self.fixed_keep = self.previous <= np.percentile(self.previous, percentile)

    def threshold(self) -> float:
        return float(np.percentile(self.previous, self.percentile))

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
        if self.robust == "lts":
            kept = values <= self.threshold()
        elif self.robust == "fixed-lts":
            kept = self.fixed_keep[indices]
        else:
            kept = np.ones_like(values, dtype=bool)
        if not kept.any():  # every image of this batch is above the threshold: follow the best one
            kept = values == values.min()
        if self.robust == "irls":
            scale = max(float(np.median(self.previous)), 1e-12)
            weights = 1.0 / (1.0 + (values / scale) ** 2)
        else:
            weights = kept.astype(np.float64)
        counted = np.flatnonzero(weights > 0)
        objective = sum(losses[i] * float(weights[i]) for i in counted) / float(weights[counted].sum())
        self.previous[indices] = values
        return objective, kept, weights
