"""A weight-free dense descriptor made to match Internet photos to renders of a reference model: the layout of
oriented log-gradient histograms around each cell, at three scales.

Per cell of `CELL` pixels (image resized to `input_size` on its long side, aspect ratio kept), it starts from the
offline descriptor's cell histograms (12 signed orientations of the gradients of the log colour channels,
`offline.py`), pools them over k x k cells for each k of SCALES, and at each scale stacks the pooled histograms of
the 3 x 3 positions k cells apart around the cell: where around the cell each orientation occurs, as SIFT keeps it,
but on a grid of cells and at three widths (1, 3 and 5 cells: 24 to 120 pixels of a 256-pixel image). Each scale's
108 values are normalised as SIFT's are: to unit length (with a floor relative to the image's median, so that flat
sky is not noise blown up), clipped at CLIP, and to unit length again.

Why (docs/teacher-benchmark.md): on the paper's photo/render pairs the offline descriptor's pooled histograms give a
wide basin but drop where inside its region each orientation lies, and dense SIFT keeps that but over one 16-pixel
support, so its landscape is narrow. The layout at three scales keeps both. The clipping limits what the strongest
edges weigh, which a render's blur and haze change less than the fine ones.

Invariant, as the offline descriptor, to global exposure, per-channel white balance and gamma curves; not to
viewpoint changes beyond a cell, cast shadows, occluders.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from sg_nerfstudio.features.base import CellDescriptor
from sg_nerfstudio.features.offline import CELL, LOG_OFFSET, ORIENTATIONS, _box_pool, _cell_orientation_histograms, _sobel

SCALES = (1, 3, 5)
"""Widths, in cells, of the pooled histograms and of the steps between the 3 x 3 positions of one scale."""
LAYOUT = 3
"""Positions per side around the cell (3 x 3, centred on it)."""
CLIP = 0.2
"""SIFT's clipping of a unit-length descriptor."""
FLOOR = 0.1
"""Norm floor, as a share of the image's median descriptor norm (as the offline descriptor's)."""
DEFAULT_INPUT_SIZE = 256
VERSION = 1


class HogLayoutTeacher(CellDescriptor):
    """image [H, W, 3] in [0, 1] -> [rows, columns, 324] (3 scales x 9 positions x 12 orientations; long side:
    input_size / 8 cells)."""

    cell, default_input_size, cell_name = CELL, DEFAULT_INPUT_SIZE, "hog-layout cell size"
    feature_dim = len(SCALES) * LAYOUT**2 * ORIENTATIONS

    def settings(self) -> dict:
        return {"teacher": "hog_layout", "version": VERSION, "input_size": self.input_size, "cell": CELL,
                "orientations": ORIENTATIONS, "scales": list(SCALES), "layout": LAYOUT, "clip": CLIP, "floor": FLOOR}

    def describe_resized(self, pixels: Tensor) -> Tensor:
        """[1, 3, 8 rows, 8 columns] -> [1, 324, rows, columns]."""
        log_channels = torch.log(pixels.clamp(min=0.0) + LOG_OFFSET).transpose(0, 1)  # [3, 1, S, S]
        gx, gy = _sobel(log_channels[:, 0])
        cells = _cell_orientation_histograms(gx, gy, CELL)[None]  # [1, 12, rows, columns]
        scales = [_sift_normalised(_layout(cells if width == 1 else _box_pool(cells, width), width)) for width in SCALES]
        return torch.cat(scales, dim=1) / math.sqrt(len(SCALES))


def _layout(pooled: Tensor, step: int) -> Tensor:
    """[1, B, rows, columns] -> [1, 9 B, rows, columns]: at each cell, the pooled histograms of the LAYOUT x LAYOUT
    positions `step` cells apart centred on it (positions past the edge repeat the edge's)."""
    reach = (LAYOUT - 1) // 2 * step
    padded = F.pad(pooled, (reach, reach, reach, reach), mode="replicate")
    rows, columns = pooled.shape[-2:]
    offsets = range(0, 2 * reach + 1, step)
    return torch.cat([padded[..., down:down + rows, right:right + columns] for down in offsets for right in offsets], dim=1)


def _sift_normalised(descriptors: Tensor) -> Tensor:
    """[1, D, rows, columns] -> unit length with a floor, clipped at CLIP, unit length with the same floor again."""
    for clip in (CLIP, None):
        norm = descriptors.norm(dim=1, keepdim=True)
        floor = FLOOR * norm.flatten().median().detach().clamp(min=1e-6)
        descriptors = descriptors / torch.sqrt(norm**2 + floor**2)
        if clip is not None:
            descriptors = descriptors.clamp(max=clip)
    return descriptors
