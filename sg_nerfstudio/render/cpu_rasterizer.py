"""Front-to-back alpha compositing of projected 2D Gaussians on the CPU, in pure PyTorch.

Why hand-written: gsplat's rasterizer is CUDA-only, and its pure-torch reference (`_torch_impl`) still
needs the CUDA tile-intersection kernel and is far too slow for training or registration. No
maintained library composites Gaussians on the CPU with gradients, so this module does it.

Algorithm (one camera at a time, everything vectorised, autograd-friendly):

1. *Support*: a Gaussian with opacity o can only reach alpha >= 1/255 where its Mahalanobis
   "power" `sigma = 0.5 d^T Sigma^-1 d <= ln(255 o)`. That ellipse's axis-aligned box is
   `mean +- sqrt(2 ln(255 o) Sigma_xx)` (resp. yy); every pixel centre in the box becomes a
   (Gaussian, pixel) *pair*. Gaussians are visited in depth order, so pairs come out depth-sorted.
2. *Alpha*: `alpha = min(0.999, o exp(-sigma))` per pair; pairs below 1/255 are dropped (gsplat's rule).
3. *Transmittance*: a stable sort by pixel groups each pixel's pairs front to back; the exclusive
   transmittance is `exp` of a segmented cumulative sum of `log(1 - alpha)` (float64 so that the
   running sum over the whole image does not eat the per-pixel precision). A pair whose inclusive
   transmittance drops to <= 1e-4 and everything behind it is dropped (gsplat's early stop).
4. *Accumulation*: the weights `w = alpha T` form a sparse [pixels, Gaussians] matrix; the image is
   `W @ colors` with a CSR sparse-dense product. Its backward (`_SparseComposite`) uses the transposed
   CSR for the colour gradient and a sampled dense-dense product for the weight gradient, so no
   [pairs, channels] tensor is ever materialised; with colours frozen (registration) only the
   weight gradient is computed.

The image model is exactly "every Gaussian contributes wherever its alpha >= 1/255", independent of
any tiling, which is what the brute-force reference compositor in the tests evaluates densely.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch
from torch import Tensor

ALPHA_THRESHOLD = 1.0 / 255.0
MAX_ALPHA = 0.999
TRANSMITTANCE_THRESHOLD = 1e-4



@dataclass
class PixelGaussianPairs:
    """Candidate (Gaussian, pixel) pairs of one camera, depth-sorted per Gaussian.

    Attributes:
        gaussian: [P] index into the camera's visible Gaussians (ascending = front to back).
        pixel: [P] flat pixel index `y * width + x`.
    """

    gaussian: Tensor
    pixel: Tensor


def support_boxes(
    means2d: Tensor, cov2d: Tensor, opacities: Tensor, width: int, height: int
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Pixel ranges whose centres can receive alpha >= 1/255 from each Gaussian.

    Args:
        means2d: [M, 2] pixel coordinates.
        cov2d: [M, 3] (xx, xy, yy) blurred 2D covariance.
        opacities: [M] effective opacities.

    Returns:
        x0, y0 (first column/row, int64) and counts nx, ny (>= 0) per Gaussian, each [M].
    """
    with torch.no_grad():
        power = torch.log(torch.clamp(opacities * 255.0, min=1.0))  # 0 -> empty support
        extent_x = torch.sqrt(2.0 * power * cov2d[:, 0].clamp(min=0.0))
        extent_y = torch.sqrt(2.0 * power * cov2d[:, 2].clamp(min=0.0))
        # pixel j has centre j + 0.5
        x0 = torch.ceil(means2d[:, 0] - extent_x - 0.5).clamp(min=0, max=width)
        x1 = torch.floor(means2d[:, 0] + extent_x - 0.5).clamp(min=-1, max=width - 1)
        y0 = torch.ceil(means2d[:, 1] - extent_y - 0.5).clamp(min=0, max=height)
        y1 = torch.floor(means2d[:, 1] + extent_y - 0.5).clamp(min=-1, max=height - 1)
        nx = (x1 - x0 + 1).clamp(min=0)
        ny = (y1 - y0 + 1).clamp(min=0)
        empty = power <= 0
        nx[empty] = 0
    return x0.long(), y0.long(), nx.long(), ny.long()


