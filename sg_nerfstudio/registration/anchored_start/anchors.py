"""Keypoint anchors: the SIFT initialisers' verified 2D-3D matches with the reference as a reprojection term.

The dense objective's minimum sits where a coarse descriptor of blurry renders matches the photos; a SIFT keypoint is
located to a pixel of the full photo against points triangulated from the reference's own images. With
`anchors.weight > 0` every stage minimises

    dense(T) + weight * dense(T_stage_start) * mean_photos mean_keypoints rho(|r| / c)

with r a keypoint's reprojection error under the Sim(3) T (meta -> dataparser) in teacher cells, rho(u) = log(1 + u^2)
(Cauchy: quadratic near the answer, a slowly growing cost for RANSAC's mistakes) and c = `KERNEL_CELLS`; the detached
dense(T_stage_start) makes the weight independent of the descriptor's units. The same anchors pull any start toward
them, so `Anchoring.prealign` first minimises the term alone, render-free. Photos without matches add nothing; a
meta-image without any is registered by the dense objective alone (the paper's method).

Frames: keypoints are pixels of the original (distorted) photo (COLMAP convention), undistorted once with the photo's
pycolmap camera; points are in the reference world and go to the dataparser frame with `world_to_dataparser`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch
from torch import Tensor

from sg_nerfstudio.geometry.meta_image import MetaImage
from sg_nerfstudio.geometry.sim3 import Sim3
from sg_nerfstudio.initialisers.estimate import PhotoKeypoints
from sg_nerfstudio.registration.anchored_start.least_squares import RobustResiduals

KERNEL_CELLS = 0.5
"""Scale c of the Cauchy kernel in teacher cells: about the initialiser's RANSAC threshold, so that its inliers sit in
the quadratic part."""
FIT_KERNEL_FRACTION = 1 / 160
"""Cauchy kernel while the cameras are fitted, as a fraction of the photo's long side (4 px of 640): near SIFT's
localisation error, so a free photo follows its well-located keypoints, not RANSAC's few-pixel mistakes. The stages
after a pose fit keep it (`Anchoring.narrow`)."""
MIN_DEPTH = 1e-6
"""Points at or behind a camera (under the current transform) carry no keypoint term for that step."""
SCALE_RESOLUTION = 0.02
"""The change of scale (log factor, 2%) the anchors must see to fix the scale (`anchors_fix_scale`), and the fine step
of the scale search."""
KEYPOINT_PRECISION_PX = 0.1
"""The least error `anchors_fix_scale` compares with: about the best SIFT localises a keypoint (a motion of nothing must
not beat an error of nothing)."""
PREALIGN_LR = (0.02, 0.0005)
"""Adam's learning rate of the pre-alignment, decaying exponentially from the first to the second: large enough to cross
tens of degrees in 1000 render-free steps, small enough at the end not to overshoot the keypoints' basin."""


def anchors_fix_scale(motion_px: float, error_px: float) -> bool:
    """Whether anchors whose keypoints move `motion_px` under a SCALE_RESOLUTION change of scale and miss by `error_px`
    (`KeypointTerm.scale_motion_px`) fix the Sim(3)'s scale: the motion exceeds the error (and KEYPOINT_PRECISION_PX)."""
    return motion_px > max(error_px, KEYPOINT_PRECISION_PX)


