"""Level of detail: the frozen reference with the Gaussians far below a render pixel merged into coarser ones.

A registration renders at low resolution (about 128 px on a CPU), while a reference trained for a real
landmark holds millions of Gaussians, most of them far smaller than one render pixel at the photos' distance.
Rendering them all costs what the *model* holds, not what the *photos* show. `coarsen` merges them so that the
cost follows the pixels:

1. Footprint: a Gaussian at depth z in a photo with focal length f (pixels of its render) spans f / z pixels
   per scene unit. Over the photos that see it, the finest detail any of them resolves there is
   `cell = pixels * min_c(z_c / f_c)` scene units (`pixels`, the cell size in render pixels, 1 by default).
2. Cells: each Gaussian goes to a voxel of an octree-like grid whose size is the largest power of two times
   `base` (the smallest cell of all) not above its own `cell`, so near and far parts of a landmark each get
   cells of about one pixel; Gaussians whose own extent (sqrt of the covariance's trace) is larger than their
   cell stay as they are.
3. Merge: the Gaussians of one voxel become one by opacity-weighted moment matching (as hierarchical 3DGS,
   Kerbl et al. 2024): weights w = opacity x area (area = product of the two largest standard deviations,
   the disc a Gaussian shows face on); mean and colours, SH coefficients and features are the weighted means;
   the covariance is the weighted mean of each member's covariance plus its offset's outer product; opacity
   is the covered area (sum of w) over the merged Gaussian's area. Where that would exceed 1 (opaque members
   tiling a surface) the merged Gaussian's two largest axes grow until opacity 1 holds the covered area, so
   that the merged Gaussians of a surface still cover it without holes. A voxel of one Gaussian is unchanged.

Why by hand: gsplat and nerfstudio have no level of detail for a trained model; the published hierarchies
(hierarchical 3DGS, Octree-GS) are CUDA training pipelines, not a function of a frozen model.

Frames: everything in the frame the Gaussians are in (the dataparser frame during registration); depths come
from the caller (the visibility cull already has them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
from torch import Tensor

from sg_nerfstudio.registration.reference import ReferenceModel

DEFAULT_PIXELS = 1.0
"""Voxel size in render pixels at the nearest photo that sees it."""


@dataclass
class MergePlan:
    """Which Gaussians merge into which.

    Attributes:
        cluster: [N] int64 index of each input Gaussian's merged Gaussian, in [0, M).
        count: M, the Gaussians after merging.
    """

    cluster: Tensor
    count: int


def footprint_cells(depths: Tensor, focal: Tensor, seen: Tensor, pixels: float = DEFAULT_PIXELS) -> Tensor:
    """The finest detail any photo resolves at each Gaussian, in scene units: [N].

    Args:
        depths: [C, N] camera-frame depth of every Gaussian's mean in every photo's render camera.
        focal: [C] focal length of each render camera in pixels (the larger of fx, fy).
        seen: [C, N] bool, photo c (with the pose margin of the cull) sees Gaussian n.
        pixels: voxel size in render pixels.

    Returns:
        [N] cell size; +inf for a Gaussian no photo sees (the caller has culled those).
    """
    per_camera = torch.where(seen & (depths > 0), depths / focal[:, None], torch.full_like(depths, math.inf))
    return pixels * per_camera.min(dim=0).values


def plan_merge(means: Tensor, covars: Tensor, cells: Tensor) -> MergePlan:
    """Group Gaussians by voxel (see the module docstring, step 2).

    Args:
        means: [N, 3], covars: [N, 3, 3] Gaussians.
        cells: [N] finest resolved detail per Gaussian (`footprint_cells`), scene units.
    """
    n = means.shape[0]
    extent = covars.diagonal(dim1=-2, dim2=-1).sum(-1).clamp(min=0.0).sqrt()
    finite = torch.isfinite(cells) & (cells > 0)
    mergeable = finite & (extent < cells)
    if not bool(mergeable.any()):
        return MergePlan(torch.arange(n, device=means.device), n)
    base = cells[mergeable].min()
    levels = torch.floor(torch.log2(cells / base)).clamp(min=0).to(torch.int64)
    sizes = base * torch.pow(2.0, levels.to(means.dtype))
    voxels = torch.floor(means / sizes[:, None]).to(torch.int64)
    keys = torch.cat([levels[:, None], voxels], dim=1)
    alone = torch.arange(n, device=means.device)
    # Gaussians that do not merge get keys of their own: a level no merging Gaussian has, and their index (one column
    # is enough, and keeps the keys' ranges small enough for `distinct_row_ids` to pack them).
    zero = torch.zeros_like(alone)
    keys[~mergeable] = torch.stack([torch.full_like(alone, -1), alone, zero, zero], dim=1)[~mergeable]
    cluster = distinct_row_ids(keys)
    return MergePlan(cluster, int(cluster.max()) + 1)


def distinct_row_ids(keys: Tensor) -> Tensor:
    """[N] ids of the distinct rows of integer `keys` [N, K], numbered in lexicographic order of the rows: the inverse
    of `torch.unique(keys, dim=0)`. Each row is first packed into one int64 (columns shifted to start at 0, mixed
    radix), since unique over rows compares them one pair at a time on the CPU (1.0 s for 1M rows of 4 columns,
    0.03 s packed); rows whose ranges do not fit in 63 bits take that path."""
    if keys.shape[0] == 0:
        return torch.zeros(0, dtype=torch.int64, device=keys.device)
    low = keys.min(dim=0).values
    ranges = [int(r) for r in keys.max(dim=0).values - low + 1]
    if math.prod(ranges) >= 2**63:
        return torch.unique(keys, dim=0, return_inverse=True)[1]
    shifted = keys - low
    packed = shifted[:, 0]
    for column, size in enumerate(ranges[1:], start=1):
        packed = packed * size + shifted[:, column]
    return torch.unique(packed, return_inverse=True)[1]


def _face_on_area(covars: Tensor) -> Tensor:
    """[N] product of the two largest standard deviations (the area of the disc a Gaussian shows face on)."""
    eigenvalues = torch.linalg.eigvalsh(covars).clamp(min=0.0)  # ascending
    return torch.sqrt(eigenvalues[:, 1] * eigenvalues[:, 2])


def _conserve_coverage(covars: Tensor, coverage: Tensor) -> tuple[Tensor, Tensor]:
    """Covariances [M, 3, 3] and opacities [M] of merged Gaussians that cover `coverage` [M] (sum of opacity x
    area of their members). Opacity = coverage / area while that is at most 1; a denser cluster (many opaque
    members tiling a surface) would need more than 1, so its two largest axes grow until the area holds the
    coverage at opacity 1: clamping instead would leave holes between the merged Gaussians of a surface."""
    eigenvalues, axes = torch.linalg.eigh(covars)
    eigenvalues = eigenvalues.clamp(min=0.0)
    area = torch.sqrt(eigenvalues[:, 1] * eigenvalues[:, 2]).clamp(min=1e-30)
    growth = (coverage / area).clamp(min=1.0)
    eigenvalues = eigenvalues * torch.stack([torch.ones_like(growth), growth, growth], dim=1)
    grown = axes @ torch.diag_embed(eigenvalues) @ axes.transpose(-1, -2)
    dense = growth > 1.0
    return torch.where(dense[:, None, None], grown, covars), (coverage / (area * growth)).clamp(max=1.0)


def _weighted_mean(values: Tensor, weights: Tensor, plan: MergePlan, totals: Tensor) -> Tensor:
    """Per cluster: sum_i w_i v_i / sum_i w_i for values [N, ...] -> [M, ...]."""
    flat = values.reshape(values.shape[0], -1) * weights[:, None]
    summed = flat.new_zeros(plan.count, flat.shape[1]).index_add_(0, plan.cluster, flat)
    return (summed / totals[:, None]).reshape((plan.count,) + tuple(values.shape[1:]))


@torch.no_grad()
def merge(reference: ReferenceModel, plan: MergePlan) -> ReferenceModel:
    """The reference with each cluster of `plan` replaced by its moment-matched Gaussian (module docstring, step 3)."""
    if plan.count == reference.count:
        return reference
    dtype = reference.means.dtype
    means, covars = reference.means.double(), reference.covars.double()
    weights = reference.opacities.double() * _face_on_area(covars).clamp(min=1e-30)
    totals = weights.new_zeros(plan.count).index_add_(0, plan.cluster, weights)
    merged_means = _weighted_mean(means, weights, plan, totals)
    offsets = means - merged_means[plan.cluster]
    spread = covars + offsets[:, :, None] * offsets[:, None, :]
    merged_covars, merged_opacities = _conserve_coverage(_weighted_mean(spread, weights, plan, totals), totals)
    return replace(
        reference,
        means=merged_means.to(dtype),
        covars=merged_covars.to(dtype),
        opacities=merged_opacities.to(reference.opacities.dtype),
        colors=_weighted_mean(reference.colors.double(), weights, plan, totals).to(reference.colors.dtype),
        gaussian_features=_weighted_mean(reference.gaussian_features.double(), weights, plan, totals).to(reference.gaussian_features.dtype),
    )


def coarsen(reference: ReferenceModel, cells: Tensor) -> ReferenceModel:
    """`reference` with every Gaussian smaller than its cell merged per voxel (`cells` [N] from `footprint_cells`)."""
    return merge(reference, plan_merge(reference.means, reference.covars, cells))