def enumerate_pairs(x0: Tensor, y0: Tensor, nx: Tensor, ny: Tensor, width: int) -> PixelGaussianPairs:
    """All (Gaussian, pixel) pairs inside each Gaussian's support box, Gaussian-major."""
    counts = nx * ny
    total = int(counts.sum())
    gaussian = torch.repeat_interleave(torch.arange(len(counts)), counts, output_size=total)
    starts = torch.cumsum(counts, 0) - counts
    local = torch.arange(total) - torch.repeat_interleave(starts, counts, output_size=total)
    row_len = nx[gaussian]
    px = x0[gaussian] + local % row_len
    py = y0[gaussian] + torch.div(local, row_len, rounding_mode="floor")
    return PixelGaussianPairs(gaussian=gaussian, pixel=py * width + px)


@dataclass
class CompositingPlan:
    """The pairs that contribute to one camera's image, decided without gradients.

    Attributes:
        gaussian: [P] visible-Gaussian index (depth-sorted order) of each contributing pair.
        pixel: [P] flat pixel index; pairs are grouped by pixel, front to back within a pixel.
        pixel_offsets: [H*W + 1] CSR row pointer: pairs of pixel p are `pixel_offsets[p]:pixel_offsets[p+1]`.
        gaussian_major: [P] permutation listing the pairs grouped by Gaussian (for the transposed product).
        gaussian_offsets: [M + 1] CSR row pointer of that Gaussian-major order.
    """

    gaussian: Tensor
    pixel: Tensor
    pixel_offsets: Tensor
    gaussian_major: Tensor
    gaussian_offsets: Tensor


@torch.no_grad()
def plan_compositing(
    means2d: Tensor, conics: Tensor, cov2d: Tensor, opacities: Tensor, width: int, height: int
) -> CompositingPlan:
    """Find every (Gaussian, pixel) pair with alpha >= 1/255 in front of the early-stop point.

    Args: per visible Gaussian, sorted front to back: means2d [M, 2], conics [M, 3], cov2d [M, 3],
        opacities [M].
    """
    n_pixels = width * height
    pairs = enumerate_pairs(*support_boxes(means2d, cov2d, opacities, width, height), width)
    alphas = _pair_alphas(_gaussian_table(means2d, conics, opacities), pairs.gaussian, pairs.pixel, width)
    significant = torch.nonzero(alphas >= ALPHA_THRESHOLD).squeeze(1)  # Gaussian-major order
    by_pixel = significant[torch.argsort(_compact_keys(pairs.pixel[significant], n_pixels), stable=True)]
    alphas = alphas[by_pixel]
    pair_counts = torch.bincount(pairs.pixel[by_pixel], minlength=n_pixels)
    trans_after = _segmented_transmittance(alphas, pair_counts) * (1.0 - alphas)
    alive = torch.nonzero(trans_after > TRANSMITTANCE_THRESHOLD).squeeze(1)
    chosen = by_pixel[alive]  # candidate ids, pixel-major
    gaussian, pixel = pairs.gaussian[chosen], pairs.pixel[chosen]

    # Gaussian-major order of the chosen pairs without another sort: candidate ids are Gaussian-major.
    position = torch.full_like(pairs.gaussian, -1)
    position[chosen] = torch.arange(len(chosen))
    gaussian_major = position[position >= 0]
    return CompositingPlan(
        gaussian=gaussian,
        pixel=pixel,
        pixel_offsets=_row_pointer(pixel, n_pixels),
        gaussian_major=gaussian_major,
        gaussian_offsets=_row_pointer(gaussian, means2d.shape[0]),
    )


def _compact_keys(keys: Tensor, bound: int) -> Tensor:
    """Narrowest integer dtype holding keys in [0, bound): sorting int16/int32 is 2-3x faster than int64."""
    if bound <= torch.iinfo(torch.int16).max:
        return keys.to(torch.int16)
    if bound <= torch.iinfo(torch.int32).max:
        return keys.to(torch.int32)
    return keys


