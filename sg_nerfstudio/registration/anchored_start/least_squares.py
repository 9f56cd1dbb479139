"""Levenberg-Marquardt for small robust least-squares problems in torch: the prior camera fit's solver.

Problem (`RobustResiduals`): cost(x) = sum_n a_n log(1 + |r_n(x)|^2) + sum_k q_k(x)^2, with r_n [D] residual vectors in
units of a Cauchy kernel (a keypoint's 2-D reprojection error over the kernel scale), a_n >= 0 their weights and q_k
quadratic residuals (priors). Each iteration weighs the robust rows by the kernel's derivative a_n / (1 + |r_n|^2)
(iteratively reweighted least squares), solves the damped normal equations (H + lambda diag(H)) dx = -g with the
Jacobian from forward-mode AD (`torch.func.jacfwd`), and adapts lambda by the ratio of actual to predicted decrease
(Nielsen's rule).

Why by hand: `scipy.optimize.least_squares` applies its robust loss to each scalar residual, while the keypoint term's
Cauchy kernel acts on each keypoint's 2-D error (isotropic, the function the rendered stages minimise); torch has no
least-squares solver; pycolmap's adjuster has no priors on intrinsics (it is the other solver, bundle_adjustment.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor


INITIAL_DAMPING = 1e-4
"""lambda at the first iteration: nearly Gauss-Newton, as the camera fit starts pre-aligned, near its minimum."""
MAX_DAMPING = 1e16
"""No step lowers the cost even at this lambda: the minimum, to rounding."""


@dataclass
class RobustResiduals:
    """Residuals at one point: `robust` [N, D] in kernel units, `weights` [N] their a_n (0: not counted, e.g. a point
    behind its camera), `quadratic` [K] the q_k."""

    robust: Tensor
    weights: Tensor
    quadratic: Tensor

    def cost(self) -> Tensor:
        """sum_n a_n log(1 + |r_n|^2) + sum_k q_k^2 (scalar)."""
        return (self.weights * torch.log1p(self.robust.pow(2).sum(-1))).sum() + self.quadratic.pow(2).sum()


@dataclass
class Solution:
    """`x` [n] where the solver stopped, `iterations` taken, `converged`: the cost stopped falling (relative change
    under the tolerance) or the gradient vanished, rather than running out of iterations or damping."""

    x: Tensor
    iterations: int
    converged: bool


def levenberg_marquardt(
    residuals: Callable[[Tensor], RobustResiduals], x0: Tensor, max_iterations: int, relative_tolerance: float = 1e-12,
    gradient_tolerance: float = 1e-12,
) -> Solution:
    """Minimise `residuals(x).cost()` from `x0` [n] (float64) by at most `max_iterations` Levenberg-Marquardt steps
    (module docstring). Stops when an accepted step lowers the cost by less than `relative_tolerance` of it, when the
    largest gradient component is under `gradient_tolerance` times the cost, or when no damping finds a lower cost."""
    x = x0.detach().clone()
    cost = float(residuals(x).cost())
    damping, growth = INITIAL_DAMPING, 2.0

    def parts(point: Tensor) -> tuple[tuple[Tensor, Tensor], tuple[Tensor, Tensor, Tensor]]:
        value = residuals(point)
        return (value.robust, value.quadratic), (value.robust, value.weights, value.quadratic)

    jacobian = torch.func.jacfwd(parts, has_aux=True)
    for iteration in range(1, max_iterations + 1):
        (robust_jacobian, quadratic_jacobian), values = jacobian(x)  # [N, D, n], [K, n]
        current = RobustResiduals(*values)
        irls = current.weights / (1.0 + current.robust.pow(2).sum(-1))  # [N]
        hessian = torch.einsum("n,ndi,ndj->ij", irls, robust_jacobian, robust_jacobian) + quadratic_jacobian.T @ quadratic_jacobian
        gradient = torch.einsum("n,ndi,nd->i", irls, robust_jacobian, current.robust) + quadratic_jacobian.T @ current.quadratic
        if float(gradient.abs().max()) <= gradient_tolerance * max(cost, 1e-300):
            return Solution(x, iteration - 1, True)
        scaling = torch.diagonal(hessian).clamp_min(1e-12 * float(torch.diagonal(hessian).max()) + 1e-300)
        while True:
            try:
                step = torch.linalg.solve(hessian + damping * torch.diag(scaling), -gradient)
                trial = float(residuals(x + step).cost())
                predicted = -float(2.0 * gradient @ step + step @ hessian @ step)
            except torch.linalg.LinAlgError:  # singular even damped: damp more
                trial, predicted = float("nan"), 0.0
            if trial == trial and trial < cost and predicted > 0:  # trial == trial: not NaN
                ratio = (cost - trial) / predicted
                damping *= max(1.0 / 3.0, 1.0 - (2.0 * ratio - 1.0) ** 3)
                growth = 2.0
                break
            damping *= growth
            growth *= 2.0
            if damping > MAX_DAMPING:  # no step lowers the cost: at the minimum to rounding, unless the gradient is not finite
                return Solution(x, iteration, bool(torch.isfinite(gradient).all()))
        x = x + step
        decrease, cost = cost - trial, trial
        if decrease <= relative_tolerance * cost:
            return Solution(x, iteration, True)
    return Solution(x, max_iterations, False)
