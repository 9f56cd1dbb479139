"""The anchored start, in order: keypoint anchors -> render-free pre-alignment -> camera fit -> the scale the anchors
leave free. `start_from_anchors` is the one entry; the registration's rendered stages begin where it ends.

Frames: transforms meta -> dataparser (numpy `Sim3`); the anchors' points are in the reference world and go to the
dataparser frame with `world_to_dataparser`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import numpy as np

from sg_nerfstudio.geometry.alignment import align_cameras, camera_residuals
from sg_nerfstudio.geometry.meta_image import MetaImage
from sg_nerfstudio.geometry.sim3 import Sim3
from sg_nerfstudio.initialisers.estimate import PhotoKeypoints
from sg_nerfstudio.registration.anchored_start.anchors import Anchoring
from sg_nerfstudio.registration.anchored_start.camera_fit import CameraFit, fit_cameras
from sg_nerfstudio.registration.anchored_start.scale_search import scale_the_anchors_leave_free
from sg_nerfstudio.registration.objectives import PhotoLosses, PreparedPhoto, with_camera_changes
from sg_nerfstudio.registration.settings import RegistrationSettings
from sg_nerfstudio.registration.stages import update_centre, uses_anchors


@dataclass
class AnchoredStart:
    """Where the rendered stages begin (`start_from_anchors`)."""

    transform: Sim3  # meta -> dataparser: after the pre-alignment, camera fit and scale search, or the start as given
    fit: CameraFit  # the photos' fitted focal scales, poses and radial k1 (none without a camera fit)
    meta: MetaImage  # the meta-image with those cameras
    given: MetaImage  # the meta-image as given
    losses: PhotoLosses  # the main stage's per-photo losses, built for `meta`
    anchor: Anchoring  # the keypoint anchors (empty without keypoints), weighed for the moved photos
    camera_shift: Sim3  # meta -> meta: maps the given cameras onto the moved ones (identity when no photo moved)
    prealigned: bool  # whether the keypoint pre-alignment ran
    scale_search: Optional[dict] = None  # the search's record where the anchors left the scale free (else None)

    def pose_corrections(self, world_per_meta: float) -> dict[str, dict[str, float]]:
        """Per moved photo, how far its moved camera sits from its given one carried by `camera_shift`: rotation
        (degrees) and centre distance in reference world units (`world_per_meta`: meta units to world)."""
        names = set(self.fit.poses)
        if not names:
            return {}
        rotation, centre = camera_residuals(self.camera_shift, np.stack(self.given.poses), np.stack(self.meta.poses))
        return {
            photo.name: {"rotation_deg": round(float(r), 4), "centre_shift": round(float(c) * world_per_meta, 6)}
            for photo, r, c in zip(self.given.photos, rotation, centre) if photo.name in names
        }


MainLosses = Callable[[MetaImage, Optional[list[PreparedPhoto]]], PhotoLosses]
"""Builds the main stage's losses for a meta-image, from its prepared photos where they are still valid (None: prepare
them again, e.g. after a new radial distortion)."""


def start_from_anchors(
    meta: MetaImage, photos: Optional[list[PreparedPhoto]], initial_ns: Sim3, settings: RegistrationSettings, world_to_ns: Sim3,
    keypoints: Optional[list[PhotoKeypoints]], grid_size: int, main_losses: MainLosses,
) -> AnchoredStart:
    """With keypoint anchors that the settings weigh (`settings.anchors`): the render-free pre-alignment from
    `initial_ns` (meta -> dataparser), the camera fit (`settings.camera_fit`), and, where the anchors leave the scale
    free, the scale the main stage's objective prefers. Without them: the start as given."""
    anchor = Anchoring(meta, keypoints or [], world_to_ns, settings.anchors.weight)
    if not prealigns(settings, bool(anchor)):
        return AnchoredStart(initial_ns, CameraFit(initial_ns), meta, meta, main_losses(meta, photos), anchor, Sim3.identity(), False)
    fit = prealign_and_fit_cameras(anchor, meta, initial_ns, settings, grid_size)
    moved, photos = with_fitted_cameras(meta, photos, fit)
    anchor = anchor.for_meta(moved, narrow=True if fit.poses else None)  # the moved photos fit their keypoints under the narrow kernel
    camera_shift = align_cameras(np.stack(meta.poses), np.stack(moved.poses)).transform if fit.poses else Sim3.identity()
    losses = main_losses(moved, photos)
    transform, scale_search = scale_the_anchors_leave_free(losses, anchor, moved, fit.transform, settings)
    return AnchoredStart(transform, fit, moved, meta, losses, anchor, camera_shift, True, scale_search)


def prealigns(settings: RegistrationSettings, anchored: bool) -> bool:
    """Whether the keypoint pre-alignment runs: keypoint anchors hold the pose and the settings ask for it."""
    return uses_anchors(settings, anchored) and settings.anchors.prealign_steps > 0


def prealign_and_fit_cameras(anchor: Anchoring, meta: MetaImage, start_ns: Sim3, settings: RegistrationSettings, grid_size: int) -> CameraFit:
    """The keypoint term alone from `start_ns` (meta -> dataparser), then, where `settings.camera_fit` frees any camera
    parameter, jointly with the photos' focal lengths, poses and / or k1 (`camera_fit.fit_cameras`)."""
    fitting = settings.camera_fit
    current = anchor.prealign(start_ns, update_centre(meta, start_ns, settings), grid_size, settings.anchors.prealign_steps)
    if not (fitting.focal or fitting.photo_poses or fitting.distortion):
        return CameraFit(current)
    pose_prior = fitting.pose_prior_scale if fitting.photo_poses else None
    return fit_cameras(
        anchor, current, update_centre(meta, current, settings), grid_size, fitting.iterations, fitting.focal, pose_prior,
        fitting.distortion, fitting.solver == "adjustment",
    )


def with_fitted_cameras(meta: MetaImage, photos: Optional[list[PreparedPhoto]], fit: CameraFit) -> tuple[MetaImage, Optional[list[PreparedPhoto]]]:
    """`meta` and its prepared `photos` (if any) with the focal lengths, poses and radial distortion of `fit`; with a new
    distortion the photos are not returned (None): they must be undistorted again (`prepare_photos`)."""
    factors = {photo.name: fit.focal_scales[photo.name] / photo.focal_scale for photo in meta.photos if photo.name in fit.focal_scales}
    meta = meta.with_focal_scales(fit.focal_scales).with_poses(fit.poses).with_radial_distortion(fit.radial_k1)
    if photos is None or fit.radial_k1:
        return meta, None
    return meta, with_camera_changes(photos, factors, fit.poses)
