"""Pose and similarity estimation with pycolmap: one photo in the reference, the meta-image's Sim(3) from
registered camera centres, and the meta-image as one generalized camera (our analogue of gDLS+++).

Frames: `cam_from_reference` / `cam_from_meta` are [3, 4] world-to-camera (OpenCV) matrices; a Sim(3)
`T` [4, 4] maps meta-image coordinates to the reference world, x_ref = s R x_meta + t. Pixel coordinates
follow COLMAP (top-left pixel centre at 0.5) and go to the estimators with each photo's real pycolmap
Camera, so distortion is handled by pycolmap.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import pycolmap

from sg_nerfstudio.geometry.alignment import AlignmentError, align_cameras, camera_residuals
from sg_nerfstudio.geometry.sim3 import Sim3

Array = np.ndarray


@dataclass(frozen=True)
class AbsolutePoseSettings:
    """COLMAP mapper's defaults for registering an image from 2D-3D correspondences."""

    max_error: float = 12.0
    """RANSAC reprojection threshold, pixels."""
    min_inliers: int = 30
    min_inlier_ratio: float = 0.25
    seed: int = 0


@dataclass
class Observations:
    """2D-3D correspondences of one photo with the reference.

    Attributes:
        camera: the photo's pycolmap camera (its real model and parameters).
        cam_from_meta: [3, 4] the photo's pose in the meta-image frame.
        points2D: [M, 2] pixels in the photo.
        points3D: [M, 3] reference world points.
    """

    name: str
    camera: pycolmap.Camera
    cam_from_meta: Array
    points2D: Array
    points3D: Array


@dataclass
class PhotoKeypoints:
    """Verified 2D-3D correspondences of one photo of a meta-image with the reference.

    Attributes:
        name: the photo's image name (as in the meta-image's COLMAP model).
        points2D: [M, 2] pixels in the original photo (COLMAP convention: top-left pixel centre at 0.5).
        points3D: [M, 3] reference world points.
    """

    name: str
    points2D: np.ndarray
    points3D: np.ndarray


@dataclass
class PhotoPose:
    name: str
    cam_from_reference: Optional[Array]
    """[3, 4], None when the photo could not be registered."""
    num_inliers: int
    num_correspondences: int
    inlier_mask: Optional[Array] = None
    """[M] bool over the photo's correspondences, set when it registered."""

    @property
    def registered(self) -> bool:
        return self.cam_from_reference is not None


def _ransac(max_error: float, seed: int, max_trials: int = 10000) -> pycolmap.RANSACOptions:
    options = pycolmap.RANSACOptions()
    options.max_error = max_error
    options.random_seed = seed
    options.max_num_trials = max_trials
    return options


def register_photo(observations: Observations, settings: AbsolutePoseSettings) -> PhotoPose:
    """Absolute pose of one photo in the reference world (LO-RANSAC P3P + refinement, intrinsics fixed)."""
    count = len(observations.points2D)
    failed = PhotoPose(observations.name, None, 0, count)
    if count < max(settings.min_inliers, 4):
        return failed
    estimation = pycolmap.AbsolutePoseEstimationOptions()
    estimation.ransac = _ransac(settings.max_error, settings.seed)
    estimation.ransac.min_inlier_ratio = 0.05
    result = pycolmap.estimate_and_refine_absolute_pose(
        observations.points2D, observations.points3D, observations.camera, estimation, pycolmap.AbsolutePoseRefinementOptions()
    )
    if result is None:
        return failed
    inliers = int(result["num_inliers"])
    if inliers < settings.min_inliers or inliers < settings.min_inlier_ratio * count:
        return PhotoPose(observations.name, None, inliers, count)
    return PhotoPose(observations.name, result["cam_from_world"].matrix(), inliers, count, np.asarray(result["inlier_mask"], dtype=bool))


def centre_of(cam_from_world: Array) -> Array:
    """[3] camera centre of a [3, 4] world-to-camera matrix, in that world."""
    return -cam_from_world[:, :3].T @ cam_from_world[:, 3]


def similarity_from_centres(meta_centres: Array, reference_centres: Array, max_error: float, seed: int = 0) -> Optional[tuple[Array, Array]]:
    """Robust Sim(3) meta -> reference from corresponding camera centres (COLMAP's model_aligner idea).

    Args:
        meta_centres, reference_centres: [P, 3], P >= 3.
        max_error: RANSAC inlier distance, reference units.

    Returns:
        (T [4, 4], inlier mask [P]) or None when no transform with >= 3 inliers exists.
    """
    if len(meta_centres) < 3:
        return None
    estimate = pycolmap.estimate_sim3d_robust(meta_centres, reference_centres, _ransac(max_error, seed))
    if estimate is None:
        return None
    similarity = estimate["tgt_from_src"]
    matrix = np.vstack([similarity.matrix(), [0.0, 0.0, 0.0, 1.0]])
    inliers = np.asarray(estimate["inlier_mask"], dtype=bool)
    if inliers.sum() < 3 or not np.isfinite(matrix).all() or similarity.scale <= 0:
        return None
    return matrix, inliers


