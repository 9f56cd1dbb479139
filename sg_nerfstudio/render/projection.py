"""Projection of 3D Gaussians to 2D image-plane Gaussians (EWA splatting), in pure PyTorch.

This follows gsplat 1.4.0's `fully_fused_projection` (non-packed, pinhole) term for term, so that the
CPU backend and gsplat's CUDA backend see the same 2D Gaussians:

- world -> camera with OpenCV `viewmats` (world-to-camera, x right, y down, z forward);
- the perspective Jacobian evaluated at the mean, with the mean's direction clamped to 1.3x the field
  of view (gsplat's guard against huge covariances of Gaussians far outside the frustum);
- a 2D blur `eps2d` added to the covariance (and, in antialiased mode, an opacity compensation);
- `radii = ceil(3 * sqrt(largest eigenvalue))`, zero for Gaussians that are culled (behind the near
  plane, beyond the far plane, degenerate, or whose 3-sigma square misses the image).

Everything is differentiable with respect to means, quats, scales and viewmats.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F
from torch import Tensor


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices from quaternions in (w, x, y, z) order.

    Args:
        quats: [..., 4], need not be normalised.

    Returns:
        [..., 3, 3] rotation matrices.
    """
    w, x, y, z = torch.unbind(F.normalize(quats, p=2, dim=-1), dim=-1)
    rot = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return rot.reshape(quats.shape[:-1] + (3, 3))


def covariances_from_quats_scales(quats: Tensor, scales: Tensor) -> Tensor:
    """World-frame 3D covariances `R S S^T R^T`.

    Args:
        quats: [N, 4] (w, x, y, z).
        scales: [N, 3] standard deviations along the Gaussian's local axes.

    Returns:
        [N, 3, 3] covariances.
    """
    m = quat_to_rotmat(quats) * scales[..., None, :]
    return m @ m.transpose(-1, -2)


@dataclass
class ProjectedGaussians:
    """2D Gaussians of N Gaussians in C cameras (non-packed: invalid entries have radii == 0).

    Attributes:
        means2d: [C, N, 2] pixel coordinates (x right, y down; pixel (i, j) has centre (j+0.5, i+0.5)).
        conics: [C, N, 3] upper triangle (a, b, c) of the inverse blurred 2D covariance.
        cov2d: [C, N, 3] (xx, xy, yy) of the blurred 2D covariance.
        depths: [C, N] camera-frame z.
        radii: [C, N] int32 3-sigma radius in pixels, 0 when culled.
        compensations: [C, N] antialiasing opacity factor, or None in classic mode.
    """

    means2d: Tensor
    conics: Tensor
    cov2d: Tensor
    depths: Tensor
    radii: Tensor
    compensations: Optional[Tensor]


def world_to_camera(means: Tensor, covars: Tensor, viewmats: Tensor) -> tuple[Tensor, Tensor]:
    """Transform means [N, 3] and covariances [N, 3, 3] by viewmats [C, 4, 4] -> [C, N, 3], [C, N, 3, 3]."""
    rot = viewmats[:, :3, :3]
    trans = viewmats[:, :3, 3]
    means_c = torch.einsum("cij,nj->cni", rot, means) + trans[:, None, :]
    covars_c = rot[:, None] @ covars[None] @ rot.transpose(-1, -2)[:, None]
    return means_c, covars_c


def project_gaussians(
    means: Tensor,
    covars: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    calc_compensations: bool = False,
) -> ProjectedGaussians:
    """Project world-frame Gaussians into C pinhole cameras.

    Args:
        means: [N, 3] world-frame centres.
        covars: [N, 3, 3] world-frame covariances.
        viewmats: [C, 4, 4] world-to-camera (OpenCV).
        Ks: [C, 3, 3] pinhole intrinsics in pixels.
        width, height: image size in pixels.
        eps2d: isotropic 2D blur (pixels^2) added to every projected covariance.
        near_plane, far_plane: depth range kept, in world units along camera z.
        calc_compensations: return the antialiasing opacity factor sqrt(det(cov) / det(cov + eps2d I)).
    """
    means_c, covars_c = world_to_camera(means, covars, viewmats)
    intrinsics = tuple(Ks[:, row, column, None] for row, column in ((0, 0), (1, 1), (0, 2), (1, 2)))  # [C, 1] each
    return _project_camera_frame(means_c, covars_c, intrinsics, width, height, eps2d, near_plane, far_plane, calc_compensations)


