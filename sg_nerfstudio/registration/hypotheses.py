"""Several starts for the first stage (`best_hypothesis`): rotations of the given start about axes spread over the
sphere and scales on a grid (`hypotheses.count` > 0, wide-cpu), scored by the first stage's robust objective, of which
the best few are optimised, and starts proposed by other means (the dense initialiser's: `hypotheses.dense_start`),
which are always optimised. The end the main stage's objective scores lowest wins. Transforms are numpy Sim3s
meta -> dataparser.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable, Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from sg_nerfstudio.geometry.meta_image import MetaImage
from sg_nerfstudio.geometry.sim3 import Sim3, rotation_angle_deg
from sg_nerfstudio.registration.objectives import PhotoLosses
from sg_nerfstudio.registration.schedules import History
from sg_nerfstudio.registration.settings import RegistrationSettings
from sg_nerfstudio.registration.stages import Stage, objective_with_anchors, optimise_stage, uses_anchors

if TYPE_CHECKING:  # the anchored start builds on the stages; they only take its anchors
    from sg_nerfstudio.registration.anchored_start import Anchoring


def best_hypothesis(
    stage: Stage, judge: PhotoLosses, meta: MetaImage, start_ns: Sim3, settings: RegistrationSettings, history: History, first_step: int,
    on_step: Optional[Callable[[int, Sim3], None]], anchor: Optional[Anchoring] = None, other_starts: Sequence[tuple[str, Sim3]] = (),
) -> tuple[Sim3, list[dict], int]:
    """Several starts for the first stage: `start_ns` and `settings.hypotheses.count` rotations of it by
    `hypotheses.rotation_deg` about axes spread over the sphere (about the cameras' centroid), each also scaled by every
    `hypotheses.scales` factor, of which the `hypotheses.kept` with the lowest robust objective are optimised over the
    stage; and every (label, start) of `other_starts`, always optimised. The end that scores lowest under `judge` (the
    main stage's objective, which tells apart ends the coarse one cannot) wins and its steps go to `history`.

    Scores are the robust objective plus, with an `anchor`, the keypoint term weighted as in `stages.optimise_stage`.

    Returns (winner, one record per optimised start, the next step number)."""
    rotated = [(None, start_ns)] + hypotheses_around(start_ns, meta, settings.hypotheses.count, settings.hypotheses.rotation_deg)
    candidates = [((axis, factor), scaled_about_centroid(transform, meta, factor)) for factor in (1.0, *settings.hypotheses.scales) for axis, transform in rotated]
    coarse_score, judge_score = (objective_with_anchors(losses, start_ns, settings, anchor) for losses in (stage.losses, judge))
    scores = [coarse_score(transform) for _, transform in candidates]
    kept = [
        ("given" if candidates[i][0] == (None, 1.0) else "around", candidates[i][0], candidates[i][1], scores[i])
        for i in np.argsort(scores, kind="stable")[: max(1, settings.hypotheses.kept)]
    ]
    kept += [(label, (None, 1.0), transform, coarse_score(transform)) for label, transform in other_starts]
    runs = []
    for label, origin, transform, start_score in kept:
        own = History(history.names)
        final, _ = optimise_stage(stage, meta, transform, settings, own, first_step, on_step, anchor=anchor)
        runs.append((final, judge_score(final), own, label, origin, start_score))
    winner, _, winner_history, _, _, _ = min(runs, key=lambda run: run[1])
    history.extend(winner_history)
    records = [
        {"start": label, "axis": axis, "scale": factor, "start_objective_coarse": start_score, "final_objective": final_score,
         "won": final is winner, **end_against_winner(final, winner)}
        for final, final_score, _, label, (axis, factor), start_score in runs
    ]
    return winner, records, first_step + stage.steps


def end_against_winner(end: Sim3, winner: Sim3) -> dict:
    """{rotation_from_winner_deg, agrees_with_winner} of one optimised start's end (numpy Sim3s, meta -> dataparser)."""
    angle = rotation_between_deg(end, winner)
    return {"rotation_from_winner_deg": angle, "agrees_with_winner": bool(angle < HYPOTHESIS_AGREEMENT_DEG)}


def runs_dense_start(settings: RegistrationSettings, anchored: bool) -> bool:
    """Whether the dense initialiser's start runs beside the given one: the settings ask for it
    (`hypotheses.dense_start`) and no keypoint anchors hold the meta-image (they fix the pose whatever the start)."""
    return settings.hypotheses.dense_start and not uses_anchors(settings, anchored)


HYPOTHESIS_AGREEMENT_DEG = 2.0
"""Optimised hypotheses that end within this rotation of the winner agree with it."""


def hypotheses_around(start_ns: Sim3, meta: MetaImage, count: int, angle_deg: float) -> list[tuple[list[float], Sim3]]:
    """`count` (axis, Sim3): `start_ns` rotated by `angle_deg` about the cameras' centroid, axes on a Fibonacci sphere."""
    golden = np.pi * (3.0 - np.sqrt(5.0))
    hypotheses = []
    for k in range(count):
        z = 1.0 - 2.0 * (k + 0.5) / count
        axis = np.array([np.sqrt(1 - z * z) * np.cos(golden * k), np.sqrt(1 - z * z) * np.sin(golden * k), z])
        delta = torch.zeros(7, dtype=torch.float64)
        delta[:3] = torch.from_numpy(axis * np.radians(angle_deg))
        hypotheses.append((axis.round(4).tolist(), moved_about_centroid(start_ns, meta, delta)))
    return hypotheses


def scaled_about_centroid(transform: Sim3, meta: MetaImage, factor: float) -> Sim3:
    """`transform` (meta -> dataparser) followed by a scaling by `factor` about the moved cameras' centroid."""
    if factor == 1.0:
        return transform
    delta = torch.zeros(7, dtype=torch.float64)
    delta[6] = float(np.log(factor))
    return moved_about_centroid(transform, meta, delta)


def moved_about_centroid(transform: Sim3, meta: MetaImage, delta: Tensor) -> Sim3:
    """U(delta) about the centroid of the cameras moved by `transform`, then `transform` (numpy Sim3s,
    meta -> dataparser; delta [7] = (omega, nu, log s))."""
    return (Sim3.update(delta, torch.from_numpy(meta.centroid_under(transform))) @ transform.to_torch()).numpy()


def rotation_between_deg(a: Sim3, b: Sim3) -> float:
    """Angle of the rotation between two similarities (degrees)."""
    return rotation_angle_deg(np.asarray(a.rotation) @ np.asarray(b.rotation).T)