def centres_degenerate(centres: Array, ratio: float = 0.2) -> bool:
    """Whether camera centres [P, 3] are (nearly) collinear, or fewer than 3: then they do not fix the rotation
    about their line (a walk along one facade; every 3-photo meta-image taken from one path)."""
    if len(centres) < 3:
        return True
    singular = np.linalg.svd(centres - centres.mean(0), compute_uv=False)
    return bool(singular[1] < ratio * max(singular[0], 1e-12))


def similarity_from_poses(
    cam_from_meta: Array, cam_from_reference: Array, max_error: float, max_rotation_deg: float = 5.0,
) -> Optional[tuple[Array, Array]]:
    """Robust Sim(3) meta -> reference from corresponding camera *poses* (orientation and centre).

    For centres that are (nearly) collinear, where the centres alone leave the rotation about their line free:
    every pair of photos proposes the similarity of `geometry.alignment.align_cameras` (rotation from the two
    orientations, scale and translation from the two centres); a photo agrees when its moved camera is within
    `max_error` (reference units) and `max_rotation_deg` of its registered pose; the hypothesis most photos
    agree with (ties: smaller residual) is refitted on them.

    Args:
        cam_from_meta, cam_from_reference: [P, 3, 4] world-to-camera poses of the same photos, P >= 2.

    Returns:
        (T [4, 4], inlier mask [P]) or None when no pair gives a similarity.
    """
    best = None
    count = len(cam_from_meta)
    for a in range(count):
        for b in range(a + 1, count):
            try:
                hypothesis = align_cameras(cam_from_meta[[a, b]], cam_from_reference[[a, b]]).transform
                scored = camera_residuals(hypothesis, cam_from_meta, cam_from_reference)
            except AlignmentError:
                continue
            inliers = (scored[1] < max_error) & (scored[0] < max_rotation_deg)
            key = (int(inliers.sum()), -float(scored[1][inliers].sum()))
            if inliers.sum() >= 2 and (best is None or key > best[0]):
                best = (key, inliers)
    if best is None:
        return None
    inliers = best[1]
    refit = align_cameras(cam_from_meta[inliers], cam_from_reference[inliers]).transform
    rotation_residual, centre_residual = camera_residuals(refit, cam_from_meta, cam_from_reference)
    inliers = (centre_residual < max_error) & (rotation_residual < max_rotation_deg)
    return np.asarray(refit), inliers


def similarity_from_one_photo(cam_from_meta: Array, cam_from_reference: Array, meta_depth: float, reference_depth: float) -> Optional[Array]:
    """Sim(3) meta -> reference [4, 4] from one photo's pose in both frames ([3, 4] world-to-camera each): rotation and
    centre from the two poses, scale from the median depth of what the photo sees in each (`meta_depth`: its own sparse
    points in the meta-image; `reference_depth`: its inlier reference points in the registered camera). One camera fixes
    6 of the 7 degrees of freedom; the depth ratio is a first guess of the scale about it, for the registration to search
    (`registration.anchored_start.scale_search.scale_the_anchors_leave_free`). None without positive depths."""
    if not (np.isfinite(meta_depth) and np.isfinite(reference_depth) and meta_depth > 0 and reference_depth > 0):
        return None
    scale = reference_depth / meta_depth
    rotation = cam_from_reference[:, :3].T @ cam_from_meta[:, :3]
    matrix = np.eye(4)
    matrix[:3, :3] = scale * rotation
    matrix[:3, 3] = centre_of(cam_from_reference) - scale * rotation @ centre_of(cam_from_meta)
    return matrix


@dataclass(frozen=True)
class GeneralizedSettings:
    max_error: float = 12.0
    """RANSAC reprojection threshold, pixels."""
    min_inliers: int = 30
    """Fewest pooled inlier correspondences for a transform."""
    min_photos: int = 2
    """Fewest photos contributing inliers (one photo does not constrain the scale)."""
    scale_range_decades: float = 2.0
    """The scale is searched over this many decades either side of a first guess."""
    scale_steps_per_decade: int = 4
    """Spacing of the first (coarsest) scale grid; finer grids follow (`search_scale`)."""
    search_trials: int = 1000
    """RANSAC trials per scale while searching (the final estimate at the chosen scale uses 10000)."""
    seed: int = 0


