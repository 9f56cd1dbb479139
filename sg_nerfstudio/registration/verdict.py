"""A verdict per registration — `registered`, `uncertain` or `failed` — from evidence that needs no ground truth.

After the optimisation the frozen model is rendered at 12 *probes* around the result: the Sim(3) rotated by
±h_r about each axis and shifted by ±h_t along each axis of the dataparser frame, about the centroid of
the moved cameras. h_r is one teacher cell's angle (the photos' median long-side field of view / the
teacher grid) and h_t the distance that moves a point at the photos' median sparse-point depth by the same
angle, so every probe shifts the image by about one descriptor cell. Evidence:

- `sharpness`: the median over probes of the robust objective's relative rise (T_probe - T) / T, with T the
  trimmed mean of the per-photo losses (the robust rule of the registration). A registration that found
  the model sits in a minimum the descriptor resolves; one that sees the wrong thing sits on a plateau.
- `flattest_rise`: the smallest of those rises; below `DESCENT_TOLERANCE` a probe is better than the result
  (the optimisation stopped on a slope, not in a minimum).
- `agreeing_photos`: photos that are at their own minimum (median rise of their own loss over the probes
  at least `PHOTO_RISE`) and that the model covers (at least `PHOTO_COVERAGE` of the render). Occluded or
  wrong photos do not agree; a wrong result has few photos that agree.
- `objective_drop`: 1 - T_final / T_initial (reported, not used: a good start has little to gain).
- `keypoint_error_cells`, `keypoint_photos` (with keypoint anchors only, registration/keypoints.py): the median
  reprojection error of the anchors at the result, in teacher cells, and how many photos have anchors. The anchors
  are RANSAC-verified matches of the photos against the reference's own images: when those of at least
  `ANCHORED_PHOTOS` photos reproject within `ANCHORS_HOLD_CELLS` at the result, they fix the pose where the dense
  objective is shallow (a reference of few views or points), so a shallow minimum alone does not make it uncertain.
- `depth_log_ratio`, `depth_agreeing`, `depth_points` (registration/depth_agreement.py): the median log ratio of
  the reference's rendered depth to the meta-image's own sparse points' depth at the result, the share of
  points within 10%, and how many the model covers; reported, not used: a wrong scale or depth shows there
  (0.1 for 10%), but most inaccurate results of the benchmark (3 of wide-cpu's 5 from 30°) were rotations that
  keep the depths (docs/measurements.md "Depth agreement").
- `hypothesis_margin` (with `hypotheses` only): how much higher, relative to the winner, the objective ended
  for the best optimised hypothesis that finished elsewhere (more than 2° away); reported, not used.

Rule (thresholds calibrated on generated scenes, see README "Verdict"): `failed` when fewer than
`FAILED_AGREEING` of the photos agree or the objective is flat (sharpness below `FAILED_SHARPNESS`);
`registered` when at least `REGISTERED_AGREEING` agree, sharpness is at least `REGISTERED_SHARPNESS` (or the
anchors hold, above) and no probe descends; `uncertain` otherwise. Frames: the transform is meta -> dataparser, as in `PhotoLosses`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Literal, Optional

import numpy as np
import torch
from torch import Tensor

from sg_nerfstudio.geometry.meta_image import MetaImage
from sg_nerfstudio.geometry.sim3 import Sim3
from sg_nerfstudio.registration.depth_agreement import DepthAgreement
from sg_nerfstudio.registration.robust import TrimmingRule

Array = np.ndarray
Label = Literal["registered", "uncertain", "failed"]
SEVERITY = {"registered": 0, "uncertain": 1, "failed": 2}

PHOTO_RISE = 0.02
PHOTO_COVERAGE = 0.25
DESCENT_TOLERANCE = -0.005
FAILED_AGREEING = 1 / 3
FAILED_SHARPNESS = 0.015
REGISTERED_AGREEING = 0.5
REGISTERED_SHARPNESS = 0.05
ANCHORED_PHOTOS = 2  # one photo's anchors fix its own pose, not the meta-image's scale
ANCHORS_HOLD_CELLS = 0.25  # chosen, not calibrated: anchored results sit at 0.02-0.17 cells, a pose 3° off at several


@dataclass
class Evidence:
    """What the verdict is decided from (all fractions relative; see the module docstring)."""

    sharpness: float
    flattest_rise: float
    agreeing_photos: int
    photos: int
    median_coverage: float
    objective_drop: float
    probe_rotation_deg: float
    probe_translation: float  # dataparser units
    per_photo_rise: list[float] = field(default_factory=list)
    per_photo_coverage: list[float] = field(default_factory=list)
    hypothesis_margin: Optional[float] = None
    keypoint_error_cells: Optional[float] = None
    keypoint_photos: Optional[int] = None
    depth_log_ratio: Optional[float] = None
    depth_agreeing: Optional[float] = None
    depth_points: int = 0

    @property
    def agreeing_fraction(self) -> float:
        return self.agreeing_photos / max(self.photos, 1)

    @property
    def anchors_hold(self) -> bool:
        """Whether the keypoint anchors of at least ANCHORED_PHOTOS photos reproject within ANCHORS_HOLD_CELLS."""
        if self.keypoint_photos is None or self.keypoint_error_cells is None:
            return False
        return self.keypoint_photos >= ANCHORED_PHOTOS and self.keypoint_error_cells <= ANCHORS_HOLD_CELLS


@dataclass
class Verdict:
    label: Label
    reasons: list[str]
    evidence: Evidence

    def as_record(self) -> dict:
        return {"verdict": self.label, "reasons": self.reasons, "evidence": asdict(self.evidence)}


def probe_sizes(meta: MetaImage, photos, grid_size: int, meta_to_dataparser: Sim3) -> tuple[float, float]:
    """(h_r radians, h_t dataparser units): one teacher cell's angle and the shift that moves a point at the
    median sparse-point depth by that angle. `photos`: PreparedPhoto list (K and render width/height)."""
    fovs = [2.0 * math.atan(0.5 * max(p.width, p.height) / float(p.K[0, 0] if p.width >= p.height else p.K[1, 1])) for p in photos]
    rotation = float(np.median(fovs)) / grid_size
    depths = np.concatenate([photo.point_depths for photo in meta.photos])
    depths = depths[depths > 0]
    depth = float(np.median(depths)) * meta_to_dataparser.scale if len(depths) else 1.0
    return rotation, depth * rotation


def probes(rotation: float, translation: float) -> list[Tensor]:
    """12 deltas (omega, nu, log s) [7]: ±rotation about each axis, ±translation along each axis."""
    deltas = []
    for offset, size in ((0, rotation), (3, translation)):
        for axis in range(3):
            for sign in (1.0, -1.0):
                delta = torch.zeros(7, dtype=torch.float64)
                delta[offset + axis] = sign * size
                deltas.append(delta)
    return deltas



def gather_evidence(
    losses, meta: MetaImage, final_ns: Sim3, final_losses: Array, coverage: Array, initial_losses: Array, rule: TrimmingRule,
    depth: Optional[DepthAgreement] = None,
) -> Evidence:
    """Render the probes around `final_ns` (meta -> dataparser) and measure the evidence.

    Args:
        losses: the registration's `objectives.PhotoLosses`.
        final_losses, initial_losses: [P] per-photo losses at the result and at the start.
        coverage: [P] fraction of each photo's render the model covers at the result.
        rule: the registration's robust rule (the objective T is its trimmed mean).
        depth: the depth agreement at the result (`depth_agreement.summarise`), reported as it is; None: not measured.
    """
    indices = list(range(len(losses.photos)))
    rotation, translation = probe_sizes(meta, losses.photos, losses.objective.teacher.grid_size, final_ns)
    start = final_ns.to_torch()
    centre = torch.from_numpy(meta.centroid_under(final_ns))
    with torch.no_grad():
        probe_losses = np.stack([
            torch.stack(losses(Sim3.update(delta, centre) @ start, indices)[0]).double().numpy() for delta in probes(rotation, translation)
        ])  # [12, P]
    final = rule.trimmed_mean(final_losses)
    rises = np.array([rule.trimmed_mean(row) for row in probe_losses]) / max(final, 1e-12) - 1.0
    photo_rise = np.median(probe_losses / np.maximum(final_losses, 1e-12)[None] - 1.0, axis=0)
    agreeing = (photo_rise >= PHOTO_RISE) & (coverage >= PHOTO_COVERAGE)
    initial = rule.trimmed_mean(initial_losses)
    return Evidence(
        sharpness=float(np.median(rises)), flattest_rise=float(rises.min()), agreeing_photos=int(agreeing.sum()),
        photos=len(indices), median_coverage=float(np.median(coverage)), objective_drop=1.0 - final / max(initial, 1e-12),
        probe_rotation_deg=math.degrees(rotation), probe_translation=translation,
        per_photo_rise=[float(v) for v in photo_rise], per_photo_coverage=[float(v) for v in coverage],
        depth_log_ratio=depth.log_ratio if depth and depth.points else None,
        depth_agreeing=depth.agreeing if depth and depth.points else None, depth_points=depth.points if depth else 0,
    )


def decide(evidence: Evidence) -> Verdict:
    """The label and the reasons for it (see the module docstring for the rule)."""
    agreeing = f"{evidence.agreeing_photos} of {evidence.photos} photos agree"
    sharp = f"objective rises {100 * evidence.sharpness:.1f}% one cell away"
    if evidence.agreeing_fraction < FAILED_AGREEING:
        return Verdict("failed", [f"only {agreeing}", sharp], evidence)
    if evidence.sharpness < FAILED_SHARPNESS:
        return Verdict("failed", [f"flat objective: {sharp}", agreeing], evidence)
    reasons = []
    if evidence.agreeing_fraction < REGISTERED_AGREEING:
        reasons.append(f"only {agreeing}")
    if evidence.sharpness < REGISTERED_SHARPNESS and not evidence.anchors_hold:
        reasons.append(f"shallow minimum: {sharp}")
    if evidence.flattest_rise < DESCENT_TOLERANCE:
        reasons.append(f"not converged: a probe is {100 * -evidence.flattest_rise:.1f}% lower")
    if reasons:
        return Verdict("uncertain", reasons, evidence)
    if evidence.sharpness < REGISTERED_SHARPNESS:
        held = f"anchors of {evidence.keypoint_photos} photos hold within {evidence.keypoint_error_cells:.2f} cells"
        return Verdict("registered", [agreeing, f"shallow minimum ({sharp}) but {held}"], evidence)
    return Verdict("registered", [agreeing, sharp], evidence)
