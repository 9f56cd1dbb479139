"""The teacher benchmark: does a teacher's map of a photo single out the photo's true pose against a render of the
reference? Measured on photo/render pairs at a known pose (layout: bench/pairs.py; `sg-bench teacher PAIRS`).

A hypothesis is what a small pose error does to one photo: an image shift (the camera turned about its centre), an
in-plane rotation (a roll) or a zoom (a focal-length or scale error). The render is warped by it, photo and render
are cropped to the same centred square and described by the teacher, and the distance of the two maps (the mean over
cells of the L1 distance of their features, as the issue that asked for this benchmark defined it) is one point of a
landscape whose lowest point should be the truth (no warp).

Why crops of the warped render, not maps shifted by whole cells: photo and render then share one frame for every
hypothesis, as in registration (the render is always made with the photo's camera), so what a teacher does at the
frame's edge (padding, a network's border tokens) is the same everywhere. Shifting maps instead makes edge effects
line up at zero shift only: on the paper's pairs, dense SIFT with 12-pixel bins then calls 53% of photo/render pairs
of *different* landmarks "identifiable" (chance: 9 of 169 shifts, 5%); with crops, 10% (docs/teacher-benchmark.md).

Measures of one pair and one teacher:
- identifiable: the lowest point of the shift landscape (shifts up to MAX_SHIFT_CELLS cells of a GRID_CELLS-cell
  grid over the crop, 19% of its width) lies within one cell of the truth; for rotations and zooms, within one step;
- basin at k: the share of the starts k cells from the truth from which steepest descent over the 8 neighbouring
  shifts ends within one cell of it (what a descent-based registration can reach);
- prominence: how much larger the lowest distance at least FAR cells away is than the truth's, relative to it;
- control (every CONTROL_EVERY-th pair): the photo against a render of another landmark; identifiable there is a
  false positive.
And of the pair alone: SIFT matches (OpenCV, ratio SIFT_RATIO) that land within SIFT_TOLERANCE of their own position.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

import cv2
import numpy as np
import torch

from sg_nerfstudio.bench.pairs import Pair, read_pair, read_rgb

GRID_CELLS = 32
"""Cells across the crop that a shift is counted in (the offline teacher's grid at its default input size)."""
MAX_SHIFT_CELLS = 6
"""Largest shift, in cells: 6 / 32 = 19% of the crop's width."""
ANGLES = (-10.0, -7.5, -5.0, -2.5, 0.0, 2.5, 5.0, 7.5, 10.0)
"""In-plane rotations (degrees) of the rotation landscape."""
ZOOMS = (0.85, 0.9, 0.95, 1.0, 1.05, 1.1, 1.15)
"""Magnifications of the zoom landscape."""
BASIN_DISTANCES = (2, 3, 4, 5, 6)
FAR = 2
"""Cells from the truth where a hypothesis counts as a wrong one for the prominence."""
CONTROL_EVERY = 3
SIFT_RATIO = 0.8
SIFT_TOLERANCE = 4.0 / 300.0
"""Largest distance (a share of the short side: 4 pixels of a 300-pixel image) between a match's two positions."""
SIFT_ENOUGH = 15
"""Right matches a SIFT initialiser needs to place a photo (the share of pairs with this many is reported)."""

Describe = Callable[[np.ndarray], torch.Tensor]
"""A teacher as the benchmark calls it: [side, side, 3] float32 RGB in [0, 1] -> [rows, columns, features]."""


def crop_side(height: int, width: int) -> int:
    """Side of the centred square that stays inside an image of this size under every hypothesis (the largest shift
    on both sides; a 10° roll and a 0.85 zoom need less), rounded down to an even number of pixels."""
    return int(min(height, width) / (1.0 + 2.0 * MAX_SHIFT_CELLS / GRID_CELLS)) // 2 * 2


def hypothesis_view(image: np.ndarray, side: int, shift: tuple[float, float] = (0.0, 0.0), angle: float = 0.0,
                    zoom: float = 1.0) -> np.ndarray:
    """The [side, side, 3] crop of `image` [H, W, 3] centred `shift` = (right, down) pixels from its centre, with the
    content turned `angle` degrees (clockwise on screen: what lies right of the centre comes to lie below it at 90°)
    and magnified `zoom` times (bilinear)."""
    height, width = image.shape[:2]
    radians = math.radians(angle)
    turn = np.array([[math.cos(radians), math.sin(radians)], [-math.sin(radians), math.cos(radians)]]) / zoom
    source_centre = np.array([width / 2.0 + shift[0], height / 2.0 + shift[1]])
    crop_to_source = np.concatenate([turn, (source_centre - turn @ np.full(2, side / 2.0))[:, None]], axis=1)
    return cv2.warpAffine(image, crop_to_source, (side, side), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REFLECT)


def map_distance(first: torch.Tensor, second: torch.Tensor) -> float:
    """Mean over cells of the L1 distance of two [rows, columns, features] maps."""
    return float((first - second).abs().sum(dim=-1).mean())


@dataclass
class Landscapes:
    """Map distances of one photo to its render under each hypothesis; the truth is each array's centre."""

    shift: np.ndarray
    """[2 MAX_SHIFT_CELLS + 1, 2 MAX_SHIFT_CELLS + 1]: rows = downward shift, columns = rightward shift, in cells."""
    rotation: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """[len(ANGLES)]."""
    zoom: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """[len(ZOOMS)]."""


def landscapes(describe: Describe, photo: np.ndarray, render: np.ndarray, shift_only: bool = False) -> Landscapes:
    """The distance landscapes of `photo` against `render` (both [H, W, 3] float32, same size)."""
    side = crop_side(*photo.shape[:2])
    cell = side / GRID_CELLS
    photo_map = describe(hypothesis_view(photo, side))

    def distance(**hypothesis) -> float:
        return map_distance(photo_map, describe(hypothesis_view(render, side, **hypothesis)))

    shifts = range(-MAX_SHIFT_CELLS, MAX_SHIFT_CELLS + 1)
    shift = np.array([[distance(shift=(right * cell, down * cell)) for right in shifts] for down in shifts])
    if shift_only:
        return Landscapes(shift)
    return Landscapes(shift, np.array([distance(angle=a) for a in ANGLES]), np.array([distance(zoom=z) for z in ZOOMS]))


def descend(landscape: np.ndarray, start: tuple[int, ...]) -> tuple[int, ...]:
    """Where steepest descent from `start` over the neighbouring points (8 in 2D, 2 in 1D) of `landscape` stops."""
    here = tuple(start)
    offsets = [o for o in np.ndindex(*(3,) * landscape.ndim) if any(v != 1 for v in o)]
    while True:
        neighbours = [tuple(h + o - 1 for h, o in zip(here, offset)) for offset in offsets]
        inside = [n for n in neighbours if all(0 <= v < s for v, s in zip(n, landscape.shape))]
        best = min(inside, key=lambda n: landscape[n])
        if landscape[best] >= landscape[here]:
            return here
        here = best


def _steps_from_truth(point: tuple[int, ...], landscape: np.ndarray) -> int:
    return max(abs(v - s // 2) for v, s in zip(point, landscape.shape))


def identifiable(landscape: np.ndarray) -> bool:
    """Whether the landscape's lowest point is within one step of its centre (the truth)."""
    return bool(_steps_from_truth(np.unravel_index(int(np.argmin(landscape)), landscape.shape), landscape) <= 1)


def basin(landscape: np.ndarray, distance: int) -> float:
    """Share of the points `distance` steps from the centre from which `descend` ends within one step of it."""
    starts = [p for p in np.ndindex(*landscape.shape) if _steps_from_truth(p, landscape) == distance]
    return float(np.mean([_steps_from_truth(descend(landscape, p), landscape) <= 1 for p in starts]))


def prominence(landscape: np.ndarray) -> float:
    """(lowest distance >= FAR steps from the truth - the truth's) / the truth's: > 0 when the truth stands out."""
    truth = landscape[tuple(s // 2 for s in landscape.shape)]
    far = [landscape[p] for p in np.ndindex(*landscape.shape) if _steps_from_truth(p, landscape) >= FAR]
    return float((min(far) - truth) / max(truth, 1e-12))


def pair_measures(found: Landscapes) -> dict:
    """The measures (module docstring) of one pair's landscapes, as a JSON-ready dict."""
    measures = {
        "identifiable": identifiable(found.shift),
        "basin": {str(k): basin(found.shift, k) for k in BASIN_DISTANCES},
        "prominence": prominence(found.shift),
    }
    for name, line in (("rotation", found.rotation), ("zoom", found.zoom)):
        if line.size:
            measures[f"{name}_identifiable"] = identifiable(line)
            measures[f"{name}_basin"] = basin(line, line.size // 2)  # from both ends
    return measures


def sift_matches(photo: np.ndarray, render: np.ndarray) -> int:
    """SIFT matches (OpenCV, Lowe's ratio SIFT_RATIO) whose two positions lie within SIFT_TOLERANCE of each other."""
    sift = cv2.SIFT_create()
    found = [sift.detectAndCompute(cv2.cvtColor((image * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY), None)
             for image in (photo, render)]
    (points_photo, photo_descriptors), (points_render, render_descriptors) = found
    if photo_descriptors is None or render_descriptors is None or len(render_descriptors) < 2:
        return 0
    tolerance = SIFT_TOLERANCE * min(photo.shape[:2])
    right = 0
    for candidates in cv2.BFMatcher().knnMatch(photo_descriptors, render_descriptors, k=2):
        if len(candidates) == 2 and candidates[0].distance < SIFT_RATIO * candidates[1].distance:
            a, b = points_photo[candidates[0].queryIdx].pt, points_render[candidates[0].trainIdx].pt
            right += math.dist(a, b) <= tolerance
    return right


def control_partner(index: int, landmarks: list[str]) -> Optional[int]:
    """The pair whose render serves as `index`'s control: the first, half the list on, of another landmark (of another
    pair when there is one landmark); None for a single pair."""
    count = len(landmarks)
    order = [(index + count // 2 + step) % count for step in range(count)]
    others = [j for j in order if landmarks[j] != landmarks[index]] or [j for j in order if j != index]
    return others[0] if others else None


def colour_cells(image: np.ndarray) -> torch.Tensor:
    """The photometric baseline: [side, side, 3] -> [GRID_CELLS, GRID_CELLS, 3] mean colour per cell, each channel
    standardised over the image (so a global exposure or tint is removed)."""
    cells = cv2.resize(image, (GRID_CELLS, GRID_CELLS), interpolation=cv2.INTER_AREA)
    return torch.from_numpy((cells - cells.mean(axis=(0, 1))) / (cells.std(axis=(0, 1)) + 1e-6))


BASELINE = "colour"
"""The photometric baseline's name among the benchmark's teachers."""


def build_describers(names: tuple[str, ...], dinov2_weights=None, dinov2_input_size: int = 448) -> dict[str, Describe]:
    """name -> Describe for the baseline and the package's teachers (each at its default input size; DINOv2 at
    `dinov2_input_size`, 32 patches, from local weights). TeacherInputError (one sentence) when one cannot load."""
    from sg_nerfstudio.features import TeacherConfig, TeacherInputError, build_teacher
    from sg_nerfstudio.features.dinov2 import weight_search_paths

    if "dinov2" in names and dinov2_weights is None and not any(path.exists() for path in weight_search_paths(None)):
        listed = "; ".join(str(path) for path in weight_search_paths(None))
        raise TeacherInputError(f"No DINOv2 ViT-S/14 weights found (looked at: {listed}); pass --dinov2-weights FILE or leave dinov2 out of --teachers.")
    describers: dict[str, Describe] = {}
    for name in names:
        if name == BASELINE:
            describers[name] = colour_cells
            continue
        config = TeacherConfig(name=name, weights=dinov2_weights, input_size=dinov2_input_size if name == "dinov2" else None)
        teacher = build_teacher(config)
        describers[name] = lambda image, teacher=teacher: teacher.extract(torch.from_numpy(image))
    return describers


def benchmark_pair(describers: dict[str, Describe], photo: np.ndarray, render: np.ndarray,
                   control: Optional[np.ndarray]) -> tuple[dict, dict[str, Landscapes]]:
    """One pair's record ({"sift_matches", "teachers": {name: measures}, "seconds": {name: s}}) and its landscapes
    by teacher; `control` is a render of another landmark (or None)."""
    record: dict = {"sift_matches": sift_matches(photo, render), "teachers": {}, "seconds": {}}
    found = {}
    for name, describe in describers.items():
        started = time.perf_counter()
        found[name] = landscapes(describe, photo, render)
        record["teachers"][name] = pair_measures(found[name])
        if control is not None:
            record["teachers"][name]["control_identifiable"] = identifiable(landscapes(describe, photo, control, shift_only=True).shift)
        record["seconds"][name] = time.perf_counter() - started
    return record, found


def figure_pairs(pairs: list[Pair], count: int = 4) -> list[int]:
    """Indices of the pairs the landscape figure shows: the first pair of each of the first `count` landmarks (more
    pairs of the first landmark when there are fewer landmarks)."""
    firsts = [i for i, pair in enumerate(pairs) if i == 0 or pairs[i - 1].landmark != pair.landmark]
    return (firsts + [i for i in range(len(pairs)) if i not in firsts])[:count]


def run_pairs(pairs: list[Pair], describers: dict[str, Describe], on_pair: Callable[[int], None] = lambda i: None) -> tuple[list[dict], list]:
    """Every pair's record (benchmark_pair's, with its landmark and name), and the figure's pairs as (title, photo,
    render, landscapes by teacher). Reads each image when its pair comes (PairsError names a bad one)."""
    landmarks = [pair.landmark for pair in pairs]
    shown_indices = set(figure_pairs(pairs))
    records, shown = [], []
    for index, pair in enumerate(pairs):
        photo, render = read_pair(pair)
        partner = control_partner(index, landmarks) if index % CONTROL_EVERY == 0 else None
        control = _resized_like(read_rgb(pairs[partner].render), photo) if partner is not None else None
        record, found = benchmark_pair(describers, photo, render, control)
        records.append({"landmark": pair.landmark, "name": pair.name, **record})
        if index in shown_indices:
            shown.append((f"{pair.landmark}/{pair.name}", photo, render, found))
        on_pair(index)
    return records, shown


def _resized_like(image: np.ndarray, like: np.ndarray) -> np.ndarray:
    """`image` resized to `like`'s size (a control render from a pair of another size)."""
    if image.shape == like.shape:
        return image
    return cv2.resize(image, (like.shape[1], like.shape[0]), interpolation=cv2.INTER_AREA)
