"""The Sim(3)'s scale where the keypoint anchors leave it free (one photo's anchors, or those of photos taken from nearly
one spot): a 1-D search about the anchored photos' mean camera centre on the other photos' dense objective
(`scale_the_anchors_leave_free`). Transforms are numpy Sim3s meta -> dataparser.
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from sg_nerfstudio.geometry.meta_image import MetaImage
from sg_nerfstudio.geometry.sim3 import Sim3
from sg_nerfstudio.registration.anchored_start.anchors import SCALE_RESOLUTION, Anchoring, anchors_fix_scale
from sg_nerfstudio.registration.objectives import PhotoLosses
from sg_nerfstudio.registration.robust import TrimmingRule
from sg_nerfstudio.registration.settings import RegistrationSettings
from sg_nerfstudio.registration.stages import objective_at

Array = np.ndarray


SCALE_SEARCH = (2.0, 17, 4 * SCALE_RESOLUTION, 9)
"""The 1-D scale search of `scale_the_anchors_leave_free`: factors from 1/2 to 2 (17, log-spaced: 9% apart), then 9
around the best, 0.08 of a log unit on either side (SCALE_RESOLUTION, 2%, apart)."""


def scale_the_anchors_leave_free(
    losses: PhotoLosses, anchor: Anchoring, meta: MetaImage, transform: Sim3, settings: RegistrationSettings,
) -> tuple[Sim3, Optional[dict]]:
    """When the keypoint anchors do not fix the Sim(3)'s scale (`anchors_fix_scale`: one photo's anchors, or those of
    photos taken from nearly one spot) and some photos have none, the Sim(3) (meta -> dataparser) scaled about the
    anchored photos' mean camera centre by the factor the main stage's objective prefers; otherwise `transform`.

    Scaling the world about a camera's centre leaves that camera's image unchanged, so such anchors fix 6 of the 7
    degrees of freedom; the other photos see the scale (their cameras move along the rays from the anchored ones). The
    search scores factors (SCALE_SEARCH) by the robust objective of those other photos only (the anchored ones' renders
    do not change and would fill the trimmed mean's kept half) plus the keypoint term weighed as a stage weighs it.
    Returns the best, with a record of the search."""
    term = anchor.term(losses.objective.teacher.grid_size, 1.0) if anchor else None
    if not term or term.photos >= len(meta.photos):
        return transform, None
    motion, error = term.scale_motion_px(transform)
    if anchors_fix_scale(motion, error):
        return transform, None
    centre = transform.apply(term.centres.mean(0).numpy())
    unanchored = [index for index, photo in enumerate(losses.photos) if photo.name not in set(term.names)]
    rule = TrimmingRule.of(settings)
    dense = lambda candidate: rule.trimmed_mean(objective_at(losses, candidate, unanchored))
    weight = dense(transform)  # the term's weight, as a stage starting here would set it (its cost is linear in it)
    score = lambda candidate: dense(candidate) + weight * anchor.cost(term, candidate)

    def scaled(log_factor: float) -> Sim3:
        return Sim3.scaling_about(np.exp(log_factor), centre) @ transform

    def best(log_factors: Array) -> tuple[float, float]:
        scores = [score(scaled(value)) for value in log_factors]
        index = min(range(len(scores)), key=lambda i: (scores[i], abs(log_factors[i])))  # ties: the smallest change
        return float(log_factors[index]), float(scores[index])

    widest, coarse, step, fine = SCALE_SEARCH
    chosen, _ = best(np.linspace(-np.log(widest), np.log(widest), coarse))
    chosen, value = best(chosen + np.linspace(-step, step, fine))
    record = {"photos": term.names, "anchor_motion_px": round(motion, 3), "anchor_error_px": round(error, 3)}
    return scaled(chosen), record | {"factor": round(float(np.exp(chosen)), 4), "objective": value}