class KeypointTerm:
    """The reprojection term of one stage (see the module docstring): call it with a torch Sim3 (meta ->
    dataparser) to get a scalar with gradients.

    Tensors: `rays` [M, 2] normalised image coordinates (x/z, y/z) of the keypoints, `points` [M, 3] the
    matched points in the dataparser frame, `photo` [M] the index of the photo each belongs to, `cells` [M, 2]
    teacher cells per unit of normalised coordinate (fx, fy of the photo over its cell size in pixels),
    `rotations` [P', 3, 3] / `centres` [P', 3] each photo's world-to-camera rotation and centre in the meta frame
    (moved by `pose_corrections` in `residuals`), `depths` [P'] each photo's median sparse-point depth (meta units, NaN without points). A
    transform moves the points back into the meta frame (its inverse) rather than the cameras forward: one
    batched operation for all photos."""

    def __init__(self, meta: MetaImage, keypoints: list[PhotoKeypoints], world_to_dataparser: Sim3, grid_size: int, weight: float, kernel: float = KERNEL_CELLS):
        by_name = {k.name: k for k in keypoints if len(k.points2D)}
        rays, points, photo, cells, pixels, intrinsics = [], [], [], [], [], []
        cam_from_meta, focal_scales, camera_ids, self.names, depths = [], [], [], [], []
        for photo_meta in meta.photos:
            found = by_name.get(photo_meta.name)
            if found is None:
                continue
            index = len(cam_from_meta)
            self.names.append(photo_meta.name)
            depths.append(photo_meta.median_depth)
            cam_from_meta.append(torch.from_numpy(photo_meta.cam_from_world))
            focal_scales.append(photo_meta.focal_scale)
            camera_ids.append(int(photo_meta.camera.camera_id))
            rays.append(np.asarray(photo_meta.camera.cam_from_img(np.asarray(found.points2D, dtype=np.float64))))
            points.append(np.asarray(world_to_dataparser.apply(np.asarray(found.points3D, dtype=np.float64))))
            photo.append(np.full(len(found.points2D), index))
            K = photo_meta.pinhole_intrinsics()
            cell_px = max(photo_meta.camera.width, photo_meta.camera.height) / grid_size
            cells.append(np.tile([K[0, 0] / cell_px, K[1, 1] / cell_px], (len(found.points2D), 1)))
            pixels.append(np.asarray(found.points2D, dtype=np.float64))
            intrinsics.append(np.tile([*lens_parameters(photo_meta.camera), cell_px], (len(found.points2D), 1)))
        self.photos = len(cam_from_meta)
        self.weight = float(weight)
        self.kernel = float(kernel)  # the Cauchy kernel's scale c, teacher cells
        if not self.photos:
            return
        self.rays = torch.from_numpy(np.concatenate(rays))
        self.pixels = torch.from_numpy(np.concatenate(pixels))  # [M, 2] the keypoints in the distorted photo
        self.intrinsics = torch.from_numpy(np.concatenate(intrinsics))  # [M, 10] `lens_parameters` of its photo's camera, cell px
        self.points = torch.from_numpy(np.concatenate(points))
        self.photo = torch.from_numpy(np.concatenate(photo))
        self.cells = torch.from_numpy(np.concatenate(cells))
        poses = torch.stack(cam_from_meta)  # [P', 3, 4]
        self.rotations = poses[:, :, :3]
        self.centres = -torch.einsum("pji,pj->pi", self.rotations, poses[:, :, 3])
        self.depths = torch.tensor(depths, dtype=torch.float64)
        self.counts = torch.bincount(self.photo, minlength=self.photos).double()
        self.focal_scales = torch.tensor(focal_scales, dtype=torch.float64)  # [P'] the photos' Photo.focal_scale
        self.camera_ids = sorted(set(camera_ids))  # the G COLMAP cameras of these photos (photos may share one)
        self.camera_of = torch.tensor([self.camera_ids.index(c) for c in camera_ids])  # [P'] index into camera_ids

    def __bool__(self) -> bool:
        return self.photos > 0 and self.weight > 0

    def residuals(
        self, meta_to_dataparser: Sim3, log_focal: Optional[Tensor] = None, pose_corrections: Optional[Tensor] = None,
        k1_delta: Optional[Tensor] = None,
    ) -> tuple[Tensor, Tensor]:
        """[M] reprojection errors (lengths, teacher cells) and [M] bool in front of the camera: `error_vectors`' lengths."""
        error, in_front = self.error_vectors(meta_to_dataparser, log_focal, pose_corrections, k1_delta)
        return torch.sqrt((error**2).sum(-1) + 1e-18), in_front

    def error_vectors(
        self, meta_to_dataparser: Sim3, log_focal: Optional[Tensor] = None, pose_corrections: Optional[Tensor] = None,
        k1_delta: Optional[Tensor] = None,
    ) -> tuple[Tensor, Tensor]:
        """[M, 2] reprojection errors in teacher cells and [M] bool in front of the camera, under a torch Sim3 and, with
        `log_focal` [G], each COLMAP camera's focal lengths times exp(log_focal) on top of the photos' `focal_scale`;
        with `pose_corrections` [P', 6] each photo's camera moved (`corrected_rotations_and_centres`); with `k1_delta`
        [G] each camera's first radial coefficient changed by it, the keypoints of cameras of RADIAL_MODELS are compared
        in the distorted photo instead (`distorted_errors`: projected, distorted with k1 + delta, scaled by the focal
        length; exact for any focal scale), the others as without it (their rays undistorted once with the SfM
        intrinsics, then compared in the undistorted plane: exact for a focal scale only without distortion)."""
        linear, translation, scale = meta_to_dataparser.linear, meta_to_dataparser.translation, meta_to_dataparser.scale
        in_meta = (self.points - translation) @ linear / scale**2  # the inverse similarity: L^-1 = L^T / s^2
        rotations, centres = self.rotations, self.centres
        if pose_corrections is not None:
            rotations, centres = corrected_rotations_and_centres(rotations, centres, pose_corrections)
        in_camera = torch.einsum("mij,mj->mi", rotations[self.photo], in_meta - centres[self.photo])
        depth = in_camera[:, 2]
        in_front = depth > MIN_DEPTH
        projected = in_camera[:, :2] / torch.where(in_front, depth, torch.ones_like(depth))[:, None]
        scales = self.focal_scales if log_focal is None else self.focal_scales * torch.exp(log_focal)[self.camera_of]
        error = (projected * scales[self.photo, None] - self.rays) * self.cells  # pixels of the undistorted photo / cell size
        if k1_delta is not None:
            lens = self.intrinsics[:, 8] > 0  # keypoints of cameras with a radial model
            distorted = self.distorted_errors(projected, scales[self.photo], k1_delta[self.camera_of][self.photo])
            error = torch.where(lens[:, None], distorted, error)
        return error, in_front

    def distorted_errors(self, projected: Tensor, focal_scale: Tensor, k1_change: Tensor) -> Tensor:
        """[M, 2] keypoint errors in cells of the distorted photo: `projected` [M, 2] (normalised, undistorted) distorted
        with the camera's radial (k1 + `k1_change` [M], k2) and tangential (p1, p2) terms (COLMAP's RADIAL_MODELS:
        OpenCV's formula), times its focal lengths x `focal_scale` [M], plus the principal point, minus the keypoint."""
        fx, fy, cx, cy, k1, k2, p1, p2, _, cell_px = self.intrinsics.unbind(1)
        x, y = projected.unbind(1)
        r2 = x * x + y * y
        radial = 1.0 + (k1 + k1_change) * r2 + k2 * r2 * r2
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        pixels = torch.stack([fx * focal_scale * xd + cx, fy * focal_scale * yd + cy], 1)
        return (pixels - self.pixels) / cell_px[:, None]

    def __call__(self, meta_to_dataparser: Sim3, free: Optional["FreeCameras"] = None) -> Tensor:
        """weight x mean over photos of the mean Cauchy cost of their keypoints (scalar, float64). With `free` cameras
        (`FreeCameras`: focal scales and / or pose corrections and their priors) each photo's mean also counts one
        pseudo-observation per prior: (log focal scale of its camera / its sigma)^2, sum((its correction / its
        sigma)^2)."""
        return self.robust_residuals(meta_to_dataparser, free).cost()

    def robust_residuals(self, meta_to_dataparser: Sim3, free: Optional["FreeCameras"] = None) -> RobustResiduals:
        """The term as `least_squares.RobustResiduals` (its `cost()` is the term's value): the keypoints' error vectors
        over the kernel [M, 2], each weighted by weight / (photos x (its photo's keypoints + priors)) (0 behind the camera),
        and the priors' residuals with the square root of their photo's weight."""
        free = free or FreeCameras()
        error, in_front = self.error_vectors(meta_to_dataparser, free.log_focal, free.pose_corrections, free.k1_delta)
        priors = free.prior_residuals(self.camera_of)  # [P', k] each
        per_photo = self.weight / (self.photos * (self.counts + len(priors)))  # [P']
        weights = torch.where(in_front, per_photo[self.photo], torch.zeros_like(per_photo[self.photo]))
        quadratic = [(prior * per_photo.sqrt()[:, None]).reshape(-1) for prior in priors]
        return RobustResiduals(error / self.kernel, weights, torch.cat(quadratic) if quadratic else error.new_zeros(0))

    def pose_sigma(self, rotation_deg: dict[str, float], focal_sigma: Optional[dict[int, float]] = None) -> Optional[Tensor]:
        """[P', 6] prior standard deviations of the pose corrections (radians for the rotation, meta units for the centre
        shift along the photo's own camera axes x, y, z) from `rotation_deg` {photo name: degrees}: that angle for the
        rotation, and for the centre the shift that moves the photographed scene as much, the photo's median point depth
        times the angle (photos without points: the median over the others). With `focal_sigma` {COLMAP camera id:
        relative standard deviation of its focal length} (the focal lengths are fitted too), the shift along the optical
        axis also gets the depth change that focal uncertainty allows, depth x sqrt(angle^2 + sigma_f^2): an SfM that
        got a focal length some percent long put that photo as many percent nearer its scene, and moving it back is what
        correcting the focal length asks (`implausibility` allows the same). 0 (the photo is not moved) for photos not named;
        None when no photo is moved."""
        depths = self.depths.clone()
        known = torch.isfinite(depths) & (depths > 0)
        angles = torch.tensor([np.radians(rotation_deg.get(name, 0.0)) for name in self.names], dtype=torch.float64)
        if not bool(known.any()) or not bool((angles > 0).any()):
            return None
        depths[~known] = depths[known].median()
        focal = torch.tensor([(focal_sigma or {}).get(camera_id, 0.0) for camera_id in self.camera_ids], dtype=torch.float64)[self.camera_of]
        along_axis = torch.where(angles > 0, torch.sqrt(angles**2 + focal**2), angles)
        return torch.stack([angles, angles, angles, depths * angles, depths * angles, depths * along_axis], dim=1)

    def scale_motion_px(self, meta_to_dataparser: Sim3, log_factor: float = SCALE_RESOLUTION) -> tuple[float, float]:
        """(motion, error) in pixels of the photos under a numpy Sim3 (meta -> dataparser): the RMS distance the keypoints'
        projections move when the Sim(3) is scaled by exp(`log_factor`) about the anchored photos' mean camera centre,
        and the keypoints' median reprojection error (keypoints in front of their cameras).

        Scaling about a camera's centre leaves its image unchanged, so the anchors see the scale only through how far
        their photos stand apart: one photo's anchors, or those of photos taken from nearly one spot, move by (almost)
        nothing (`anchors_fix_scale` compares the two)."""
        centre = meta_to_dataparser.apply(self.centres.mean(0).numpy())
        scaled = Sim3.scaling_about(np.exp(log_factor), centre) @ meta_to_dataparser
        with torch.no_grad():
            before, in_front = self.error_vectors(meta_to_dataparser.to_torch())
            after, still_in_front = self.error_vectors(scaled.to_torch())
        kept, cell_px = in_front & still_in_front, self.intrinsics[:, 9]
        if not bool(kept.any()):
            return 0.0, float("inf")
        motion = ((after - before).norm(dim=1) * cell_px)[kept]
        return float(motion.pow(2).mean().sqrt()), float((before.norm(dim=1) * cell_px)[kept].median())

    def median_error_cells(self, meta_to_dataparser: Sim3) -> float:
        """Median reprojection error (teacher cells) of the keypoints in front of their cameras."""
        with torch.no_grad():
            errors, in_front = self.residuals(meta_to_dataparser.to_torch())
        return float(errors[in_front].median()) if bool(in_front.any()) else float("nan")