def _csr_matrix(row_pointer: Tensor, columns: Tensor, values: Tensor, size: tuple[int, int]) -> Tensor:
    """A CSR matrix without invariant checks (the plan guarantees them) and without torch's beta warning."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state")
        return torch.sparse_csr_tensor(row_pointer, columns, values, size=size, check_invariants=False)


def _row_pointer(rows: Tensor, n_rows: int) -> Tensor:
    pointer = torch.zeros(n_rows + 1, dtype=torch.int64)
    pointer[1:] = torch.cumsum(torch.bincount(rows, minlength=n_rows), 0)
    return pointer


class _SparseComposite(torch.autograd.Function):
    """`out = W @ colors` for the sparse weights W [pixels, Gaussians] of a `CompositingPlan`.

    Gradients flow to `weights` [P] (a sampled dense-dense product) and `colors` [M, D] (the
    transposed CSR product); neither materialises a [P, D] tensor.
    """

    @staticmethod
    def forward(ctx, weights: Tensor, colors: Tensor, plan: CompositingPlan):
        n_pixels = plan.pixel_offsets.shape[0] - 1
        matrix = _csr_matrix(plan.pixel_offsets, plan.gaussian, weights, (n_pixels, colors.shape[0]))
        ctx.save_for_backward(weights, colors)
        ctx.plan = plan
        return matrix @ colors

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        weights, colors = ctx.saved_tensors
        plan = ctx.plan
        n_pixels, n_gaussians = plan.pixel_offsets.shape[0] - 1, colors.shape[0]
        grad_out = grad_out.contiguous()
        grad_weights = grad_colors = None
        if ctx.needs_input_grad[0]:
            pattern = _csr_matrix(plan.pixel_offsets, plan.gaussian, torch.ones_like(weights), (n_pixels, n_gaussians))
            grad_weights = torch.sparse.sampled_addmm(pattern, grad_out, colors.t().contiguous(), beta=0.0).values()
        if ctx.needs_input_grad[1]:
            transposed = _csr_matrix(
                plan.gaussian_offsets, plan.pixel[plan.gaussian_major], weights[plan.gaussian_major], (n_gaussians, n_pixels)
            )
            grad_colors = transposed @ grad_out
        return grad_weights, grad_colors, None


def composite_camera(
    means2d: Tensor,
    conics: Tensor,
    cov2d: Tensor,
    opacities: Tensor,
    colors: Tensor,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:
    """Render the visible Gaussians of one camera, given front to back.

    Args:
        means2d: [M, 2], conics: [M, 3], cov2d: [M, 3], opacities: [M], colors: [M, D] of the camera's
            visible Gaussians sorted by increasing depth (see `front_to_back`).

    Returns:
        render [H, W, D] (no background) and alpha [H, W, 1].
    """
    n_pixels = width * height
    channels = colors.shape[-1]
    if means2d.shape[0] == 0:
        return empty_image(means2d, conics, cov2d, opacities, colors, width, height)

    plan = plan_compositing(means2d.detach(), conics.detach(), cov2d.detach(), opacities.detach(), width, height)
    alphas = _pair_alphas(_gaussian_table(means2d, conics, opacities), plan.gaussian, plan.pixel, width)
    pair_counts = plan.pixel_offsets[1:] - plan.pixel_offsets[:-1]
    weights = alphas * _segmented_transmittance(alphas, pair_counts)
    render = _SparseComposite.apply(weights, colors, plan)
    alpha = torch.zeros(n_pixels, dtype=weights.dtype).index_add(0, plan.pixel, weights)
    return render.reshape(height, width, channels), alpha.reshape(height, width, 1)


def empty_image(means2d, conics, cov2d, opacities, colors, width: int, height: int) -> tuple[Tensor, Tensor]:
    """Zero render [H, W, D] and alpha [H, W, 1] for a camera that sees no Gaussian, still attached to
    every input so that gradients are zeros rather than None."""
    zero = (means2d.sum() + conics.sum() + cov2d.sum() + opacities.sum() + colors.sum()) * 0.0
    return zero + colors.new_zeros(height, width, colors.shape[-1]), zero + colors.new_zeros(height, width, 1)


def front_to_back(visible: Tensor, depths: Tensor) -> Tensor:
    """Indices [M] of the Gaussians where `visible` [N] (bool) is set, sorted by increasing depth (ties by index)."""
    ids = torch.nonzero(visible).squeeze(1)
    return ids[torch.argsort(depths.detach()[ids], stable=True)]


def _gaussian_table(means2d: Tensor, conics: Tensor, opacities: Tensor) -> Tensor:
    """[M, 6] (x, y, conic a, b, c, opacity): one gather per pair instead of four."""
    return torch.cat([means2d, conics, opacities[:, None]], dim=1)


def _pair_alphas(table: Tensor, gaussian: Tensor, pixel: Tensor, width: int) -> Tensor:
    """alpha = min(0.999, o exp(-sigma)) per pair from a `_gaussian_table`; sigma < 0 gives 0."""
    params = table.index_select(0, gaussian)
    px = (pixel % width).to(table.dtype) + 0.5
    py = torch.div(pixel, width, rounding_mode="floor").to(table.dtype) + 0.5
    dx, dy = px - params[:, 0], py - params[:, 1]
    sigma = 0.5 * (params[:, 2] * dx * dx + params[:, 4] * dy * dy) + params[:, 3] * dx * dy
    alphas = torch.clamp_max(params[:, 5] * torch.exp(-sigma), MAX_ALPHA)
    return torch.where(sigma >= 0, alphas, torch.zeros_like(alphas))


def _segmented_transmittance(alphas: Tensor, pair_counts: Tensor) -> Tensor:
    """Exclusive product of (1 - alpha) within consecutive segments of lengths `pair_counts`.

    Args:
        alphas: [P] grouped by segment, front to back inside each.
        pair_counts: [S] segment lengths, summing to P.

    Returns:
        [P] transmittance in front of each pair, in the dtype of `alphas`.
    """
    log_keep = torch.log1p(-alphas.to(torch.float64))
    inclusive = torch.cumsum(log_keep, 0)
    segment_end = torch.cumsum(pair_counts, 0)
    offset_before_segment = torch.cat([inclusive.new_zeros(1), inclusive])[segment_end - pair_counts]
    offset = torch.repeat_interleave(offset_before_segment, pair_counts, output_size=alphas.shape[0])
    return torch.exp(inclusive - log_keep - offset).to(alphas.dtype)


def brute_force_composite(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    colors: Tensor,
    depths: Tensor,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:
    """Dense reference: every Gaussian against every pixel, sequential in depth order.

    Same image model as `composite_camera` (alpha threshold, 0.999 cap, early stop) with none of its
    machinery; O(pixels x Gaussians) memory, for tests and benchmarks only.

    Returns:
        render [H, W, D] and alpha [H, W, 1].
    """
    order = torch.argsort(depths.detach(), stable=True)
    means2d, conics, opacities, colors = means2d[order], conics[order], opacities[order], colors[order]
    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=means2d.dtype) + 0.5, torch.arange(width, dtype=means2d.dtype) + 0.5, indexing="ij"
    )
    dx = xs.reshape(-1, 1) - means2d[None, :, 0]  # [HW, M]
    dy = ys.reshape(-1, 1) - means2d[None, :, 1]
    sigma = 0.5 * (conics[None, :, 0] * dx * dx + conics[None, :, 2] * dy * dy) + conics[None, :, 1] * dx * dy
    alphas = torch.clamp_max(opacities[None] * torch.exp(-sigma), MAX_ALPHA)
    alphas = torch.where((sigma >= 0) & (alphas >= ALPHA_THRESHOLD), alphas, torch.zeros_like(alphas))
    trans_after = torch.cumprod(1.0 - alphas, dim=1)  # [HW, M]
    trans_before = torch.cat([torch.ones_like(trans_after[:, :1]), trans_after[:, :-1]], dim=1)
    weights = torch.where(trans_after.detach() > TRANSMITTANCE_THRESHOLD, alphas * trans_before, torch.zeros_like(alphas))
    render = weights @ colors
    return render.reshape(height, width, -1), weights.sum(1).reshape(height, width, 1)
