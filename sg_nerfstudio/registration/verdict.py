"""A verdict per registration — `registered`, `uncertain` or `failed` — from evidence that needs no ground truth.

After the optimisation the frozen model is rendered at 12 *probes* around the result: the Sim(3) turned by one teacher
cell's angle about each axis and shifted by the distance that moves a point at the photos' median depth as much, both
ways. A result that found the model sits in a minimum the descriptor resolves and that most photos share; one that sees
the wrong thing sits on a plateau that few photos agree with. `Evidence` lists what is measured; docs/verdict.md says
what each piece of evidence means and how the thresholds were chosen.

Without keypoint anchors six *orbit probes* follow: the result turned by ORBIT_DEG about each axis through where the
photos look, the direction the dense objective resolves worst.

Rule: `failed` when too few photos agree or the objective is flat. `registered` when enough photos agree, the minimum
is sharp (or shallow but held by keypoint anchors or by the meta-image's own depths), no probe (orbit probes included)
descends, no photo contradicts the result, the anchors (if any) reproject close, no camera fit was refused, no other minimum lies close
and the scale (where the anchors left it free) is seen. `uncertain` otherwise, with the reasons.

| threshold | value | meaning |
|---|---|---|
| `FAILED_AGREEING` | 1/3 | fewer photos than this share agree: failed |
| `FAILED_SHARPNESS` | 1.5% | the objective rises less one cell away: flat, failed (and a free scale not seen: uncertain) |
| `REGISTERED_AGREEING` | 1/2 | at least this share of photos agree to register |
| `REGISTERED_SHARPNESS` | 5% | the rise one cell away a registered minimum needs (unless anchors or depths hold it) |
| `DESCENT_TOLERANCE` | -0.5% | a probe (or an orbit probe) lower than the result by more: not converged |
| `ORBIT_DEG` | 2.5° | the orbit probes' turn about where the photos look (half the benchmark's 5° accuracy angle) |
| `PHOTO_RISE` | 2% | a photo agrees when its own loss rises this much at the median probe; contradicts when it falls this much |
| `PHOTO_COVERAGE` | 25% | ... and the model covers at least this share of its render |
| `ANCHORS_HOLD_CELLS` | 0.25 | anchors hold when their median reprojection error is within this many teacher cells |
| `DEPTH_HOLDS_SHARE` | 60% | the depths hold when this share of the meta-image's sparse points lie within 10% of the rendered depth |
| `DEPTH_HOLDS_POINTS` | 50 | ... of at least this many covered points |
| `other_minimum.MARGIN` | 5% | another minimum less than this much higher than the result: uncertain |

Frames: the transform is meta -> dataparser, as in `PhotoLosses`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Literal, Optional

import numpy as np
import torch
from torch import Tensor

from sg_nerfstudio.geometry.alignment import camera_centres
from sg_nerfstudio.geometry.meta_image import MetaImage
from sg_nerfstudio.geometry.sim3 import Sim3
from sg_nerfstudio.registration.depth_agreement import AGREEING_LOG_RATIO, DepthAgreement
from sg_nerfstudio.registration.anchored_start import anchors_fix_scale
from sg_nerfstudio.registration.other_minimum import MARGIN as OTHER_MINIMUM_MARGIN
from sg_nerfstudio.registration.robust import TrimmingRule

Array = np.ndarray
Label = Literal["registered", "uncertain", "failed"]
SEVERITY = {"registered": 0, "uncertain": 1, "failed": 2}

PHOTO_RISE = 0.02
"""A photo's own loss rising this much at the median probe puts it at its minimum (falling as much: it contradicts)."""
PHOTO_COVERAGE = 0.25
"""A photo agrees or contradicts only where the model covers this share of its render (an empty render reads flat)."""
DESCENT_TOLERANCE = -0.005
"""A probe lower than the result by more than this (relative): the optimisation stopped on a slope, not in a minimum."""
FAILED_AGREEING = 1 / 3
"""Fewer agreeing photos than this share: failed. Calibrated on generated scenes (docs/verdict.md)."""
FAILED_SHARPNESS = 0.015
"""A rise of the objective below this one cell away is a plateau: failed. Calibrated on generated scenes (docs/verdict.md)."""
REGISTERED_AGREEING = 0.5
"""A registered result needs at least this share of its photos agreeing (the median rule counts half of them)."""
REGISTERED_SHARPNESS = 0.05
"""A registered minimum rises at least this much one cell away, unless anchors or depths hold it. Calibrated on generated
scenes (docs/verdict.md)."""
ORBIT_DEG = 2.5
"""The orbit probes turn the result this far about where the photos look (`MetaImage.look_at_under`): half the
benchmark's accuracy angle (`metrics.ACCURATE`), so a result that far off along the weakest direction sees it descend."""
ANCHORS_HOLD_CELLS = 0.25
"""Chosen, not calibrated: anchored results sit at 0.02-0.17 cells, a pose 3° off at several."""
DEPTH_HOLDS_SHARE = 0.6
"""Chosen, not calibrated: accurate real-photo results without anchors read a median of 93% (10th percentile 70%), outliers 3-49%."""
DEPTH_HOLDS_POINTS = 50
"""Chosen, not calibrated: a handful of points agree by chance; accurate real-photo results cover 74-2289."""


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
    hypothesis_elsewhere_deg: Optional[float] = None
    keypoint_error_cells: Optional[float] = None
    keypoint_photos: Optional[int] = None
    keypoint_scale_motion_px: Optional[float] = None
    keypoint_error_px: Optional[float] = None
    depth_log_ratio: Optional[float] = None
    depth_agreeing: Optional[float] = None
    depth_points: int = 0
    scale_rise: Optional[float] = None
    scale_probe: Optional[float] = None
    camera_fit_refused: Optional[str] = None
    other_minimum_rise: Optional[float] = None
    other_minimum_cells: Optional[float] = None
    orbit_rise: Optional[float] = None

    @property
    def agreeing_fraction(self) -> float:
        return self.agreeing_photos / max(self.photos, 1)

    @property
    def anchors_hold(self) -> bool:
        """Whether the keypoint anchors reproject within ANCHORS_HOLD_CELLS and fix the scale (a 2% change moves them
        by more than their median error: `keypoints.anchors_fix_scale`)."""
        if None in (self.keypoint_error_cells, self.keypoint_scale_motion_px, self.keypoint_error_px):
            return False
        return self.keypoint_error_cells <= ANCHORS_HOLD_CELLS and anchors_fix_scale(self.keypoint_scale_motion_px, self.keypoint_error_px)

    @property
    def depths_hold(self) -> bool:
        """Whether at least DEPTH_HOLDS_SHARE of at least DEPTH_HOLDS_POINTS covered sparse points of the meta-image lie
        within 10% of the reference's rendered depth at the result (`depth_agreement`)."""
        if self.depth_agreeing is None:
            return False
        return self.depth_points >= DEPTH_HOLDS_POINTS and self.depth_agreeing >= DEPTH_HOLDS_SHARE


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
    depth: Optional[DepthAgreement] = None, scale_free_about: Optional[list[str]] = None,
) -> Evidence:
    """Render the probes around `final_ns` (meta -> dataparser) and measure the evidence.

    Args:
        losses: the registration's `objectives.PhotoLosses`.
        final_losses, initial_losses: [P] per-photo losses at the result and at the start.
        coverage: [P] fraction of each photo's render the model covers at the result.
        rule: the registration's robust rule (the objective T is its trimmed mean).
        depth: the depth agreement at the result (`depth_agreement.summarise`), reported as it is; None: not measured.
        scale_free_about: names of the anchored photos when the anchors left the scale free (the scale probes about
            their mean camera centre); None: no scale probes.
    """
    indices = list(range(len(losses.photos)))
    rotation, translation = probe_sizes(meta, losses.photos, losses.objective.teacher.grid_size, final_ns)
    start = final_ns.to_torch()
    centre = torch.from_numpy(meta.centroid_under(final_ns))
    probe_losses = np.stack([losses_at(losses, Sim3.update(delta, centre) @ start, indices) for delta in probes(rotation, translation)])  # [12, P]
    final = rule.trimmed_mean(final_losses)
    rises = np.array([rule.trimmed_mean(row) for row in probe_losses]) / max(final, 1e-12) - 1.0
    photo_rise = np.median(probe_losses / np.maximum(final_losses, 1e-12)[None] - 1.0, axis=0)
    agreeing = (photo_rise >= PHOTO_RISE) & (coverage >= PHOTO_COVERAGE)
    initial = rule.trimmed_mean(initial_losses)
    scale_rise, scale_probe = scale_probes(losses, meta, final_ns, final_losses, rule, translation, scale_free_about)
    return Evidence(
        sharpness=float(np.median(rises)), flattest_rise=float(rises.min()), agreeing_photos=int(agreeing.sum()),
        photos=len(indices), median_coverage=float(np.median(coverage)), objective_drop=1.0 - final / max(initial, 1e-12),
        probe_rotation_deg=math.degrees(rotation), probe_translation=translation,
        per_photo_rise=[float(v) for v in photo_rise], per_photo_coverage=[float(v) for v in coverage],
        depth_log_ratio=depth.log_ratio if depth and depth.points else None,
        depth_agreeing=depth.agreeing if depth and depth.points else None, depth_points=depth.points if depth else 0,
        scale_rise=scale_rise, scale_probe=scale_probe,
    )