@dataclass
class FreeCameras:
    """What a keypoint fit may change besides the Sim(3), and the priors that hold it. Tensors: `log_focal` [G] log
    focal scales of the term's COLMAP cameras, `focal_sigma` [G] their priors (relative standard deviations);
    `pose_corrections` [P', 6] per photo with keypoints a rotation vector (radians, about the camera centre, in the meta
    frame) and a centre shift (meta units, along the photo's own camera axes: x, y, z the optical axis), `pose_sigma`
    [P', 6] their priors; `k1_delta` [G] the change of each camera's first radial coefficient, `k1_sigma` [G] its prior.
    None: not free."""

    log_focal: Optional[Tensor] = None
    focal_sigma: Optional[Tensor] = None
    pose_corrections: Optional[Tensor] = None
    pose_sigma: Optional[Tensor] = None
    k1_delta: Optional[Tensor] = None
    k1_sigma: Optional[Tensor] = None

    def prior_residuals(self, camera_of: Tensor) -> list[Tensor]:
        """Per free kind, [P', k] residuals whose squares summed over k are one photo's pseudo-observation cost of that
        kind (`camera_of` [P']: each photo's index into the cameras): its camera's log focal scale / sigma, its camera's k1
        change / sigma, its pose correction / sigma (0 for photos not moved)."""
        out = []
        if self.log_focal is not None:
            out.append((self.log_focal / self.focal_sigma)[camera_of, None])
        if self.k1_delta is not None:
            out.append((self.k1_delta / self.k1_sigma)[camera_of, None])
        if self.pose_corrections is not None:
            held = self.pose_sigma > 0  # photos not moved: no correction, no prior
            out.append(torch.where(held, self.pose_corrections / torch.where(held, self.pose_sigma, torch.ones_like(self.pose_sigma)), 0.0))
        return out


