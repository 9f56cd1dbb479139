"""Levenberg-Marquardt for small robust least-squares problems in torch: the keypoint camera fit's solver.

The joint fit of the Sim(3) with the meta-image's cameras (`camera_fit.fit_jointly`: 7 + 6 per photo + 2 per COLMAP
camera parameters, 31 for a 3-photo meta-image) is a bundle adjustment with the 3-D points held: smooth, small and
ill-conditioned (focal length against depth, a common turn of every photo against the Sim(3)). L-BFGS had not
converged after 1000 iterations there (largest gradient component 0.24), so its end point moved with 1e-11 changes
of the priors and a fit landed on either side of the plausibility limit from run to run (docs/measurements.md "The keypoint kernel
after the camera fit, measured"); 5000 iterations converged but took 19 s. A Gauss-Newton step uses the Jacobian of
the residuals, which is what such problems are made of: it converges in tens of iterations.

Problem form (`RobustResiduals`): cost(x) = sum_n a_n log(1 + |r_n(x)|^2) + sum_k q_k(x)^2, with r_n [D] residual
vectors in units of a Cauchy kernel (a keypoint's 2-D reprojection error over the kernel scale), a_n >= 0 their
weights, and q_k quadratic residuals (priors). Each iteration weighs the robust rows by the Cauchy kernel's
derivative, a_n / (1 + |r_n|^2) (iteratively reweighted least squares: the model's gradient is the cost's),
solves the damped normal equations (H + lambda diag(H)) dx = -g with the Jacobian from forward-mode AD
(`torch.func.jacfwd`, one pass per parameter), and adapts lambda by the ratio of actual to predicted decrease
(Nielsen's rule).

Why by hand: `scipy.optimize.least_squares` applies its robust loss to each scalar residual, while the keypoint
term's Cauchy kernel acts on each keypoint's 2-D error (isotropic: the same function the render stages minimise,
`keypoints.KeypointTerm`); torch has no least-squares solver.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor


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
    damping, growth = 1e-4, 2.0

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
            if damping > 1e16:  # no step lowers the cost: at the minimum to rounding, unless the gradient is not finite
                return Solution(x, iteration, bool(torch.isfinite(gradient).all()))
        x = x + step
        decrease, cost = cost - trial, trial
        if decrease <= relative_tolerance * cost:
            return Solution(x, iteration, True)
    return Solution(x, max_iterations, False)
