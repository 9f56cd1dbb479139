"""Depth agreement: do the meta-image's own sparse points lie on the reference's surface under a Sim(3)?

A Sim(3) T (meta -> dataparser, scale s) moves a photo's camera and the points it observes together, so under
any T each point projects to the same pixel u of the photo, at camera depth s * z (z: its depth in the meta
camera). The reference rendered from the moved camera has an expected depth D(u) at that pixel. At the right T,

    r = log D(u) - log s - log z

is near 0 for most points: apart from SfM noise, the reference's blur at depth edges, and points on what stands
in front of the landmark (people, vehicles: closer than the reference's surface). A wrong scale, or cameras
moved along their view direction, shifts r for all points at once; a rotation of a facade's photos tilts r
across each photo.

The dense objective sees scale only through the parallax between the photos (weak for three photos along one
facade) and depth only through the photos' magnification, so a registration can drift in scale and depth
while its renders still match. r measures that with no ground truth; the verdict reports it (`summarise`) and, where
most points agree, lets it hold a shallow minimum (`verdict.Evidence.depths_hold`).
About 0.1 for a 10% scale error; as a term of the objective it was tried and not kept (docs/measurements.md "Depth
agreement").
Frames: points in each photo's OpenCV camera frame (meta units); renders in the dataparser frame. Written here
because it is a comparison of two of this project's own inputs (no library has it); the expected depth itself is the
rasterizer's "RGB+ED" mode (gsplat's convention).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

MIN_ALPHA = 0.5
"""A point counts only where the reference covers its pixel at least this much (sky and empty space do not)."""
AGREEING_LOG_RATIO = 0.1
"""A point agrees when its rendered depth is within about 10% of its own (|r| below this)."""


@dataclass
class PointPixels:
    """The sparse points one photo observes, where they land in its render (fixed: independent of the Sim(3)).

    rows, columns: [M] int64 pixel of each point in the render (K at render size, pixel centres at +0.5);
    log_depth: [M] float64 log z, the point's depth in the photo's meta-frame camera. Points behind the camera
    or outside the render are left out."""

    rows: Tensor
    columns: Tensor
    log_depth: Tensor

    @classmethod
    def of(cls, points_camera: np.ndarray, K: np.ndarray, width: int, height: int) -> "PointPixels":
        """From the points [M, 3] in the photo's camera frame and its render's K [3, 3] and size."""
        points = points_camera[points_camera[:, 2] > 0]
        pixels = points @ K.T
        columns = np.floor(pixels[:, 0] / pixels[:, 2]).astype(np.int64)
        rows = np.floor(pixels[:, 1] / pixels[:, 2]).astype(np.int64)
        inside = (columns >= 0) & (columns < width) & (rows >= 0) & (rows < height)
        return cls(torch.from_numpy(rows[inside]), torch.from_numpy(columns[inside]), torch.from_numpy(np.log(points[inside, 2])))


def log_depth_ratios(depth: Tensor, alpha: Tensor, pixels: PointPixels, log_scale: Tensor) -> Tensor:
    """r [M'] of the points whose pixel the reference covers (alpha >= MIN_ALPHA, rendered depth > 0).

    Args:
        depth: [H, W] expected depth rendered from the moved camera (dataparser units), with gradients.
        alpha: [H, W] the render's alpha.
        log_scale: scalar log s of the Sim(3) (with gradients, or a float tensor).
    """
    rendered = depth[pixels.rows, pixels.columns].double()
    valid = (alpha.detach()[pixels.rows, pixels.columns] >= MIN_ALPHA) & (rendered.detach() > 0)
    return torch.log(rendered[valid]) - log_scale - pixels.log_depth[valid]


@dataclass
class DepthAgreement:
    """`log_ratio`: the median r over the photos' covered points (nan without any); `agreeing`: the share of
    those points with |r| < AGREEING_LOG_RATIO; `points`: how many were covered."""

    log_ratio: float
    agreeing: float
    points: int


def summarise(ratios: list[Tensor]) -> DepthAgreement:
    """The pooled median and agreeing share of per-photo ratios (`log_depth_ratios`)."""
    pooled = torch.cat([r.detach().double() for r in ratios]).numpy() if ratios else np.zeros(0)
    if len(pooled) == 0:
        return DepthAgreement(log_ratio=float("nan"), agreeing=0.0, points=0)
    return DepthAgreement(
        log_ratio=float(np.median(pooled)), agreeing=float(np.mean(np.abs(pooled) < AGREEING_LOG_RATIO)), points=len(pooled),
    )
