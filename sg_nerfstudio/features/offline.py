"""A weight-free dense descriptor: multi-scale histograms of oriented log-intensity gradients.

For machines without DINOv2 weights. Per location of a grid (one cell = `CELL` pixels of the image
resized to `input_size` on its long side, aspect ratio kept) it stacks, for each of three pooling
scales (1, 2 and 4 cells), a histogram of signed gradient orientations of the *logarithm* of each colour channel (summed over channels, magnitude-weighted, soft
binned), and normalises each histogram by its length plus an image-relative floor.

Invariant (up to clipping, sensor noise and the small log offset) to:
- global exposure (a multiplicative gain: log adds a constant, the gradient removes it);
- white balance (independent per-channel gains, removed the same way per channel);
- gamma / contrast curves I -> I^g (log-gradients scale by g; the normalisation removes the scale).
Not invariant to: viewpoint changes beyond a cell, cast shadows and shading edges, occluders, blur
(it changes gradient magnitudes across scales). That is the right trade for registration: structure
(windows, edges, ornaments) is kept, photometric conditions are dropped.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from sg_nerfstudio.features.base import CellDescriptor

CELL = 8
ORIENTATIONS = 12
POOLING_CELLS = (1, 2, 4)
DEFAULT_INPUT_SIZE = 256
LOG_OFFSET = 2.0 / 255.0
VERSION = 2  # 2: aspect ratio kept
TINY = 1e-10


class OfflineTeacher(CellDescriptor):
    """image [H, W, 3] in [0, 1] -> [rows, columns, 36] oriented-gradient descriptor (long side: input_size / 8)."""

    cell, default_input_size, cell_name = CELL, DEFAULT_INPUT_SIZE, "offline descriptor cell size"
    feature_dim = ORIENTATIONS * len(POOLING_CELLS)

    def settings(self) -> dict:
        return {"teacher": "offline_hog", "version": VERSION, "input_size": self.input_size, "cell": CELL,
                "orientations": ORIENTATIONS, "pooling_cells": list(POOLING_CELLS)}

    def describe_resized(self, pixels: Tensor) -> Tensor:
        """[1, 3, 8 rows, 8 columns] -> [1, 36, rows, columns]."""
        log_channels = torch.log(pixels.clamp(min=0.0) + LOG_OFFSET).transpose(0, 1)  # [3, 1, S, S]
        gx, gy = _sobel(log_channels[:, 0])  # [3, S, S] each
        cells = _cell_orientation_histograms(gx, gy, CELL)[None]  # [1, B, rows, columns]
        blocks = []
        for width in POOLING_CELLS:
            pooled = cells if width == 1 else _box_pool(cells, width)
            norm = pooled.norm(dim=1, keepdim=True)
            floor = 0.1 * norm.flatten().median().clamp(min=1e-6)
            blocks.append(pooled / torch.sqrt(norm**2 + floor**2))
        features = torch.cat(blocks, dim=1) / math.sqrt(len(POOLING_CELLS))
        return features


def _sobel(channels: Tensor) -> tuple[Tensor, Tensor]:
    """Sobel derivatives (x right, y down; kernel / 8, replicate padding) of [C, H, W] -> two [C, H, W].

    Written as separable shifted sums rather than `conv2d`: a 3x3 convolution of single-channel maps is
    one of the slowest paths of CPU convolution (its backward above all), and registration differentiates
    through it for every render of every step.
    """
    padded = F.pad(channels[:, None], (1, 1, 1, 1), mode="replicate")[:, 0]  # [C, H + 2, W + 2]
    smooth_rows = padded[:, :-2] + 2.0 * padded[:, 1:-1] + padded[:, 2:]  # [C, H, W + 2]
    smooth_columns = padded[:, :, :-2] + 2.0 * padded[:, :, 1:-1] + padded[:, :, 2:]  # [C, H + 2, W]
    gx = (smooth_rows[:, :, 2:] - smooth_rows[:, :, :-2]) / 8.0
    gy = (smooth_columns[:, 2:] - smooth_columns[:, :-2]) / 8.0
    return gx, gy


def _cell_orientation_histograms(gx: Tensor, gy: Tensor, cell: int) -> Tensor:
    """Per cell of `cell` x `cell` pixels, the mean over its pixels and channels of the magnitude-weighted
    signed orientation histogram, linearly interpolated between the two nearest of the ORIENTATIONS bins.

    Each pixel's two weighted votes are added straight into its cell's bins (one `index_add`), so no
    per-pixel histogram [C, ORIENTATIONS, H, W] is ever built (that was most of the descriptor's cost).

    Args:
        gx, gy: [C, H, W] gradients, H and W multiples of `cell`.

    Returns:
        [ORIENTATIONS, H / cell, W / cell].
    """
    channels, height, width = gx.shape
    rows, columns = height // cell, width // cell
    # The tiny offsets keep the gradients finite where the image is flat (sqrt and atan2 at 0); they change
    # the descriptor by less than float32 resolution.
    magnitude = torch.sqrt(gx**2 + gy**2 + TINY**2)
    position = (torch.atan2(gy, gx + TINY) % (2 * math.pi)) / (2 * math.pi) * ORIENTATIONS
    lower = torch.floor(position.detach())
    upper_weight = position - lower
    lower_bin = lower.long() % ORIENTATIONS
    upper_bin = (lower_bin + 1) % ORIENTATIONS
    device = gx.device
    cell_of_pixel = (torch.arange(height, device=device) // cell)[:, None] * columns + (torch.arange(width, device=device) // cell)[None, :]
    n_cells = rows * columns
    slots = torch.stack([lower_bin * n_cells + cell_of_pixel, upper_bin * n_cells + cell_of_pixel])  # [2, C, H, W]
    votes = torch.stack([magnitude * (1 - upper_weight), magnitude * upper_weight])
    histogram = torch.zeros(ORIENTATIONS * n_cells, device=device, dtype=gx.dtype).index_add(0, slots.flatten(), votes.flatten())
    return histogram.reshape(ORIENTATIONS, rows, columns) / (cell * cell)


def _box_pool(cells: Tensor, width: int) -> Tensor:
    """Mean over a width x width window of cells centred (as well as an even width allows) on each cell."""
    left = (width - 1) // 2
    padded = F.pad(cells, (left, width - 1 - left, left, width - 1 - left), mode="replicate")
    return F.avg_pool2d(padded, width, stride=1)
