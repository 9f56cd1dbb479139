"""Tile-binned front-to-back compositing of 2D Gaussians on the CPU, compiled with numba.

Why hand-written: gsplat's rasterizer is CUDA-only and no maintained library composites Gaussians on
the CPU with gradients. The pure-torch compositor (`cpu_rasterizer.composite_camera`) is exact but
spends most of its time building and sorting a (Gaussian, pixel) pair list through autograd; this
module runs gsplat's own per-pixel loop instead, compiled by numba (LLVM) and parallel over tiles, with
a hand-written backward. Same image model as the torch compositor, which the tests compare it with:

- a Gaussian with opacity o reaches a pixel where `sigma = 0.5 d^T conic d >= 0` and
  `alpha = min(0.999, o exp(-sigma)) >= 1/255`; its support box (`cpu_rasterizer.support_boxes`)
  decides which `TILE_SIZE` x `TILE_SIZE` tiles list it, in front-to-back order, and which pixels of
  such a tile it visits (only those inside the box: no pixel outside can receive alpha >= 1/255);
- each pixel walks its tile's list front to back, `w = alpha T`, `T <- T (1 - alpha)`, and stops
  *before* the pair that would bring T to <= 1e-4 (gsplat's early stop); the loop is Gaussian-outer
  within a tile, so each Gaussian's colour row is read once per tile;
- the backward walks the same pairs back to front, recovering T by division (float64), and
  accumulates per-Gaussian gradients in one buffer per worker, summed afterwards (no atomics).

Inputs are per camera, already culled and sorted front to back: means2d [M, 2] (pixels), conics
[M, 3] (a, b, c of the inverse 2D covariance), opacities [M], colors [M, D]. Outputs: render [H, W, D]
without background and alpha [H, W, 1] = 1 - final transmittance.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
from numba import njit, prange
from torch import Tensor

from sg_nerfstudio.render.cpu_rasterizer import (
    ALPHA_THRESHOLD,
    MAX_ALPHA,
    TRANSMITTANCE_THRESHOLD,
    empty_image,
    support_boxes,
)

TILE_SIZE = 8  # best forward+backward at 20k Gaussians, 64 px among 4, 8 and 16 (pixel-outer prototype)


@njit(cache=True)
def _bin_by_tile(x0, y0, nx, ny, tiles_x, tiles_y, tile):  # pragma: no cover - compiled
    """Counting sort of (tile, Gaussian) intersections; Gaussians keep their (depth) order in a tile.

    Args: support box per Gaussian, x0/y0 first pixel, nx/ny pixel counts (int64 [M]).
    Returns: tile_offsets [T + 1] and tile_gaussians [K] (CSR by tile, T = tiles_x * tiles_y).
    """
    n_tiles = tiles_x * tiles_y
    counts = np.zeros(n_tiles + 1, dtype=np.int64)
    for g in range(x0.shape[0]):
        if nx[g] <= 0 or ny[g] <= 0:
            continue
        for ty in range(y0[g] // tile, (y0[g] + ny[g] - 1) // tile + 1):
            for tx in range(x0[g] // tile, (x0[g] + nx[g] - 1) // tile + 1):
                counts[ty * tiles_x + tx + 1] += 1
    for t in range(n_tiles):
        counts[t + 1] += counts[t]
    fill = counts[:-1].copy()
    tile_gaussians = np.empty(counts[n_tiles], dtype=np.int64)
    for g in range(x0.shape[0]):
        if nx[g] <= 0 or ny[g] <= 0:
            continue
        for ty in range(y0[g] // tile, (y0[g] + ny[g] - 1) // tile + 1):
            for tx in range(x0[g] // tile, (x0[g] + nx[g] - 1) // tile + 1):
                t = ty * tiles_x + tx
                tile_gaussians[fill[t]] = g
                fill[t] += 1
    return counts, tile_gaussians


@njit(inline="always")
def _pair_alpha(means2d, conics, opacities, max_sigma, g, px, py):  # pragma: no cover - compiled
    """(alpha, sigma, dx, dy, unclamped) of Gaussian g at pixel centre (px, py); alpha 0 if it does not reach."""
    dx = px - means2d[g, 0]
    dy = py - means2d[g, 1]
    sigma = 0.5 * (conics[g, 0] * dx * dx + conics[g, 2] * dy * dy) + conics[g, 1] * dx * dy
    if sigma < 0.0 or sigma > max_sigma[g]:
        return 0.0, sigma, dx, dy, False
    raw = opacities[g] * math.exp(-sigma)
    alpha = min(MAX_ALPHA, raw)
    if alpha < ALPHA_THRESHOLD:
        return 0.0, sigma, dx, dy, False
    return alpha, sigma, dx, dy, raw <= MAX_ALPHA


@njit(inline="always")
def _box_in_tile(boxes, g, x0, y0, cols, rows):  # pragma: no cover - compiled
    """Pixel range [bx0, bx1) x [by0, by1) of Gaussian g's support box (boxes[g] = x0, y0, nx, ny) inside
    the tile of `cols` x `rows` pixels starting at (x0, y0): the only pixels of the tile it can reach."""
    bx0, by0 = max(boxes[g, 0], x0), max(boxes[g, 1], y0)
    bx1, by1 = min(boxes[g, 0] + boxes[g, 2], x0 + cols), min(boxes[g, 1] + boxes[g, 3], y0 + rows)
    return bx0, max(bx1, bx0), by0, max(by1, by0)


@njit(parallel=True, cache=True, fastmath={"reassoc", "contract"})
def _forward(means2d, conics, opacities, max_sigma, colors, boxes, tile_offsets, tile_gaussians, width, height, tiles_x, tile,
             render, final_transmittance, list_end):  # pragma: no cover - compiled
    """Fill render [H*W, D], final_transmittance [H*W] (float64) and list_end [H*W] (one past the
    last contributing entry of the pixel's tile list).

    Gaussian-outer within a tile (as gsplat's CUDA kernel): each Gaussian's colour row is read once
    per tile and applied to the tile's pixels that are still transparent enough."""
    channels = colors.shape[1]
    n_tiles = tile_offsets.shape[0] - 1
    for t in prange(n_tiles):
        ty, tx = t // tiles_x, t % tiles_x
        start, end = tile_offsets[t], tile_offsets[t + 1]
        y0, x0 = ty * tile, tx * tile
        rows, cols = min(tile, height - y0), min(tile, width - x0)
        n = rows * cols
        transmittance = np.ones(n, dtype=np.float64)
        last = np.full(n, start, dtype=np.int64)
        done = np.zeros(n, dtype=np.bool_)
        alive = n
        for k in range(start, end):
            if alive == 0:
                break
            g = tile_gaussians[k]
            bx0, bx1, by0, by1 = _box_in_tile(boxes, g, x0, y0, cols, rows)
            for y in range(by0, by1):
                for x in range(bx0, bx1):
                    i = (y - y0) * cols + x - x0
                    if done[i]:
                        continue
                    alpha, _, _, _, _ = _pair_alpha(means2d, conics, opacities, max_sigma, g, x + 0.5, y + 0.5)
                    if alpha == 0.0:
                        continue
                    next_transmittance = transmittance[i] * (1.0 - alpha)
                    if next_transmittance <= TRANSMITTANCE_THRESHOLD:
                        done[i] = True
                        alive -= 1
                        continue
                    weight = alpha * transmittance[i]
                    p = y * width + x
                    for d in range(channels):
                        render[p, d] += weight * colors[g, d]
                    transmittance[i] = next_transmittance
                    last[i] = k + 1
        for i in range(n):
            p = (y0 + i // cols) * width + x0 + i % cols
            final_transmittance[p] = transmittance[i]
            list_end[p] = last[i]


@njit(parallel=True, cache=True, fastmath={"reassoc", "contract"})
def _backward(means2d, conics, opacities, max_sigma, colors, boxes, tile_offsets, tile_gaussians, width, height, tiles_x, tile,
              final_transmittance, list_end, grad_render, grad_alpha, with_color_grad,
              grad_means2d, grad_conics, grad_opacities, grad_colors):  # pragma: no cover - compiled
    """Accumulate gradients into per-worker buffers grad_* [workers, M, ...]; worker w owns tiles w, w+W, ...

    Walks each tile's list back to front, Gaussian-outer: per Gaussian the tile's pixel contributions
    are summed locally and added to the worker's buffers once."""
    channels = colors.shape[1]
    n_tiles = tile_offsets.shape[0] - 1
    workers = grad_means2d.shape[0]
    for worker in prange(workers):
        # the buffers come from np.empty: each worker zeroes its own (page faults in order, in parallel)
        grad_means2d[worker] = 0.0
        grad_conics[worker] = 0.0
        grad_opacities[worker] = 0.0
        grad_colors[worker] = 0.0
        color_sum = np.zeros(channels, dtype=np.float64)
        for t in range(worker, n_tiles, workers):
            ty, tx = t // tiles_x, t % tiles_x
            start = tile_offsets[t]
            y0, x0 = ty * tile, tx * tile
            rows, cols = min(tile, height - y0), min(tile, width - x0)
            n = rows * cols
            transmittance = np.empty(n, dtype=np.float64)
            behind = np.zeros(n, dtype=np.float64)  # sum over later pairs of w_k (colors_k . grad + grad_alpha)
            ends = np.empty(n, dtype=np.int64)
            last = start
            for i in range(n):
                p = (y0 + i // cols) * width + x0 + i % cols
                transmittance[i] = final_transmittance[p]
                ends[i] = list_end[p]
                last = max(last, ends[i])
            for k in range(last - 1, start - 1, -1):
                g = tile_gaussians[k]
                touched = False
                g_mx = g_my = g_a = g_b = g_c = g_o = 0.0
                bx0, bx1, by0, by1 = _box_in_tile(boxes, g, x0, y0, cols, rows)
                for pixel in range((bx1 - bx0) * (by1 - by0)):
                    y, x = by0 + pixel // (bx1 - bx0), bx0 + pixel % (bx1 - bx0)
                    i = (y - y0) * cols + x - x0
                    if k >= ends[i]:
                        continue
                    alpha, _, dx, dy, unclamped = _pair_alpha(means2d, conics, opacities, max_sigma, g, x + 0.5, y + 0.5)
                    if alpha == 0.0:
                        continue
                    p = y * width + x
                    if not touched:
                        touched = True
                        color_sum[:] = 0.0
                    transmittance[i] = transmittance[i] / (1.0 - alpha)
                    weight = alpha * transmittance[i]
                    shade = grad_alpha[p]
                    for d in range(channels):
                        shade += colors[g, d] * grad_render[p, d]
                    if with_color_grad:
                        for d in range(channels):
                            color_sum[d] += weight * grad_render[p, d]
                    grad_of_alpha = transmittance[i] * shade - behind[i] / (1.0 - alpha)
                    behind[i] += weight * shade
                    if not unclamped:
                        continue
                    g_o += alpha / opacities[g] * grad_of_alpha
                    grad_sigma = -alpha * grad_of_alpha
                    g_a += 0.5 * dx * dx * grad_sigma
                    g_b += dx * dy * grad_sigma
                    g_c += 0.5 * dy * dy * grad_sigma
                    g_mx -= (conics[g, 0] * dx + conics[g, 1] * dy) * grad_sigma
                    g_my -= (conics[g, 1] * dx + conics[g, 2] * dy) * grad_sigma
                if not touched:
                    continue
                if with_color_grad:
                    for d in range(channels):
                        grad_colors[worker, g, d] += color_sum[d]
                grad_opacities[worker, g, 0] += g_o
                grad_conics[worker, g, 0] += g_a
                grad_conics[worker, g, 1] += g_b
                grad_conics[worker, g, 2] += g_c
                grad_means2d[worker, g, 0] += g_mx
                grad_means2d[worker, g, 1] += g_my


@njit(parallel=True, cache=True)
def _sum_workers(buffers):  # pragma: no cover - compiled
    """[W, M, K] -> [M, K], parallel over M."""
    total = np.empty(buffers.shape[1:], dtype=buffers.dtype)
    for g in prange(buffers.shape[1]):
        total[g] = buffers[0, g]
        for worker in range(1, buffers.shape[0]):
            total[g] += buffers[worker, g]
    return total


class _TileComposite(torch.autograd.Function):
    """Autograd wrapper: (means2d, conics, opacities, colors) -> (render [H*W, D], alpha [H*W])."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, cov2d, width, height):
        means2d_np, conics_np, opacities_np, colors_np = (
            t.detach().contiguous().numpy() for t in (means2d, conics, opacities, colors)
        )
        # sigma beyond ln(255 o) cannot reach alpha 1/255: a cheap test before exp (margin for rounding)
        max_sigma = np.log(np.maximum(255.0 * opacities_np.astype(np.float64), 1e-30)) + 1e-3
        boxes = torch.stack(support_boxes(means2d.detach(), cov2d.detach(), opacities.detach(), width, height), dim=1).numpy()
        x0, y0, nx, ny = boxes.T.copy()
        tiles_x, tiles_y = -(-width // TILE_SIZE), -(-height // TILE_SIZE)
        tile_offsets, tile_gaussians = _bin_by_tile(x0, y0, nx, ny, tiles_x, tiles_y, TILE_SIZE)
        n_pixels = width * height
        render = np.zeros((n_pixels, colors_np.shape[1]), dtype=colors_np.dtype)
        final_transmittance = np.ones(n_pixels, dtype=np.float64)
        list_end = np.zeros(n_pixels, dtype=np.int64)
        gaussians = (means2d_np, conics_np, opacities_np, max_sigma, colors_np, boxes)
        plan = (tile_offsets, tile_gaussians, width, height, tiles_x, TILE_SIZE)
        _forward(*gaussians, *plan, render, final_transmittance, list_end)
        ctx.gaussians, ctx.plan, ctx.pixel_state = gaussians, plan, (final_transmittance, list_end)
        alpha = torch.from_numpy(1.0 - final_transmittance).to(colors.dtype)
        return torch.from_numpy(render), alpha

    @staticmethod
    def backward(ctx, grad_render, grad_alpha):
        colors = ctx.gaussians[4]
        workers = numba.get_num_threads()
        m, channels = colors.shape
        with_color_grad = bool(ctx.needs_input_grad[3])
        if not (grad_render.any() or grad_alpha.any()):  # e.g. a photo the robust loss ignores this step
            dtype = grad_render.dtype
            color_grad = torch.zeros(m, channels, dtype=dtype) if with_color_grad else None
            zeros = (torch.zeros(m, 2, dtype=dtype), torch.zeros(m, 3, dtype=dtype), torch.zeros(m, dtype=dtype))
            return *zeros, color_grad, None, None, None
        grad_means2d = np.empty((workers, m, 2), dtype=colors.dtype)
        grad_conics = np.empty((workers, m, 3), dtype=colors.dtype)
        grad_opacities = np.empty((workers, m, 1), dtype=colors.dtype)
        grad_colors = np.empty((workers, m if with_color_grad else 0, channels), dtype=colors.dtype)
        _backward(
            *ctx.gaussians, *ctx.plan, *ctx.pixel_state,
            grad_render.detach().contiguous().numpy(), grad_alpha.detach().contiguous().numpy(), with_color_grad,
            grad_means2d, grad_conics, grad_opacities, grad_colors,
        )
        summed = [torch.from_numpy(_sum_workers(buffer)) for buffer in (grad_means2d, grad_conics, grad_opacities)]
        color_grad = torch.from_numpy(_sum_workers(grad_colors)) if with_color_grad else None
        return summed[0], summed[1], summed[2][:, 0], color_grad, None, None, None


def composite_camera_tiled(
    means2d: Tensor,
    conics: Tensor,
    cov2d: Tensor,
    opacities: Tensor,
    colors: Tensor,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor]:
    """Drop-in for `cpu_rasterizer.composite_camera` (same arguments, same image, same gradients).

    Returns:
        render [H, W, D] (no background) and alpha [H, W, 1].
    """
    channels = colors.shape[-1]
    if means2d.shape[0] == 0:
        return empty_image(means2d, conics, cov2d, opacities, colors, width, height)
    dtype = colors.dtype
    render, alpha = _TileComposite.apply(
        means2d.to(dtype), conics.to(dtype), opacities.to(dtype), colors, cov2d, width, height
    )
    return render.reshape(height, width, channels), alpha.reshape(height, width, 1)