@dataclass
class GeneralizedPose:
    transform: Sim3  # meta -> reference
    num_inliers: int
    inliers_per_photo: dict[str, int]
    inliers: dict[str, tuple[Array, Array]] = field(default_factory=dict)
    """Photo name -> its inlier correspondences under the rig's pose: ([K, 2] pixels, [K, 3] reference world points)."""


class _GeneralizedProblem:
    """Pooled correspondences of the photos, and the rig of the meta-image at a given scale.

    Attributes:
        points2D: [M, 2] pixels; points3D: [M, 3] reference world; camera_index: [M] photo of each.
    """

    def __init__(self, photos: list[Observations], meta_depth: float, settings: GeneralizedSettings):
        self.photos, self.settings = photos, settings
        self.points2D = np.concatenate([p.points2D for p in photos])
        self.points3D = np.concatenate([p.points3D for p in photos])
        self.camera_index = np.concatenate([np.full(len(p.points2D), i) for i, p in enumerate(photos)])
        self.cameras = [p.camera for p in photos]
        centres = np.stack([centre_of(p.cam_from_meta) for p in photos])  # [P, 3] meta frame
        self.meta_centroid = centres.mean(axis=0)
        focal = float(np.median([camera.mean_focal_length() for camera in self.cameras]))
        spread = float(np.median(np.linalg.norm(centres - self.meta_centroid, axis=1)))
        self.pixels_per_scale_error = focal * spread / max(meta_depth, 1e-12)
        """Pixels a photo's points move when the rig's scale is off by a relative 1 (small errors scale linearly):
        its centre moves by that fraction of its distance to the rig's centroid, seen at the scene's depth."""

    def rig(self, scale: float) -> list:
        """cam_from_rig per photo when the rig frame is the meta frame scaled by `scale`."""
        return [pycolmap.Rigid3d(pycolmap.Rotation3d(p.cam_from_meta[:, :3]), scale * p.cam_from_meta[:, 3]) for p in self.photos]

    def ransac(self, scale: float, trials: int, refine: bool, max_error: Optional[float] = None):
        """(rig_from_world [3, 4], inlier mask [M]) or None; `max_error` pixels (default: the settings')."""
        options = _ransac(self.settings.max_error if max_error is None else max_error, self.settings.seed, trials)
        estimator = pycolmap.estimate_and_refine_generalized_absolute_pose if refine else pycolmap.estimate_generalized_absolute_pose
        result = estimator(self.points2D, self.points3D, self.camera_index.tolist(), self.rig(scale), self.cameras, options)
        if result is None:
            return None
        return result["rig_from_world"].matrix(), np.asarray(result["inlier_mask"], dtype=bool)

    def score(self, scale: float, max_error: float) -> tuple[int, float]:
        """(inliers, -mean reprojection error) of a quick RANSAC at `scale`: larger is better."""
        found = self.ransac(scale, self.settings.search_trials, refine=False, max_error=max_error)
        if found is None:
            return -1, -math.inf
        rig_from_world, mask = found
        return int(mask.sum()), -self.error(rig_from_world, scale, mask)

    def refine_at(self, scale: float, rig_from_world: Array, mask: Array) -> Array:
        """rig_from_world [3, 4] refined (inliers fixed) at another scale, starting from `rig_from_world`."""
        start = pycolmap.Rigid3d(rig_from_world)
        result = pycolmap.refine_generalized_absolute_pose(
            start, self.points2D, self.points3D, mask, self.camera_index.tolist(), self.rig(scale), self.cameras
        )
        return rig_from_world if result is None else result["rig_from_world"].matrix()

    def error(self, rig_from_world: Array, scale: float, mask: Array) -> float:
        return _mean_reprojection_error(rig_from_world, self.rig(scale), self.photos, self.points2D, self.points3D, self.camera_index, mask)