@torch.no_grad()
def cull_gaussians(
    means: Tensor,
    covars: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
) -> tuple[Tensor, Tensor]:
    """Cheap conservative visibility: a superset of the Gaussians `project_gaussians` gives radii > 0.

    Projects only the means. The exact radius is 3 sqrt(largest eigenvalue of J Sigma J^T + eps2d I) (plus
    0.1 from its clamp), and that eigenvalue is at most ||J||_F^2 trace(Sigma), so a circle of that bound
    around the projected mean contains the exact 3-sigma square's test; no 3x3 products for all C x N.

    Returns:
        depths [C, N] (camera-frame z of the means) and candidates [C, N] bool.
    """
    rot, trans = viewmats[:, :3, :3], viewmats[:, :3, 3]
    means_c = torch.einsum("cij,nj->cni", rot, means) + trans[:, None, :]
    tx, ty, tz = torch.unbind(means_c, dim=-1)
    safe_tz = torch.where(tz.abs() < 1e-10, torch.full_like(tz, 1e-10), tz)
    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    u, v = _clamped_directions(tx, ty, safe_tz, (fx, fy, cx, cy), width, height)  # as in the Jacobian
    jacobian_sq = (fx**2 * (1 + u**2) + fy**2 * (1 + v**2)) / safe_tz**2  # ||J||_F^2
    trace = covars.diagonal(dim1=-2, dim2=-1).sum(-1).clamp(min=0.0)  # [N]
    radius = 3.0 * torch.sqrt(jacobian_sq * trace + eps2d + 0.1) + 1.0
    mx, my = fx * tx / safe_tz + cx, fy * ty / safe_tz + cy
    inside = (mx + radius > 0) & (mx - radius < width) & (my + radius > 0) & (my - radius < height)
    return tz, inside & (tz > near_plane) & (tz < far_plane) & torch.isfinite(radius)


def project_gaussians_packed(
    means: Tensor,
    covars: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    camera_ids: Tensor,
    width: int,
    height: int,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    calc_compensations: bool = False,
) -> ProjectedGaussians:
    """`project_gaussians` for a list of (Gaussian, camera) entries instead of every Gaussian in every camera.

    gsplat's "packed" layout: entry s is Gaussian `means[s]` seen by camera `camera_ids[s]`. The CPU backend
    uses it to project what several cameras see in one batch of tensor operations (and one autograd graph)
    rather than one per camera.

    Args:
        means: [S, 3], covars: [S, 3, 3] world-frame Gaussians, one row per entry.
        viewmats: [C, 4, 4], Ks: [C, 3, 3] as in `project_gaussians`.
        camera_ids: [S] int64 camera of each entry.

    Returns:
        `ProjectedGaussians` whose fields have the leading shape [S] instead of [C, N].
    """
    entry_viewmats = viewmats.index_select(0, camera_ids)  # [S, 4, 4]; backward is a cheap index_add
    rotations = entry_viewmats[:, :3, :3]
    means_c = (rotations @ means[:, :, None])[:, :, 0] + entry_viewmats[:, :3, 3]
    covars_c = rotations @ covars @ rotations.transpose(-1, -2)
    entry_Ks = Ks.index_select(0, camera_ids)
    intrinsics = tuple(entry_Ks[:, row, column] for row, column in ((0, 0), (1, 1), (0, 2), (1, 2)))  # [S] each
    return _project_camera_frame(means_c, covars_c, intrinsics, width, height, eps2d, near_plane, far_plane, calc_compensations)


