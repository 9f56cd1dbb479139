"""EWA projection of a *frozen* model's Gaussians with gradients for the cameras only, compiled with numba.

A registration renders a frozen reference and needs gradients with respect to the cameras (viewmats) alone.
Through autograd (`projection.project_gaussians_packed`) every (Gaussian, camera) entry costs some 20 tensor
operations and their backward over [S, 3, 3] batches, about 1.5 us per entry on this project's 2-core CPU: a
16-photo step of a 45k-Gaussian model spent half of its time there. This module computes the same outputs
in one compiled pass per entry and, backwards, accumulates the 12 viewmat gradients per camera directly
(one buffer per worker, summed afterwards), so projection costs a few tens of nanoseconds per entry. The same
holds for view-dependent colour: `frozen_sh_colors` evaluates the SH colour of each entry towards its camera
and returns gradients for the camera centres only (measured on that step: autograd SH 0.37 s forward and 0.37 s
backward; compiled 0.10 s and 0.09 s; the whole step 2.0 s -> 1.5 s in that profile). The model's float32 arrays are read
in place (the kernels compute in float64 all the same; `_as_array`), and the SH forward evaluates the basis
without its gradient, which only the backward needs: on a 16-photo step of a 1M-Gaussian reference these two
took the step from 15.3 s to 8.9 s (copies to float64 3.3 s, SH forward 2.7 -> 1.1 s).

Why by hand: gsplat's fused projection (which this follows term for term, classic mode) has CUDA kernels
only, and nothing maintained projects Gaussians on the CPU. `tests/test_render.py` checks the outputs and the
viewmat gradients against `project_gaussians_packed` (itself checked against gsplat's torch reference).

Frames and shapes as in `projection.py`: viewmats [C, 4, 4] world-to-camera (OpenCV), Ks [C, 3, 3], entries
s = (Gaussian means[s], covars[s], camera camera_ids[s]).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from sg_nerfstudio.render.projection import ProjectedGaussians


@njit(cache=True)
def _entry(means, covars, viewmats, Ks, camera_ids, s, width, height, eps2d, RS, W):  # pragma: no cover - compiled
    """Camera-frame mean, clamp state and 2D covariance of entry s (the forward's intermediates); fills the
    scratch RS = R Sigma and W = R Sigma R^T [3, 3]."""
    c = camera_ids[s]
    R = viewmats[c]
    x = R[0, 0] * means[s, 0] + R[0, 1] * means[s, 1] + R[0, 2] * means[s, 2] + viewmats[c, 0, 3]
    y = R[1, 0] * means[s, 0] + R[1, 1] * means[s, 1] + R[1, 2] * means[s, 2] + viewmats[c, 1, 3]
    z = R[2, 0] * means[s, 0] + R[2, 1] * means[s, 1] + R[2, 2] * means[s, 2] + viewmats[c, 2, 3]
    z_live = abs(z) >= 1e-10
    if not z_live:
        z = 1e-10
    fx, fy, cx, cy = Ks[c, 0, 0], Ks[c, 1, 1], Ks[c, 0, 2], Ks[c, 1, 2]
    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    u, v = x / z, y / z
    u_low, u_high = -(cx / fx + 0.3 * tan_x), (width - cx) / fx + 0.3 * tan_x
    v_low, v_high = -(cy / fy + 0.3 * tan_y), (height - cy) / fy + 0.3 * tan_y
    u_free = u_low <= u <= u_high
    v_free = v_low <= v <= v_high
    u = min(max(u, u_low), u_high)
    v = min(max(v, v_low), v_high)
    j00, j02 = fx / z, -fx * u / z  # -fx * (z u) / z^2
    j11, j12 = fy / z, -fy * v / z
    for i in range(3):
        for k in range(3):
            RS[i, k] = R[i, 0] * covars[s, 0, k] + R[i, 1] * covars[s, 1, k] + R[i, 2] * covars[s, 2, k]
    for i in range(3):
        for k in range(3):
            W[i, k] = RS[i, 0] * R[k, 0] + RS[i, 1] * R[k, 1] + RS[i, 2] * R[k, 2]
    # cov = J W J^T with J = [[j00, 0, j02], [0, j11, j12]]
    a0 = j00 * W[0, 0] + j02 * W[2, 0]
    a1 = j00 * W[0, 1] + j02 * W[2, 1]
    a2 = j00 * W[0, 2] + j02 * W[2, 2]
    b1 = j11 * W[1, 1] + j12 * W[2, 1]
    b2 = j11 * W[1, 2] + j12 * W[2, 2]
    cov_xx = a0 * j00 + a2 * j02
    cov_xy = a1 * j11 + a2 * j12
    cov_yy = b1 * j11 + b2 * j12
    return c, x, y, z, z_live, u, v, u_free, v_free, j00, j02, j11, j12, cov_xx + eps2d, cov_xy, cov_yy + eps2d


@njit(parallel=True, cache=True)
def _forward(means, covars, viewmats, Ks, camera_ids, width, height, eps2d, workers, means2d, conics, cov2d, depths):  # pragma: no cover - compiled
    n = means.shape[0]
    for worker in prange(workers):
        RS, W = np.empty((3, 3)), np.empty((3, 3))
        for s in range(worker * n // workers, (worker + 1) * n // workers):
            _forward_entry(means, covars, viewmats, Ks, camera_ids, s, width, height, eps2d, RS, W, means2d, conics, cov2d, depths)


@njit(cache=True)
def _forward_entry(means, covars, viewmats, Ks, camera_ids, s, width, height, eps2d, RS, W, means2d, conics, cov2d, depths):  # pragma: no cover - compiled
    c, x, y, z, _, _, _, _, _, _, _, _, _, a, b, cc = _entry(means, covars, viewmats, Ks, camera_ids, s, width, height, eps2d, RS, W)
    det = max(a * cc - b * b, 1e-10)
    conics[s, 0], conics[s, 1], conics[s, 2] = cc / det, -b / det, a / det
    cov2d[s, 0], cov2d[s, 1], cov2d[s, 2] = a, b, cc
    means2d[s, 0] = Ks[c, 0, 0] * x / z + Ks[c, 0, 2]
    means2d[s, 1] = Ks[c, 1, 1] * y / z + Ks[c, 1, 2]
    depths[s] = z


@njit(parallel=True, cache=True)
def _backward(means, covars, viewmats, Ks, camera_ids, width, height, eps2d, g_means2d, g_conics, g_cov2d, g_depths, grads):  # pragma: no cover - compiled
    """grads [workers, C, 3, 4]: each worker's sum of d loss / d viewmat[:3, :4] over its entries."""
    workers = grads.shape[0]
    n = means.shape[0]
    for worker in prange(workers):
        grads[worker] = 0.0
        RS, W, G = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
        for s in range(worker * n // workers, (worker + 1) * n // workers):
            c, x, y, z, z_live, u, v, u_free, v_free, j00, j02, j11, j12, a, b, cc = _entry(
                means, covars, viewmats, Ks, camera_ids, s, width, height, eps2d, RS, W
            )
            fx, fy = Ks[c, 0, 0], Ks[c, 1, 1]
            det_raw = a * cc - b * b
            det = max(det_raw, 1e-10)
            g_a, g_b, g_c = g_cov2d[s, 0], g_cov2d[s, 1], g_cov2d[s, 2]
            k0, k1, k2 = g_conics[s, 0], g_conics[s, 1], g_conics[s, 2]
            # conics = (cc, -b, a) / det
            g_a += k2 / det
            g_b += -k1 / det
            g_c += k0 / det
            if det_raw > 1e-10:
                g_det = -(k0 * cc - k1 * b + k2 * a) / (det * det)
                g_a += g_det * cc
                g_c += g_det * a
                g_b += g_det * (-2.0 * b)
            # cov_xx = J0 W J0^T, cov_yy = J1 W J1^T, cov_xy = J0 W J1^T (W symmetric)
            # d/dW = g_a J0 J0^T + g_c J1 J1^T + g_b (J0 J1^T + J1 J0^T) / 2
            J0 = (j00, 0.0, j02)
            J1 = (0.0, j11, j12)
            for i in range(3):
                for k in range(3):
                    G[i, k] = g_a * J0[i] * J0[k] + g_c * J1[i] * J1[k] + 0.5 * g_b * (J0[i] * J1[k] + J1[i] * J0[k])
            # d/dJ0 = 2 g_a W J0 + g_b W J1, d/dJ1 = 2 g_c W J1 + g_b W J0 (only the non-zero entries of J matter)
            g_j00 = 2.0 * g_a * (W[0, 0] * j00 + W[0, 2] * j02) + g_b * (W[0, 1] * j11 + W[0, 2] * j12)
            g_j02 = 2.0 * g_a * (W[2, 0] * j00 + W[2, 2] * j02) + g_b * (W[2, 1] * j11 + W[2, 2] * j12)
            g_j11 = 2.0 * g_c * (W[1, 1] * j11 + W[1, 2] * j12) + g_b * (W[1, 0] * j00 + W[1, 2] * j02)
            g_j12 = 2.0 * g_c * (W[2, 1] * j11 + W[2, 2] * j12) + g_b * (W[2, 0] * j00 + W[2, 2] * j02)
            # j00 = fx / z, j02 = -fx u / z with u = x / z (or a constant when clamped); the same in y
            g_x = 0.0
            g_y = 0.0
            g_z = g_depths[s]
            g_z += -g_j00 * fx / (z * z) - g_j11 * fy / (z * z)
            g_u = -g_j02 * fx / z
            g_v = -g_j12 * fy / z
            g_z += g_j02 * fx * u / (z * z) + g_j12 * fy * v / (z * z)
            if u_free:
                g_x += g_u / z
                g_z -= g_u * x / (z * z)
            if v_free:
                g_y += g_v / z
                g_z -= g_v * y / (z * z)
            # means2d = (fx x / z + cx, fy y / z + cy)
            gm0, gm1 = g_means2d[s, 0], g_means2d[s, 1]
            g_x += gm0 * fx / z
            g_y += gm1 * fy / z
            g_z -= (gm0 * fx * x + gm1 * fy * y) / (z * z)
            if not z_live:
                g_z = 0.0
            # p = R mu + t; W = R Sigma R^T -> d/dR = g_p mu^T + 2 G R Sigma (G, Sigma symmetric)
            g_p = (g_x, g_y, g_z)
            for i in range(3):
                for k in range(3):
                    grads[worker, c, i, k] += g_p[i] * means[s, k] + 2.0 * (G[i, 0] * RS[0, k] + G[i, 1] * RS[1, k] + G[i, 2] * RS[2, k])
                grads[worker, c, i, 3] += g_p[i]


def _as_array(tensor: Tensor, float64: bool = False) -> np.ndarray:
    """A numpy view of `tensor` (detached, contiguous), in float64 when asked, else in its own floating dtype.

    The per-camera inputs (viewmats, Ks, camera centres: a few numbers) are passed as float64, so that every
    product in the kernels has a float64 operand and they compute in float64 as before; the per-Gaussian and
    per-entry arrays are read in the model's dtype (float32 -> float64 on reading is exact), because copying
    them to float64 cost more than the kernels themselves (profile of a 16-photo step of a 1M-Gaussian
    reference: 3.3 s of 15.3 s)."""
    tensor = tensor.detach().contiguous()
    if float64 or tensor.dtype not in (torch.float32, torch.float64):
        tensor = tensor.to(torch.float64)
    return tensor.numpy()


class _FrozenProjection(torch.autograd.Function):
    """viewmats -> (means2d, conics, cov2d, depths) of the packed entries; gradients for viewmats only."""

    @staticmethod
    def forward(ctx, viewmats, means, covars, Ks, camera_ids, width, height, eps2d):
        arrays = [_as_array(means), _as_array(covars), _as_array(viewmats, float64=True), _as_array(Ks, float64=True)]
        ids = camera_ids.contiguous().numpy()
        n, dtype = means.shape[0], arrays[0].dtype
        outputs = (np.empty((n, 2), dtype), np.empty((n, 3), dtype), np.empty((n, 3), dtype), np.empty(n, dtype))
        _forward(*arrays, ids, width, height, eps2d, max(1, min(numba.get_num_threads(), n)), *outputs)
        ctx.inputs, ctx.ids, ctx.size, ctx.dtype = arrays, ids, (width, height, eps2d), means.dtype
        return tuple(torch.from_numpy(output) for output in outputs)

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_cov2d, g_depths):
        n = ctx.inputs[0].shape[0]
        upstream = [
            _as_array(torch.zeros(shape, dtype=ctx.dtype) if grad is None else grad.to(ctx.dtype))
            for grad, shape in zip((g_means2d, g_conics, g_cov2d, g_depths), ((n, 2), (n, 3), (n, 3), (n,)))
        ]
        cameras = ctx.inputs[2].shape[0]
        grads = np.empty((max(1, min(numba.get_num_threads(), n)), cameras, 3, 4))
        _backward(*ctx.inputs, ctx.ids, *ctx.size, *upstream, grads)
        viewmat_grad = torch.zeros(cameras, 4, 4, dtype=torch.float64)
        viewmat_grad[:, :3, :4] = torch.from_numpy(grads.sum(axis=0))
        return viewmat_grad.to(ctx.dtype), None, None, None, None, None, None, None


def project_frozen_packed(
    means: Tensor, covars: Tensor, viewmats: Tensor, Ks: Tensor, camera_ids: Tensor, width: int, height: int,
    eps2d: float = 0.3, near_plane: float = 0.01, far_plane: float = 1e10,
) -> ProjectedGaussians:
    """`projection.project_gaussians_packed` (classic mode) for Gaussians that need no gradient.

    Args:
        means: [S, 3], covars: [S, 3, 3] world-frame Gaussians, one row per entry (no gradient).
        viewmats: [C, 4, 4] world-to-camera (OpenCV), with or without gradient; Ks [C, 3, 3].
        camera_ids: [S] int64 camera of each entry.

    Returns:
        `ProjectedGaussians` with leading shape [S]; means2d, conics, cov2d and depths carry gradients to
        `viewmats`; radii as in `project_gaussians_packed`; no compensations.
    """
    means2d, conics, cov2d, depths = _FrozenProjection.apply(viewmats, means, covars, Ks, camera_ids, width, height, eps2d)
    with torch.no_grad():
        det = cov2d[:, 0] * cov2d[:, 2] - cov2d[:, 1] ** 2
        half_trace = 0.5 * (cov2d[:, 0] + cov2d[:, 2])
        radius = torch.ceil(3.0 * torch.sqrt(half_trace + torch.sqrt(torch.clamp(half_trace**2 - det.clamp(min=1e-10), min=0.01))))
        valid = (det.clamp(min=1e-10) > 0) & (depths > near_plane) & (depths < far_plane) & torch.isfinite(radius)
        mx, my = means2d[:, 0], means2d[:, 1]
        inside = (mx + radius > 0) & (mx - radius < width) & (my + radius > 0) & (my - radius < height)
        radii = torch.where(valid & inside, radius, torch.zeros_like(radius)).int()
    return ProjectedGaussians(means2d=means2d, conics=conics, cov2d=cov2d, depths=depths, radii=radii, compensations=None)


SH_BANDS_CONSTANTS = (0.2820947917738781, 0.48860251190292, 0.5462742152960395, 1.092548430592079, 0.9461746957575601,
                      0.3153915652525201, 0.5900435899266435, 1.445305721320277, 2.285228997322329, 0.4570457994644658,
                      1.865881662950577, 1.119528997770346)
"""The constants of `spherical_harmonics.sh_basis` (gsplat's basis), in the order the kernel reads them."""


@njit(cache=True)
def _sh_basis(x, y, z, bases, values):  # pragma: no cover - compiled
    """`spherical_harmonics.sh_basis` at (x, y, z) into values [16]; the first `bases` only."""
    c0, k1, k2a, k2b, k2c, k2d, k3a, k3b, k3c, k3d, k3e, k3f = SH_BANDS_CONSTANTS
    values[0] = c0
    if bases > 1:
        values[1], values[2], values[3] = -k1 * y, k1 * z, -k1 * x
    if bases > 4:
        values[4] = k2a * 2.0 * x * y
        values[5] = -k2b * z * y
        values[6] = k2c * z * z - k2d
        values[7] = -k2b * z * x
        values[8] = k2a * (x * x - y * y)
    if bases > 9:
        tmp_c = -k3c * z * z + k3d
        values[9] = -k3a * (3.0 * x * x * y - y * y * y)
        values[10] = k3b * z * 2.0 * x * y
        values[11] = tmp_c * y
        values[12] = z * (k3e * z * z - k3f)
        values[13] = tmp_c * x
        values[14] = k3b * z * (x * x - y * y)
        values[15] = -k3a * (x * x * x - 3.0 * x * y * y)


@njit(cache=True)
def _sh_basis_gradient(x, y, z, bases, grads):  # pragma: no cover - compiled
    """The gradient of `_sh_basis` with respect to (x, y, z) (taken as independent, as autograd does on the
    formulas) into grads [16, 3]; the first `bases` only."""
    c0, k1, k2a, k2b, k2c, k2d, k3a, k3b, k3c, k3d, k3e, k3f = SH_BANDS_CONSTANTS
    grads[0, 0] = grads[0, 1] = grads[0, 2] = 0.0
    if bases > 1:
        grads[1, 0], grads[1, 1], grads[1, 2] = 0.0, -k1, 0.0
        grads[2, 0], grads[2, 1], grads[2, 2] = 0.0, 0.0, k1
        grads[3, 0], grads[3, 1], grads[3, 2] = -k1, 0.0, 0.0
    if bases > 4:
        grads[4, 0], grads[4, 1], grads[4, 2] = 2.0 * k2a * y, 2.0 * k2a * x, 0.0
        grads[5, 0], grads[5, 1], grads[5, 2] = 0.0, -k2b * z, -k2b * y
        grads[6, 0], grads[6, 1], grads[6, 2] = 0.0, 0.0, 2.0 * k2c * z
        grads[7, 0], grads[7, 1], grads[7, 2] = -k2b * z, 0.0, -k2b * x
        grads[8, 0], grads[8, 1], grads[8, 2] = 2.0 * k2a * x, -2.0 * k2a * y, 0.0
    if bases > 9:
        tmp_c = -k3c * z * z + k3d
        grads[9, 0], grads[9, 1], grads[9, 2] = -k3a * 6.0 * x * y, -k3a * (3.0 * x * x - 3.0 * y * y), 0.0
        grads[10, 0], grads[10, 1], grads[10, 2] = 2.0 * k3b * y * z, 2.0 * k3b * x * z, 2.0 * k3b * x * y
        grads[11, 0], grads[11, 1], grads[11, 2] = 0.0, tmp_c, -2.0 * k3c * z * y
        grads[12, 0], grads[12, 1], grads[12, 2] = 0.0, 0.0, 3.0 * k3e * z * z - k3f
        grads[13, 0], grads[13, 1], grads[13, 2] = tmp_c, 0.0, -2.0 * k3c * z * x
        grads[14, 0], grads[14, 1], grads[14, 2] = 2.0 * k3b * z * x, -2.0 * k3b * z * y, k3b * (x * x - y * y)
        grads[15, 0], grads[15, 1], grads[15, 2] = -k3a * (3.0 * x * x - 3.0 * y * y), k3a * 6.0 * x * y, 0.0


@njit(cache=True)
def _direction(means, centres, gaussian, camera):  # pragma: no cover - compiled
    """Unit direction camera centre -> Gaussian and the length it was divided by (F.normalize's eps)."""
    dx = means[gaussian, 0] - centres[camera, 0]
    dy = means[gaussian, 1] - centres[camera, 1]
    dz = means[gaussian, 2] - centres[camera, 2]
    norm = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
    return dx / norm, dy / norm, dz / norm, norm


@njit(parallel=True, cache=True)
def _sh_forward(means, coeffs, centres, gaussian_ids, camera_ids, bases, workers, unclamped):  # pragma: no cover - compiled
    """unclamped [S, 3]: 0.5 + SH colour of each entry (the output clamps it at 0)."""
    n = gaussian_ids.shape[0]
    for worker in prange(workers):
        values = np.empty(16)
        for s in range(worker * n // workers, (worker + 1) * n // workers):
            g = gaussian_ids[s]
            x, y, z, _ = _direction(means, centres, g, camera_ids[s])
            _sh_basis(x, y, z, bases, values)
            for channel in range(3):
                total = 0.5
                for b in range(bases):
                    total += values[b] * coeffs[g, b, channel]
                unclamped[s, channel] = total


@njit(parallel=True, cache=True)
def _sh_backward(means, coeffs, centres, gaussian_ids, camera_ids, bases, unclamped, g_colors, grads_out):  # pragma: no cover - compiled
    """grads_out [workers, C, 3]: d loss / d camera centre, per worker."""
    n = gaussian_ids.shape[0]
    workers = grads_out.shape[0]
    for worker in prange(workers):
        grads_out[worker] = 0.0
        grads = np.empty((16, 3))
        for s in range(worker * n // workers, (worker + 1) * n // workers):
            g, c = gaussian_ids[s], camera_ids[s]
            x, y, z, norm = _direction(means, centres, g, c)
            _sh_basis_gradient(x, y, z, bases, grads)
            gx = gy = gz = 0.0
            for channel in range(3):
                upstream = g_colors[s, channel]
                if upstream == 0.0 or unclamped[s, channel] < 0.0:  # clamp_min passes the gradient at >= 0
                    continue
                for b in range(1, bases):
                    weight = upstream * coeffs[g, b, channel]
                    gx += weight * grads[b, 0]
                    gy += weight * grads[b, 1]
                    gz += weight * grads[b, 2]
            radial = gx * x + gy * y + gz * z  # through the normalisation: (I - d d^T) / |d|
            grads_out[worker, c, 0] -= (gx - radial * x) / norm
            grads_out[worker, c, 1] -= (gy - radial * y) / norm
            grads_out[worker, c, 2] -= (gz - radial * z) / norm


class _FrozenColors(torch.autograd.Function):
    """camera centres -> SH colours of the packed entries (clamped at 0 after +0.5); gradients for the centres only."""

    @staticmethod
    def forward(ctx, centres, means, coeffs, gaussian_ids, camera_ids, degree):
        arrays = [_as_array(means), _as_array(coeffs), _as_array(centres, float64=True)]
        ids = (gaussian_ids.contiguous().numpy(), camera_ids.contiguous().numpy())
        bases = (degree + 1) ** 2
        unclamped = np.empty((ids[0].shape[0], 3), arrays[1].dtype)
        _sh_forward(*arrays, *ids, bases, max(1, min(numba.get_num_threads(), ids[0].shape[0])), unclamped)
        ctx.inputs, ctx.ids, ctx.bases, ctx.unclamped, ctx.dtype = arrays, ids, bases, unclamped, coeffs.dtype
        return torch.from_numpy(np.maximum(unclamped, 0.0)).to(coeffs.dtype)

    @staticmethod
    def backward(ctx, g_colors):
        cameras = ctx.inputs[2].shape[0]
        grads = np.empty((max(1, min(numba.get_num_threads(), ctx.ids[0].shape[0])), cameras, 3))
        _sh_backward(*ctx.inputs, *ctx.ids, ctx.bases, ctx.unclamped, _as_array(g_colors.detach().to(ctx.dtype)), grads)
        return torch.from_numpy(grads.sum(axis=0)).to(ctx.dtype), None, None, None, None, None


def frozen_sh_colors(means: Tensor, coeffs: Tensor, camera_centres: Tensor, gaussian_ids: Tensor, camera_ids: Tensor, degree: int) -> Tensor:
    """Colours [S, 3] of packed entries from SH coefficients, as `rasterization._entry_colors` computes them
    (gsplat's basis, direction camera centre -> Gaussian, +0.5, clamped at 0), for a model that needs no
    gradient: only `camera_centres` [C, 3] receive one.

    Args:
        means: [N, 3]; coeffs: [N, K, 3] with K >= (degree + 1) ** 2; gaussian_ids, camera_ids: [S] int64.
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"sh_degree must be between 0 and 3, got {degree}.")
    return _FrozenColors.apply(camera_centres, means, coeffs, gaussian_ids, camera_ids, degree)