def generalized_similarity(photos: list[Observations], meta_depth: float, settings: GeneralizedSettings) -> Optional[GeneralizedPose]:
    """The meta-image as one generalized camera (rig = meta frame, cameras = the photos).

    pycolmap's generalized absolute pose is rigid (6 DoF), so the scale is found around it: for a scale s
    the rig holds the photos with cam_from_rig = (R_c, s t_c) (the meta frame scaled by s). Log-spaced grids,
    coarse to fine, around the first guess `points' spread in the reference / meta_depth` pick the scale
    whose pose has most inliers (`search_scale`), then the pose is estimated and refined there, and the
    scale is refined continuously by minimising the inliers' reprojection error (pose re-refined at each
    trial scale). gDLS+++ solves the 7 DoF jointly; this is the same objective with pycolmap's building blocks.

    Args:
        photos: per-photo correspondences (photos without any are skipped).
        meta_depth: typical depth of the scene in the photos, meta units (median sparse-point depth).

    Returns:
        the transform, or None when fewer than `min_inliers` correspondences or `min_photos` photos agree.
    """
    used = [p for p in photos if len(p.points2D)]
    if sum(len(p.points2D) for p in used) < max(settings.min_inliers, 6) or len(used) < settings.min_photos:
        return None
    problem = _GeneralizedProblem(used, meta_depth, settings)
    spread = float(np.median(np.linalg.norm(problem.points3D - np.median(problem.points3D, axis=0), axis=1)))
    guess = max(spread, 1e-9) / max(meta_depth, 1e-9)
    scale, spacing = search_scale(problem, guess, settings)
    found = problem.ransac(scale, 10000, refine=True)
    if found is None:
        return None
    rig_from_world, mask = found
    per_photo = {p.name: int(mask[problem.camera_index == i].sum()) for i, p in enumerate(used)}
    if mask.sum() < settings.min_inliers or sum(v > 0 for v in per_photo.values()) < settings.min_photos:
        return None
    scale, rig_from_world = _refine_scale(problem, scale, rig_from_world, mask, spacing)
    rotation = rig_from_world[:, :3].T
    transform = Sim3.from_parts(scale, rotation, -rotation @ rig_from_world[:, 3])
    inliers = {
        p.name: (problem.points2D[(problem.camera_index == i) & mask], problem.points3D[(problem.camera_index == i) & mask]) for i, p in enumerate(used)
    }
    return GeneralizedPose(transform, int(mask.sum()), per_photo, inliers)


def search_scale(problem: _GeneralizedProblem, guess: float, settings: GeneralizedSettings) -> tuple[float, float]:
    """(scale, spacing in decades of the last grid): the rig scale whose generalized pose has most inliers.

    A pose at the wrong scale fits one photo and leaves the others' points displaced by about
    `pixels_per_scale_error` x the relative error; photos far apart (a walk along a facade) have a basin only
    a few percent wide, narrower than a practical grid. So each grid scores its scales with the RANSAC
    threshold widened by the displacement of half its spacing (a scale between grid points still counts the
    other photos' inliers), and the next grid, 4x finer, spans the chosen point's neighbours; the search stops
    once half a spacing displaces points by at most half of `max_error` (it then scores with at most 1.5x it).
    """
    spacing = 1.0 / settings.scale_steps_per_decade
    grid = guess * 10.0 ** np.arange(-settings.scale_range_decades, settings.scale_range_decades + spacing / 2, spacing)
    while True:
        displacement = problem.pixels_per_scale_error * (10.0 ** (spacing / 2) - 1.0)
        threshold = settings.max_error + displacement
        scale = float(max(grid, key=lambda s: problem.score(float(s), threshold)))
        if displacement <= settings.max_error / 2 or spacing < 1e-4:
            return scale, spacing
        spacing /= 4
        grid = scale * 10.0 ** (spacing * np.arange(-4, 5))


def _refine_scale(problem: _GeneralizedProblem, scale: float, rig_from_world: Array, mask: Array, decades: float) -> tuple[float, Array]:
    """(scale, rig_from_world) minimising the inliers' mean reprojection error within +-`decades`."""
    from scipy.optimize import minimize_scalar

    def pose_at(log_scale: float) -> Array:
        start = rig_from_world.copy()
        start[:, 3] += (math.exp(log_scale) - scale) * problem.meta_centroid  # keeps the photos' centroid in place
        return problem.refine_at(math.exp(log_scale), start, mask)

    def cost(log_scale: float) -> float:
        return problem.error(pose_at(log_scale), math.exp(log_scale), mask)

    centre, width = math.log(scale), decades * math.log(10.0)
    best = minimize_scalar(cost, bounds=(centre - width, centre + width), method="bounded", options={"xatol": 1e-4})
    if not best.success or cost(best.x) > cost(centre):
        return scale, rig_from_world
    return math.exp(best.x), pose_at(best.x)


def _mean_reprojection_error(rig_from_world: Array, rig: list, photos: list[Observations], points2D: Array, points3D: Array, camera_index: Array, mask: Array) -> float:
    """Mean pixel error of the inlier correspondences under a generalized pose."""
    if not mask.any():
        return math.inf
    errors = []
    world_h = np.hstack([points3D, np.ones((len(points3D), 1))])
    for i, photo in enumerate(photos):
        chosen = mask & (camera_index == i)
        if not chosen.any():
            continue
        cam_from_rig = rig[i].matrix()
        cam_from_world = cam_from_rig[:, :3] @ rig_from_world
        cam_from_world[:, 3] += cam_from_rig[:, 3]
        in_camera = world_h[chosen] @ cam_from_world.T
        projected = photo.camera.img_from_cam(in_camera, check_cheirality=False)
        errors.append(np.linalg.norm(projected - points2D[chosen], axis=1))
    return float(np.mean(np.concatenate(errors)))