def _clamped_directions(tx: Tensor, ty: Tensor, tz: Tensor, intrinsics, width: int, height: int) -> tuple[Tensor, Tensor]:
    """(tx / tz, ty / tz) clamped to 1.3x the field of view, where the perspective Jacobian is evaluated
    (gsplat's guard against huge covariances of Gaussians far outside the frustum)."""
    fx, fy, cx, cy = intrinsics
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos, lim_x_neg = (width - cx) / fx + 0.3 * tan_fovx, cx / fx + 0.3 * tan_fovx
    lim_y_pos, lim_y_neg = (height - cy) / fy + 0.3 * tan_fovy, cy / fy + 0.3 * tan_fovy
    return torch.clamp(tx / tz, min=-lim_x_neg, max=lim_x_pos), torch.clamp(ty / tz, min=-lim_y_neg, max=lim_y_pos)


def _project_camera_frame(
    means_c: Tensor,
    covars_c: Tensor,
    intrinsics: tuple[Tensor, Tensor, Tensor, Tensor],
    width: int,
    height: int,
    eps2d: float,
    near_plane: float,
    far_plane: float,
    calc_compensations: bool,
) -> ProjectedGaussians:
    """EWA projection of camera-frame Gaussians means_c [..., 3], covars_c [..., 3, 3] with pinhole
    intrinsics (fx, fy, cx, cy), each broadcastable to the leading shape [...]."""
    tx, ty, tz = torch.unbind(means_c, dim=-1)
    # Gaussians exactly in the camera plane are culled below; keep their arithmetic finite so that
    # no inf/NaN leaks into gradients of the other Gaussians.
    tz = torch.where(tz.abs() < 1e-10, torch.full_like(tz, 1e-10), tz)
    fx, fy, cx, cy = intrinsics
    u, v = _clamped_directions(tx, ty, tz, intrinsics, width, height)
    tx_clamped, ty_clamped = tz * u, tz * v

    zeros = torch.zeros_like(tz)
    jac = torch.stack(
        [fx / tz, zeros, -fx * tx_clamped / tz**2, zeros, fy / tz, -fy * ty_clamped / tz**2], dim=-1
    ).reshape(tz.shape + (2, 3))
    cov = jac @ covars_c @ jac.transpose(-1, -2)  # [..., 2, 2]
    cov_xx, cov_xy, cov_yy = cov[..., 0, 0], 0.5 * (cov[..., 0, 1] + cov[..., 1, 0]), cov[..., 1, 1]

    det_orig = cov_xx * cov_yy - cov_xy * cov_xy
    cov_xx, cov_yy = cov_xx + eps2d, cov_yy + eps2d
    det = (cov_xx * cov_yy - cov_xy * cov_xy).clamp(min=1e-10)
    compensations = torch.sqrt(torch.clamp(det_orig / det, min=0.0)) if calc_compensations else None
    conics = torch.stack([cov_yy / det, -cov_xy / det, cov_xx / det], dim=-1)

    means2d = torch.stack([fx * tx / tz + cx, fy * ty / tz + cy], dim=-1)

    with torch.no_grad():
        half_trace = 0.5 * (cov_xx + cov_yy)
        largest_eig = half_trace + torch.sqrt(torch.clamp(half_trace**2 - det, min=0.01))
        radius = torch.ceil(3.0 * torch.sqrt(largest_eig))
        valid = (det > 0) & (tz > near_plane) & (tz < far_plane) & torch.isfinite(radius)
        mx, my = means2d[..., 0], means2d[..., 1]
        inside = (mx + radius > 0) & (mx - radius < width) & (my + radius > 0) & (my - radius < height)
        radii = torch.where(valid & inside, radius, torch.zeros_like(radius)).int()

    return ProjectedGaussians(
        means2d=means2d,
        conics=conics,
        cov2d=torch.stack([cov_xx, cov_xy, cov_yy], dim=-1),
        depths=tz,
        radii=radii,
        compensations=compensations,
    )
