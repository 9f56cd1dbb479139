"""Keypoint anchors: the initialiser's verified SIFT correspondences as a reprojection term of the registration.

The dense objective compares renders of the frozen model with the photos on a coarse teacher grid (32 cells on
the long side for the CPU presets). On real photographs its minimum is not exactly at the ground truth: the
reference renders blur and distort what six training photos did not see, and the descriptor pools 8-pixel
cells of a 256-pixel image. A SIFT start is the opposite: its keypoints are located to a pixel of the full
photo against points triangulated from the reference's *photos*, but it fits each photo on its own and needs
texture. Measured on the real-photo scenes (README "Real-photo benchmark scenes"), refinement alone ended 0.1-0.2°
worse than a colmap start within 1° and stopped at 0.8-1.3° from 5° starts; README "Keypoint anchors, measured"
has what the anchors changed.

With `keypoint_weight > 0` the objective of every stage becomes

    dense(T) + keypoint_weight * dense(T_stage_start) * mean_photos mean_points rho(r / c)

where r is the reprojection error of a photo's keypoint under the current Sim(3) T (meta -> dataparser), in
teacher cells of that photo at the stage's grid, rho(u) = log(1 + u^2) (Cauchy: quadratic near the answer,
a slowly growing penalty for the correspondences RANSAC let through by mistake) and c = `KERNEL_CELLS`. The
factor dense(T_stage_start) (detached) makes the weight independent of the descriptor's units. The
correspondences do not depend on the start: the same anchors pull a 5° or a 30° start towards them (with the
render-free pre-alignment, `Anchoring.prealign`, for far starts). Photos
without correspondences (night, heavy occlusion, too few matches) simply contribute no keypoint term; a
meta-image without any is registered by the dense objective alone (the paper's method).

With `refine_focal` the render-free pre-alignment is followed by a joint fit of the Sim(3) and one focal-length scale
per COLMAP camera (`Anchoring.fit_focal_lengths`): the term then projects with each photo's focal length times its
scale, and every stage after it renders with those focal lengths (`Photo.focal_scale`).

Frames: keypoints are pixels of the original (distorted) photo, COLMAP convention, undistorted here once with
the photo's pycolmap camera to normalised image coordinates; points are in the *reference world* frame (the
reference's COLMAP model) and go to the dataparser frame with the reference's `world_to_dataparser`.
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import torch
from torch import Tensor

from sg_nerfstudio.geometry.meta_image import MetaImage, relative_focal_uncertainty
from sg_nerfstudio.geometry.sim3 import Sim3
from sg_nerfstudio.initialisers.estimate import PhotoKeypoints

KERNEL_CELLS = 0.5
"""Scale c of the Cauchy kernel in teacher cells (16 px of a 1024-px photo at a 32-cell grid): about the
initialiser's RANSAC threshold (12 px of a 640-px photo), so that its inliers sit in the quadratic part."""
MAX_FOCAL_CHANGE = 0.2
"""A fitted focal scale outside [1 / (1 + this), 1 + this] is not believed: the focal fit is dropped (every photo keeps
its SfM focal length and the pose stays the pre-aligned one)."""
MIN_DEPTH = 1e-6
"""Points at or behind a camera (under the current transform) carry no keypoint term for that step."""