def scale_probes(
    losses, meta: MetaImage, final_ns: Sim3, final_losses: Array, rule: TrimmingRule, translation: float, anchored: Optional[list[str]],
) -> tuple[Optional[float], Optional[float]]:
    """(scale_rise, scale_probe) of the Evidence (see the module docstring), or (None, None) without `anchored` names or
    without photos outside them. `translation`: the translation probe's size (dataparser units)."""
    names = [photo.name for photo in losses.photos]
    others = [index for index, name in enumerate(names) if name not in set(anchored or [])]
    if not anchored or not others or len(others) == len(names):
        return None, None
    by_name = {photo.name: photo for photo in meta.photos}
    centres = final_ns.apply(camera_centres(np.stack([by_name[name].cam_from_world for name in names])))
    centre = centres[[index for index in range(len(names)) if index not in others]].mean(0)
    step = translation / max(float(np.median(np.linalg.norm(centres[others] - centre, axis=1))), 1e-12)
    base = max(rule.trimmed_mean(final_losses[others]), 1e-12)
    rises = []
    for factor in (1.0 + step, 1.0 / (1.0 + step)):
        probe = Sim3.scaling_about(factor, centre) @ final_ns
        rises.append(rule.trimmed_mean(losses_at(losses, probe.to_torch(), others)) / base - 1.0)
    return float(min(rises)), float(step)


