"""Another minimum near the result: the verdict's look for a second answer one repetition away.

The verdict's 12 probes tell a minimum from a slope or a plateau, not one minimum from another: a facade of identical
windows has minima one window apart, equally deep (docs/measurements.md "A repetitive facade and the look for another
minimum"). Where nothing else fixes the pose (no keypoint anchors), the verdict also looks further:

1. *scan*: the result shifted along the photos' mean image axes, both ways, every `SCAN_STEP_CELLS` translation probes
   out to `SCAN_REACH_CELLS`, the robust objective at each;
2. *dip*: the lowest local minimum of those four profiles beyond the first step, refined to its parabola's vertex;
3. *descent*: if the dip reads within the gate (`DESCENT_GATE`) of the result, `REFINE_STEPS` steps of the
   registration's own optimiser from there (`refine`, given by the caller);
4. *compare*: an end at least `DISTINCT_CELLS` probes from the result is another minimum; its rise (T_other - T) / T is
   the evidence, and within `MARGIN` (or lower) the result is one of two answers the descriptor cannot tell apart.

The look runs on at most `PHOTOS` photos, those the model covers most at the result (not those with the lowest losses,
which favour the result). Frames: transforms are meta -> dataparser numpy Sim3s, as in `PhotoLosses`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from sg_nerfstudio.geometry.meta_image import MetaImage
from sg_nerfstudio.geometry.sim3 import Sim3, rotation_angle_deg

Array = np.ndarray

SCAN_STEP_CELLS = 2.0
"""Scan step in translation probes: a minimum of the offline descriptor is 3-4 cells wide, so a 2-cell step lands in it."""
SCAN_REACH_CELLS = 16.0
"""How far the scan looks, in translation probes: half the teacher grid of the fast presets (32 cells), i.e. half a
photo's width: a repetition must appear twice in a photo for the photo to be fooled by it."""
REFINE_STEPS = 20
"""Optimiser steps from the dip: enough to reach the floor of a minimum a scan step away (10 stopped short)."""
REFINE_LR = 0.01
"""Learning rate of the descent from the dip (decaying to a sixth, as the scan's step leaves it within a few cells)."""
PHOTOS = 6
"""The look uses at most this many photos (those the model covers most at the result)."""
DESCENT_GATE = 0.3
"""A dip is descended from only if it reads less than max(this, 2 x the result's sharpness) above the result: sampled up
to a cell from its bottom, a minimum as deep as the result reads about one cell's rise above it."""
DISTINCT_CELLS = 2.0
"""A descent that ends closer to the result than this many probes (translation or rotation) found the result again."""
MARGIN = 0.05
"""Another minimum less than this much higher than the result (relative) makes it uncertain: the same 5% the verdict
asks of a resolved minimum one cell away (`verdict.REGISTERED_SHARPNESS`)."""


@dataclass
class OtherMinimum:
    """The best other minimum the look found."""

    rise: float
    """(T_other - T) / T of the robust objective; negative: the other minimum is lower than the result."""
    distance_cells: float
    """How far it lies from the result, in probes: the larger of its cameras' centroid shift over the translation
    probe and its rotation over the rotation probe."""


def image_axes(meta: MetaImage, transform: Sim3) -> Array:
    """[2, 3] unit vectors of the dataparser frame: the mean of the photos' camera x axes under `transform` (meta ->
    dataparser), and the mean of their y axes made orthogonal to it."""
    rotations = np.stack([photo.cam_from_world[:, :3] for photo in meta.photos]) @ np.asarray(transform.rotation).T  # cam_from_dataparser
    x = rotations[:, 0, :].mean(0)
    x /= max(np.linalg.norm(x), 1e-12)
    y = rotations[:, 1, :].mean(0)
    y -= x * float(x @ y)
    y /= max(np.linalg.norm(y), 1e-12)
    return np.stack([x, y])


def shifted(transform: Sim3, offset: Array) -> Sim3:
    """`transform` followed by a translation of the dataparser frame by `offset` [3]."""
    return Sim3.from_parts(1.0, np.eye(3), np.asarray(offset, dtype=np.float64)) @ transform


def deepest_dip(profile: Array) -> Optional[tuple[int, float]]:
    """(index, parabola-vertex offset in samples) of the lowest local minimum of `profile` [K+1] (profile[0] at the
    result) after its first step, or None. A minimum at the last sample is not one (the profile may fall on)."""
    found = [
        i for i in range(2, len(profile) - 1) if profile[i] < profile[i - 1] and profile[i] <= profile[i + 1]
    ]
    if not found:
        return None
    index = min(found, key=lambda i: profile[i])
    before, at, after = profile[index - 1], profile[index], profile[index + 1]
    curvature = before - 2 * at + after
    return index, float(0.5 * (before - after) / curvature) if curvature > 0 else 0.0


def look_for_other_minimum(
    objective: Callable[[Sim3], float], refine: Callable[[Sim3], Sim3], meta: MetaImage, result: Sim3, result_value: float,
    rotation_probe: float, translation_probe: float, sharpness: float,
) -> Optional[OtherMinimum]:
    """The module's look (scan, dip, descent, compare) around `result` (meta -> dataparser), whose robust objective
    `objective(result)` is `result_value`; `refine(start)` runs the registration's optimiser for REFINE_STEPS steps;
    `rotation_probe` (radians), `translation_probe` (dataparser units) and `sharpness` are the verdict's probe sizes and
    median one-cell rise. None when the scan finds no dip, the dip does not pass the gate (DESCENT_GATE) or the descent
    comes back to the result."""
    step = SCAN_STEP_CELLS * translation_probe
    distances = np.arange(0.0, SCAN_REACH_CELLS + 1e-9, SCAN_STEP_CELLS) * translation_probe
    best: Optional[tuple[float, Array]] = None
    for axis in image_axes(meta, result):
        for direction in (axis, -axis):
            profile = np.array([result_value] + [objective(shifted(result, d * direction)) for d in distances[1:]])
            dip = deepest_dip(profile)
            if dip is None:
                continue
            offset = (distances[dip[0]] + dip[1] * step) * direction
            value = min(profile[dip[0]], objective(shifted(result, offset)))
            if best is None or value < best[0]:
                best = (value, offset)
    if best is None:
        return None
    value, offset = best
    if value / max(result_value, 1e-12) - 1.0 >= max(DESCENT_GATE, 2.0 * sharpness):
        return None
    other = refine(shifted(result, offset))
    moved = np.linalg.norm(meta.centroid_under(other) - meta.centroid_under(result)) / translation_probe
    turned = np.radians(rotation_angle_deg(np.asarray(other.rotation) @ np.asarray(result.rotation).T)) / rotation_probe
    distance = float(max(moved, turned))
    if distance < DISTINCT_CELLS:
        return None
    return OtherMinimum(rise=objective(other) / max(result_value, 1e-12) - 1.0, distance_cells=distance)