class KeypointTerm:
    """The reprojection term of one stage (see the module docstring): call it with a torch Sim3 (meta ->
    dataparser) to get a scalar with gradients.

    Tensors: `rays` [M, 2] normalised image coordinates (x/z, y/z) of the keypoints, `points` [M, 3] the
    matched points in the dataparser frame, `photo` [M] the index of the photo each belongs to, `cells` [M, 2]
    teacher cells per unit of normalised coordinate (fx, fy of the photo over its cell size in pixels),
    `point_rotations` [M, 3, 3] / `point_translations` [M, 3] the cam_from_meta of each keypoint's photo. A
    transform moves the points back into the meta frame (its inverse) rather than the cameras forward: one
    batched operation for all photos."""

    def __init__(self, meta: MetaImage, keypoints: list[PhotoKeypoints], world_to_dataparser: Sim3, grid_size: int, weight: float):
        by_name = {k.name: k for k in keypoints if len(k.points2D)}
        rays, points, photo, cells = [], [], [], []
        cam_from_meta, focal_scales, camera_ids = [], [], []
        for photo_meta in meta.photos:
            found = by_name.get(photo_meta.name)
            if found is None:
                continue
            index = len(cam_from_meta)
            cam_from_meta.append(torch.from_numpy(photo_meta.cam_from_world))
            focal_scales.append(photo_meta.focal_scale)
            camera_ids.append(int(photo_meta.camera.camera_id))
            rays.append(np.asarray(photo_meta.camera.cam_from_img(np.asarray(found.points2D, dtype=np.float64))))
            points.append(np.asarray(world_to_dataparser.apply(np.asarray(found.points3D, dtype=np.float64))))
            photo.append(np.full(len(found.points2D), index))
            K = photo_meta.pinhole_intrinsics()
            cell_px = max(photo_meta.camera.width, photo_meta.camera.height) / grid_size
            cells.append(np.tile([K[0, 0] / cell_px, K[1, 1] / cell_px], (len(found.points2D), 1)))
        self.photos = len(cam_from_meta)
        self.weight = float(weight)
        if not self.photos:
            return
        self.rays = torch.from_numpy(np.concatenate(rays))
        self.points = torch.from_numpy(np.concatenate(points))
        self.photo = torch.from_numpy(np.concatenate(photo))
        self.cells = torch.from_numpy(np.concatenate(cells))
        cameras = torch.stack(cam_from_meta)[self.photo]  # [M, 3, 4] cam_from_meta of each keypoint's photo
        self.point_rotations, self.point_translations = cameras[:, :, :3], cameras[:, :, 3]
        self.counts = torch.bincount(self.photo, minlength=self.photos).double()
        self.focal_scales = torch.tensor(focal_scales, dtype=torch.float64)  # [P'] the photos' Photo.focal_scale
        self.camera_ids = sorted(set(camera_ids))  # the G COLMAP cameras of these photos (photos may share one)
        self.camera_of = torch.tensor([self.camera_ids.index(c) for c in camera_ids])  # [P'] index into camera_ids

    def __bool__(self) -> bool:
        return self.photos > 0 and self.weight > 0

    def residuals(self, meta_to_dataparser: Sim3, log_focal: Optional[Tensor] = None) -> tuple[Tensor, Tensor]:
        """[M] reprojection errors in teacher cells and [M] bool in front of the camera, under a torch Sim3 and, with
        `log_focal` [G], each COLMAP camera's focal lengths times exp(log_focal) on top of the photos' `focal_scale`."""
        linear, translation, scale = meta_to_dataparser.linear, meta_to_dataparser.translation, meta_to_dataparser.scale
        in_meta = (self.points - translation) @ linear / scale**2  # the inverse similarity: L^-1 = L^T / s^2
        in_camera = torch.einsum("mij,mj->mi", self.point_rotations, in_meta) + self.point_translations
        depth = in_camera[:, 2]
        in_front = depth > MIN_DEPTH
        projected = in_camera[:, :2] / torch.where(in_front, depth, torch.ones_like(depth))[:, None]
        scales = self.focal_scales if log_focal is None else self.focal_scales * torch.exp(log_focal)[self.camera_of]
        error = (projected * scales[self.photo, None] - self.rays) * self.cells  # pixels of the undistorted photo / cell size
        return torch.sqrt((error**2).sum(-1) + 1e-18), in_front

    def __call__(self, meta_to_dataparser: Sim3, log_focal: Optional[Tensor] = None, focal_sigma: Optional[Tensor] = None) -> Tensor:
        """weight x mean over photos of the mean Cauchy cost of their keypoints (scalar, float64). With `log_focal`
        ([G], `residuals`) and its prior `focal_sigma` ([G], relative standard deviations of the SfM focal lengths) each
        photo's mean also counts one pseudo-observation (log_focal of its camera / its sigma)^2."""
        errors, in_front = self.residuals(meta_to_dataparser, log_focal)
        cost = torch.where(in_front, torch.log1p((errors / KERNEL_CELLS) ** 2), torch.zeros_like(errors))
        total = torch.zeros(self.photos, dtype=cost.dtype).index_add(0, self.photo, cost)
        if log_focal is None:
            return self.weight * (total / self.counts).mean()
        prior = ((log_focal / focal_sigma) ** 2)[self.camera_of]
        return self.weight * ((total + prior) / (self.counts + 1)).mean()

    def median_error_cells(self, meta_to_dataparser: Sim3) -> float:
        """Median reprojection error (teacher cells) of the keypoints in front of their cameras."""
        with torch.no_grad():
            errors, in_front = self.residuals(meta_to_dataparser.to_torch())
        return float(errors[in_front].median()) if bool(in_front.any()) else float("nan")