def orbit_probes(angle: float) -> list[Tensor]:
    """6 deltas (omega, nu, log s) [7]: ±`angle` radians about each axis (applied about where the photos look)."""
    return probes(angle, 0.0)[:6]  # the rotation half


def orbit_rise(losses, meta: MetaImage, final_ns: Sim3, final_losses: Array, rule: TrimmingRule) -> float:
    """The smallest relative rise of the robust objective when `final_ns` (meta -> dataparser) turns by ±ORBIT_DEG
    about each axis through where the photos look. Such an orbit keeps the photographed scene near the same pixels and
    changes only its parallax, the motion the dense objective resolves worst on few photos or a coarse reference; a
    negative value means the result is not at its minimum along it. `final_losses` [P]: the per-photo losses there."""
    centre = torch.from_numpy(meta.look_at_under(final_ns))
    start = final_ns.to_torch()
    indices = list(range(len(losses.photos)))
    base = max(rule.trimmed_mean(final_losses), 1e-12)
    values = [rule.trimmed_mean(losses_at(losses, Sim3.update(delta, centre) @ start, indices)) for delta in orbit_probes(math.radians(ORBIT_DEG))]
    return float(min(values) / base - 1.0)


def losses_at(losses, meta_to_dataparser: Tensor, indices: list[int]) -> Array:
    """[B] per-photo losses of the photos `indices` under a torch Sim3 (meta -> dataparser), without gradients."""
    with torch.no_grad():
        return torch.stack(losses(meta_to_dataparser, indices)[0]).double().numpy()


def agreement_and_sharpness(evidence: Evidence) -> tuple[str, str]:
    """The two phrases every verdict's reasons are made of: how many photos agree, how far the objective rises."""
    return f"{evidence.agreeing_photos} of {evidence.photos} photos agree", f"objective rises {100 * evidence.sharpness:.1f}% one cell away"