def corrected_rotations_and_centres(rotations: Tensor, centres: Tensor, corrections: Tensor) -> tuple[Tensor, Tensor]:
    """Cameras moved by their corrections: rotations [P, 3, 3] (world-to-camera, meta frame) times exp([omega]_x) and
    centres [P, 3] (meta frame) plus the shift, for `corrections` [P, 6] = (omega in the meta frame, shift along the
    camera's own axes as `rotations` give them)."""
    omega = corrections[:, :3]
    zero = torch.zeros_like(omega[:, 0])
    skew = torch.stack([
        torch.stack([zero, -omega[:, 2], omega[:, 1]], -1),
        torch.stack([omega[:, 2], zero, -omega[:, 0]], -1),
        torch.stack([-omega[:, 1], omega[:, 0], zero], -1),
    ], 1)
    return rotations @ torch.linalg.matrix_exp(skew), centres + torch.einsum("pji,pj->pi", rotations, corrections[:, 3:])


class Anchoring:
    """The keypoints of one registration and how each stage weighs them: `term` builds a stage's
    `KeypointTerm` on that stage's teacher grid, weighted by `anchors.weight` x the stage's dense objective at
    its start (`start_value`). Empty (falsy) when the settings' weight is 0 or no photo has keypoints."""

    def __init__(self, meta: MetaImage, keypoints: list[PhotoKeypoints], world_to_dataparser: Sim3, weight: float, narrow: bool = False):
        self.meta, self.keypoints, self.world_to_dataparser, self.weight = meta, keypoints, world_to_dataparser, float(weight)
        self.narrow = narrow
        """Whether stages weigh the keypoints with the camera fit's kernel (FIT_KERNEL_FRACTION of the long side) rather
        than KERNEL_CELLS: once photos were moved to fit their keypoints under it (`for_meta(..., narrow=True)`)."""

    def __bool__(self) -> bool:
        return self.weight > 0 and any(len(k.points2D) for k in self.keypoints)

    def term(self, grid_size: int, start_value: float, kernel: Optional[float] = None) -> Optional[KeypointTerm]:
        """The stage's keypoint term; `kernel` (teacher cells) defaults to this anchoring's (`narrow`)."""
        if not self:
            return None
        weight = self.weight * float(start_value)
        if kernel is None and self.narrow:
            # The narrow kernel with the wide one's curvature at zero error: well-located keypoints hold the pose as
            # firmly as before, the near misses beyond the narrow kernel pull less.
            kernel = FIT_KERNEL_FRACTION * grid_size
            weight *= (kernel / KERNEL_CELLS) ** 2
        return KeypointTerm(self.meta, self.keypoints, self.world_to_dataparser, grid_size, weight, KERNEL_CELLS if kernel is None else kernel)

    def prealign(self, start: Sim3, centre: np.ndarray, grid_size: int, steps: int) -> Sim3:
        """The keypoint term alone minimised from `start` (numpy Sim3, meta -> dataparser): Adam on delta about
        `centre` [3] for `steps` steps (`minimise_keypoint_term`). No render is involved (a few milliseconds a step),
        so a start far off reaches the keypoints' own optimum before the dense objective, whose basin is a few cells
        wide, takes over. Returns `start` without keypoints."""
        term = self.term(grid_size, 1.0, KERNEL_CELLS)
        if not term or steps <= 0:
            return start
        return minimise_keypoint_term(term, start, centre, steps)

    def fix_scale(self, meta_to_dataparser: Sim3, grid_size: int) -> bool:
        """Whether the anchors fix the Sim(3)'s scale under `meta_to_dataparser` (numpy): `anchors_fix_scale` of the
        term's `scale_motion_px`."""
        term = self.term(grid_size, 1.0)
        return bool(term) and anchors_fix_scale(*term.scale_motion_px(meta_to_dataparser))

    def for_meta(self, meta: MetaImage, narrow: Optional[bool] = None) -> "Anchoring":
        """The same keypoints for `meta` (e.g. its photos with new focal scales); `narrow` as this one's unless given."""
        return Anchoring(meta, self.keypoints, self.world_to_dataparser, self.weight, self.narrow if narrow is None else narrow)

    def cost(self, term: Optional[KeypointTerm], meta_to_dataparser: Sim3) -> float:
        """The term's value under a numpy Sim3 (0 without a term)."""
        if not term:
            return 0.0
        with torch.no_grad():
            return float(term(meta_to_dataparser.to_torch()))