class Anchoring:
    """The keypoints of one registration and how each stage weighs them: `term` builds a stage's
    `KeypointTerm` on that stage's teacher grid, weighted by `keypoint_weight` x the stage's dense objective at
    its start (`start_value`). Empty (falsy) when the settings' weight is 0 or no photo has keypoints."""

    def __init__(self, meta: MetaImage, keypoints: list[PhotoKeypoints], world_to_dataparser: Sim3, weight: float):
        self.meta, self.keypoints, self.world_to_dataparser, self.weight = meta, keypoints, world_to_dataparser, float(weight)

    def __bool__(self) -> bool:
        return self.weight > 0 and any(len(k.points2D) for k in self.keypoints)

    def term(self, grid_size: int, start_value: float) -> Optional[KeypointTerm]:
        if not self:
            return None
        return KeypointTerm(self.meta, self.keypoints, self.world_to_dataparser, grid_size, self.weight * float(start_value))

    def prealign(self, start: Sim3, centre: np.ndarray, grid_size: int, steps: int) -> Sim3:
        """The keypoint term alone minimised from `start` (numpy Sim3, meta -> dataparser): Adam on delta about
        `centre` [3] for `steps` steps, learning rate 0.02 decaying to 0.0005. No render is involved (a few
        milliseconds a step), so a start far from the answer reaches the keypoints' own optimum before the dense
        objective, whose basin is a few cells wide, takes over. Returns `start` without keypoints."""
        term = self.term(grid_size, 1.0)
        if not term or steps <= 0:
            return start
        return minimise_keypoint_term(term, start, centre, steps)[0]

    def fit_focal_lengths(self, start: Sim3, centre: np.ndarray, grid_size: int, steps: int) -> tuple[Sim3, dict[str, float]]:
        """The keypoint term minimised over the Sim(3) *and* one focal-length scale per COLMAP camera of the photos with
        keypoints (one per photo where, as for Internet photos, each has its own), from `start` (best already
        pre-aligned): (the Sim(3), {photo name: focal_scale} for every photo of a refined camera, keypoints or not);
        `start` and no scales when a fitted scale is beyond MAX_FOCAL_CHANGE (keypoints that cannot tell focal length
        from depth). A 3-photo SfM model's focal lengths can be a few percent off (README "Per-photo focal
        lengths"); the Sim(3) cannot absorb that, and an image-based alignment then places each camera nearer or
        farther by the same fraction. Each focal length's prior is the SfM's own uncertainty
        (`relative_focal_uncertainty`), one pseudo-observation in its photos' keypoint means: a focal length the
        meta-image's SfM fixed well (many photos) barely moves, a poorly fixed one follows the keypoints. Cameras
        whose uncertainty cannot be estimated keep their focal length."""
        term = self.term(grid_size, 1.0)
        if not term or steps <= 0:
            return start, {}
        uncertainty = relative_focal_uncertainty(self.meta.reconstruction)
        sigma = torch.tensor([uncertainty.get(camera_id, np.nan) for camera_id in term.camera_ids], dtype=torch.float64)
        free = torch.isfinite(sigma)
        if not bool(free.any()):
            return start, {}
        moved, log_focal = minimise_keypoint_term(term, start, centre, steps, focal_sigma=torch.where(free, sigma, torch.ones_like(sigma)), focal_free=free)
        if bool((log_focal.abs() > np.log1p(MAX_FOCAL_CHANGE)).any()):
            return start, {}  # the Sim(3) was fitted with that implausible focal length: neither is kept
        change = {camera_id: float(torch.exp(value)) for camera_id, value, own in zip(term.camera_ids, log_focal, free) if own}
        # every photo of a refined camera, with keypoints or not, renders with it (as the aligned model's camera)
        return moved, {p.name: p.focal_scale * change[int(p.camera.camera_id)] for p in self.meta.photos if int(p.camera.camera_id) in change}

    def for_meta(self, meta: MetaImage) -> "Anchoring":
        """The same keypoints for `meta` (e.g. its photos with new focal scales)."""
        return Anchoring(meta, self.keypoints, self.world_to_dataparser, self.weight)

    def cost(self, term: Optional[KeypointTerm], meta_to_dataparser: Sim3) -> float:
        """The term's value under a numpy Sim3 (0 without a term)."""
        if not term:
            return 0.0
        with torch.no_grad():
            return float(term(meta_to_dataparser.to_torch()))


def minimise_keypoint_term(
    term: KeypointTerm, start: Sim3, centre: np.ndarray, steps: int, focal_sigma: Optional[Tensor] = None, focal_free: Optional[Tensor] = None,
) -> tuple[Sim3, Tensor]:
    """Adam on delta [7] about `centre` (and, with `focal_sigma` [G], the log focal scales of the term's cameras that
    `focal_free` [G] marks, under that prior) for `steps` steps, learning rate 0.02 decaying to 0.0005: (the numpy Sim3
    meta -> dataparser, the [G] log focal changes, 0 where not free). `start` and zeros when the optimisation diverged."""
    with_focal = focal_sigma is not None
    base = start.to_torch()
    centre_t = torch.from_numpy(np.asarray(centre, dtype=np.float64))
    delta = torch.zeros(7, dtype=torch.float64, requires_grad=True)
    log_focal = torch.zeros(len(term.camera_ids), dtype=torch.float64, requires_grad=with_focal)
    mask = focal_free.double() if focal_free is not None else torch.ones_like(log_focal)
    optimizer = torch.optim.Adam([delta, log_focal] if with_focal else [delta], lr=0.02)
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=(0.0005 / 0.02) ** (1.0 / steps))
    for _ in range(steps):
        optimizer.zero_grad()
        transform = Sim3.update(delta, centre_t) @ base
        (term(transform, log_focal * mask, focal_sigma) if with_focal else term(transform)).backward()
        optimizer.step()
        scheduler.step()
    if not (torch.isfinite(delta).all() and torch.isfinite(log_focal).all()):
        return start, torch.zeros(len(term.camera_ids), dtype=torch.float64)
    with torch.no_grad():
        return (Sim3.update(delta, centre_t) @ base).numpy(), (log_focal * mask).detach()
