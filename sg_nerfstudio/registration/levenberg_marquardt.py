"""Levenberg-Marquardt on the 7 registration parameters: the fast alternative to the paper's Adam loop.

Same objective as Adam (`optimize.Objective`: per-photo L1/L2 distance between the frozen model's
decoded features and the teacher maps, aggregated by LTS / fixed-LTS / IRLS / none), minimised by
Gauss-Newton steps with Marquardt damping instead of 12000 first-order steps. Why: the objective is a
sum of many residuals (photos x grid cells x channels) in only 7 unknowns, and its valleys are narrow:
rotating a camera group about the scene it looks at changes the images only by parallax, so that
direction is nearly flat while the coupled translation is steep. First-order steps crawl along such
valleys; a Gauss-Newton step, which sees the coupling in J^T J, crosses them.

Per iteration, with delta = S x (S scales the translation by the scene depth so that one unit of every
coordinate moves the image comparably):

1. residuals r_i(x) of every photo (no autograd) and their per-photo losses; the robust aggregator
   turns these into photo weights w_i (LTS keeps the photos below the percentile of the previous
   iteration's losses, exactly as in the Adam loop);
2. Jacobians J_i [n_i, 7] by forward differences (7 more renders per photo; the renderer is
   piecewise smooth in the pose, so steps of a few tenths of a degree are used rather than
   infinitesimal ones);
3. for L1, iteratively reweighted least squares: residual weights 1 / max(|r|, eps);
4. solve (H + lambda diag(H)) dx = -g with H = sum_i w_i/n_i J_i^T W_i J_i, g = sum_i w_i/n_i J_i^T W_i r_i,
   cap the step (at most `max_rotation_step_deg` / `max_translation_step` of the depth), and accept it
   only if the weighted loss decreases (then lambda /= 3), else lambda *= 4 and solve again.

It stops after `steps` iterations or when no damping gives a decrease.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from sg_nerfstudio.registration.robust import LossKind, RobustAggregator

Array = np.ndarray
RESIDUAL_FLOOR = 1.0  # L1 reweighting floor, as a fraction of the mean absolute residual


@dataclass
class LMSettings:
    steps: int
    loss: LossKind
    finite_difference: float = 5e-3
    """Forward-difference step in x (radians for rotation, depth units for translation, log-scale)."""
    initial_damping: float = 1e-2
    max_rotation_step_deg: float = 3.0
    max_translation_step: float = 0.1
    """Largest translation per iteration as a fraction of the scene depth."""
    max_retries: int = 6


@dataclass
class LMStep:
    """One accepted (or final rejected) iteration: the photo losses it started from and what it kept."""

    x: Array  # [7] parameters after the iteration
    losses: Array  # [P] per-photo losses at the start of the iteration
    kept: Array  # [P] bool
    weights: Array  # [P]
    value: float  # weighted loss after the iteration
    damping: float
    accepted: bool


ResidualFn = Callable[[Tensor], list[Tensor]]
"""x [7] (float64) -> per-photo flat residuals [n_i] (rendered - target), without gradients."""


def levenberg_marquardt(
    residuals: ResidualFn,
    aggregator: RobustAggregator,
    settings: LMSettings,
    on_iteration: Callable[[int, LMStep], None] | None = None,
    x0: Array | None = None,
) -> tuple[Array, list[LMStep]]:
    """Minimise the robustly aggregated loss over x [7] from x0 (default 0). Returns (x, iterations)."""
    x = torch.zeros(7, dtype=torch.float64) if x0 is None else torch.as_tensor(x0, dtype=torch.float64).clone()
    damping = settings.initial_damping
    current = residuals(x)
    history: list[LMStep] = []
    n_photos = len(current)
    for iteration in range(settings.steps):
        losses = np.array([_loss(r, settings.loss) for r in current])
        _, kept, weights = aggregator(torch.from_numpy(losses), np.arange(n_photos))
        value = _weighted(losses, weights)
        hessian, gradient = _normal_equations(residuals, x, current, weights, settings)
        accepted = False
        for _ in range(settings.max_retries):
            step = _damped_step(hessian, gradient, damping, settings)
            candidate = residuals(x + step)
            candidate_value = _weighted(np.array([_loss(r, settings.loss) for r in candidate]), weights)
            if math.isfinite(candidate_value) and candidate_value < value:
                x, current, value, accepted = x + step, candidate, candidate_value, True
                damping = max(damping / 3.0, 1e-7)
                break
            damping *= 4.0
        record = LMStep(x.numpy().copy(), losses, kept, weights, value, damping, accepted)
        history.append(record)
        if on_iteration is not None:
            on_iteration(iteration, record)
        if not accepted:
            break
    return x.numpy(), history


def _loss(residual: Tensor, kind: LossKind) -> float:
    return float(residual.abs().mean() if kind == "l1" else residual.square().mean())


def _weighted(losses: Array, weights: Array) -> float:
    return float(np.sum(losses * weights) / max(np.sum(weights), 1e-12))


def _normal_equations(residuals: ResidualFn, x: Tensor, current: list[Tensor], weights: Array, settings: LMSettings):
    """H [7, 7] and g [7] of the weighted (IRLS for L1) least-squares model around x."""
    h = settings.finite_difference
    shifted = [residuals(x + h * torch.eye(7, dtype=x.dtype)[k]) for k in range(7)]
    hessian = torch.zeros(7, 7, dtype=torch.float64)
    gradient = torch.zeros(7, dtype=torch.float64)
    scale = float(np.sum(weights)) or 1.0
    for i, r in enumerate(current):
        if weights[i] <= 0:
            continue
        r = r.double()
        jacobian = torch.stack([(shifted[k][i].double() - r) / h for k in range(7)], dim=1)  # [n, 7]
        if settings.loss == "l1":
            floor = RESIDUAL_FLOOR * float(r.abs().mean()) + 1e-12
            residual_weights = 1.0 / torch.clamp(r.abs(), min=floor)
            factor = 0.5  # d|r| ~ d(r^2 / (2|r|))
        else:
            residual_weights = torch.ones_like(r)
            factor = 1.0
        photo = factor * weights[i] / (scale * r.numel())
        weighted_jacobian = jacobian * residual_weights[:, None]
        hessian += photo * (jacobian.T @ weighted_jacobian)
        gradient += photo * (weighted_jacobian.T @ r)
    return hessian, gradient


def _damped_step(hessian: Tensor, gradient: Tensor, damping: float, settings: LMSettings) -> Tensor:
    """Solve (H + damping diag(H)) dx = -g, then shrink dx to the per-iteration caps."""
    diagonal = torch.clamp(torch.diagonal(hessian), min=1e-12)
    step = torch.linalg.solve(hessian + damping * torch.diag(diagonal), -gradient)
    rotation = float(torch.linalg.norm(step[:3]))
    translation = float(torch.linalg.norm(step[3:6]))
    shrink = min(
        1.0,
        math.radians(settings.max_rotation_step_deg) / max(rotation, 1e-12),
        settings.max_translation_step / max(translation, 1e-12),
    )
    return step * shrink