def depths_phrase(evidence: Evidence) -> str:
    """How many of the meta-image's sparse points lie on the reference's surface (`Evidence.depths_hold`)."""
    within = f"{100 * AGREEING_LOG_RATIO:.0f}%"  # |log depth ratio| under it: about that share of the depth
    return f"{100 * evidence.depth_agreeing:.0f}% of {evidence.depth_points} sparse points lie within {within} of the reference's depth"


def failure(evidence: Evidence) -> Optional[list[str]]:
    """The reasons the evidence makes a result `failed` (too few photos agree, or a flat objective), or None."""
    agreeing, sharp = agreement_and_sharpness(evidence)
    if evidence.agreeing_fraction < FAILED_AGREEING:
        return [f"only {agreeing}", sharp]
    if evidence.sharpness < FAILED_SHARPNESS:
        return [f"flat objective: {sharp}", agreeing]
    return None


def decide(evidence: Evidence) -> Verdict:
    """The label and the reasons for it (see the module docstring for the rule)."""
    failed = failure(evidence)
    if failed:
        return Verdict("failed", failed, evidence)
    agreeing, sharp = agreement_and_sharpness(evidence)
    reasons = []
    if evidence.agreeing_fraction < REGISTERED_AGREEING:
        reasons.append(f"only {agreeing}")
    if evidence.sharpness < REGISTERED_SHARPNESS and not (evidence.anchors_hold or evidence.depths_hold):
        shallow = f"shallow minimum: {sharp}"
        if evidence.depth_agreeing is not None:
            shallow += f" ({depths_phrase(evidence)}: too few to hold it)"
        reasons.append(shallow)
    if evidence.flattest_rise < DESCENT_TOLERANCE:
        reasons.append(f"not converged: a probe is {100 * -evidence.flattest_rise:.1f}% lower")
    if evidence.orbit_rise is not None and evidence.orbit_rise < DESCENT_TOLERANCE:
        reasons.append(
            f"not converged about the photographed scene: turning the result {ORBIT_DEG:g}° about where the photos look "
            f"lowers the objective {100 * -evidence.orbit_rise:.1f}%"
        )
    contradicting = [
        rise for rise, cover in zip(evidence.per_photo_rise, evidence.per_photo_coverage) if rise < -PHOTO_RISE and cover >= PHOTO_COVERAGE
    ]
    if contradicting:
        reasons.append(f"{len(contradicting)} photo(s) contradict the result: their own loss falls {100 * -min(contradicting):.1f}% one cell away")
    if evidence.camera_fit_refused:
        reasons.append(f"the camera fit was refused ({evidence.camera_fit_refused}): the meta-image's own cameras disagree with the anchors")
    if evidence.keypoint_error_cells is not None and evidence.keypoint_error_cells > ANCHORS_HOLD_CELLS:
        reasons.append(f"the keypoint anchors reproject {evidence.keypoint_error_cells:.3f} cells off (median; more than {ANCHORS_HOLD_CELLS})")
    if evidence.other_minimum_rise is not None and evidence.other_minimum_rise < OTHER_MINIMUM_MARGIN:
        rise = evidence.other_minimum_rise
        depth = f"only {100 * rise:.1f}% higher" if rise >= 0 else f"{100 * -rise:.1f}% lower"
        reasons.append(f"another minimum {evidence.other_minimum_cells:.0f} cells away is {depth} (a repetition the descriptor cannot tell apart)")
    if evidence.scale_rise is not None and evidence.scale_rise < FAILED_SHARPNESS:
        change = f"{100 * evidence.scale_rise:+.1f}% at {100 * evidence.scale_probe:.0f}% more or less scale"
        reasons.append(f"scale not fixed: the anchors leave it free, the other photos' objective changes {change}")
    if reasons:
        return Verdict("uncertain", reasons, evidence)
    if evidence.sharpness < REGISTERED_SHARPNESS:
        if evidence.anchors_hold:
            held = f"anchors of {evidence.keypoint_photos} photos hold within {evidence.keypoint_error_cells:.2f} cells"
        else:
            held = depths_phrase(evidence)
        return Verdict("registered", [agreeing, f"shallow minimum ({sharp}) but {held}"], evidence)
    return Verdict("registered", [agreeing, sharp], evidence)