def lens_parameters(camera) -> np.ndarray:
    """[9] (fx, fy, cx, cy, k1, k2, p1, p2, 1) of a camera of RADIAL_MODELS in OpenCV's form (absent terms 0); zeros
    for other models (the last entry says which)."""
    params, name = np.asarray(camera.params, dtype=np.float64), camera.model.name
    if name == "SIMPLE_RADIAL":
        return np.array([params[0], params[0], params[1], params[2], params[3], 0.0, 0.0, 0.0, 1.0])
    if name == "RADIAL":
        return np.array([params[0], params[0], params[1], params[2], params[3], params[4], 0.0, 0.0, 1.0])
    if name == "OPENCV":
        return np.array([*params[:8], 1.0])
    return np.zeros(9)


def minimise_keypoint_term(term: KeypointTerm, start: Sim3, centre: np.ndarray, steps: int) -> Sim3:
    """Adam on delta [7] about `centre` for `steps` steps, learning rate PREALIGN_LR: the numpy Sim3 meta -> dataparser
    (`start` when the optimisation diverged)."""
    base = start.to_torch()
    centre_t = torch.from_numpy(np.asarray(centre, dtype=np.float64))
    delta = torch.zeros(7, dtype=torch.float64, requires_grad=True)
    first, last = PREALIGN_LR
    optimizer = torch.optim.Adam([delta], lr=first)
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=(last / first) ** (1.0 / steps))
    for _ in range(steps):
        optimizer.zero_grad()
        term(Sim3.update(delta, centre_t) @ base).backward()
        optimizer.step()
        scheduler.step()
    if not bool(torch.isfinite(delta).all()):
        return start
    with torch.no_grad():
        return (Sim3.update(delta, centre_t) @ base).numpy()
