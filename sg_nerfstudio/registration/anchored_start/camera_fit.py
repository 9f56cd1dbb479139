"""The camera fit: the meta-image's own cameras fitted to the keypoint anchors together with the Sim(3), render-free.

An SfM of a few photos gets focal lengths a few percent wrong, relative poses a fraction of a degree and k1 a few
hundredths; one Sim(3) cannot absorb any of them, and a dense alignment then spreads the error over the group.
`fit_cameras` frees, with the Sim(3), what `settings.camera_fit` asks: one focal scale per COLMAP camera (`focal`), each
photo's pose by a small rotation and centre shift (`photo_poses`), each camera's k1 (`distortion`). Two solvers, for two
models of the same fit:
- the *prior fit* (`fit_jointly`): the anchors alone, each parameter held by the SfM's own uncertainty of it at the
  keypoints' noise; Levenberg-Marquardt (least_squares.py). It works for any camera model and any anchors;
- the *adjustment* (bundle_adjustment.py, `solver: adjustment`): pycolmap's bundle adjuster on the meta-image's own
  tracks with the anchors as constant points, which moves focal length, depth, k1 and orientation together as the SfM's
  correlations allow. It needs anchors that fix the scale and cameras with at most k1; elsewhere the prior fit runs.
A fit that asks more of the cameras than an SfM of a few photos errs by (`beyond_limits`) is refused; the refusal is
verdict evidence (`CameraFit.refused`). Later stages render the moved cameras, and the registration reports the final
Sim(3) composed with the one that maps the given cameras onto the moved ones. Frames: as anchors.py.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import torch
from torch import Tensor

from sg_nerfstudio.geometry.meta_image import intrinsics_uncertainty, radial_k1_index, relative_rotation_uncertainty
from sg_nerfstudio.geometry.sim3 import Sim3
from sg_nerfstudio.registration.anchored_start.bundle_adjustment import adjust_with_anchors, adjustable, pose_changes
from sg_nerfstudio.registration.anchored_start.anchors import (
    FIT_KERNEL_FRACTION, KERNEL_CELLS, Anchoring, FreeCameras, KeypointTerm, corrected_rotations_and_centres,
)
from sg_nerfstudio.registration.anchored_start.least_squares import RobustResiduals, levenberg_marquardt


MAX_FOCAL_CHANGE = 0.2
"""A fitted focal scale outside [1 / (1 + this), 1 + this] is not believed (an SfM focal length is rarely 20% off): the
fit is refused."""

MAX_K1_CHANGE = 0.2
"""A change of a camera's k1 beyond this is not believed (real lenses' k1 lies within about +-0.3): the fit is refused."""

MAX_POSE_CHANGE_DEG = 2.0
"""A photo turned beyond this, or shifted beyond its median depth times this angle plus the depth change its focal change
implies (`implausibility`), is not believed (an SfM's relative poses err by fractions of a degree): the fit is refused."""


@dataclass
class CameraFit:
    """The result of `fit_cameras`: the Sim(3) (numpy, meta -> dataparser) fitted with the cameras, {photo name:
    focal_scale} of every photo of a refined camera, {photo name: [3, 4] cam_from_meta} of every moved photo and
    {COLMAP camera id: k1} of every camera whose radial distortion was refined."""

    transform: Sim3
    focal_scales: dict[str, float] = field(default_factory=dict)
    poses: dict[str, np.ndarray] = field(default_factory=dict)
    radial_k1: dict[int, float] = field(default_factory=dict)
    refused: str = ""
    """Why the fitted cameras were not kept (`beyond_limits`: the anchors asked more of the meta-image's own cameras
    than an SfM error of a few photos plausibly is), "" when they were or nothing was fitted. Verdict evidence."""


def fit_cameras(
    anchoring: Anchoring, start: Sim3, centre: np.ndarray, grid_size: int, iterations: int, focal: bool, pose_prior_scale: Optional[float],
    distortion: bool = False, adjustment: bool = False,
) -> CameraFit:
    """The keypoint term of `anchoring` minimised over the Sim(3) (numpy, meta -> dataparser; `start` best pre-aligned)
    *and* the meta-image's cameras: with `focal`, one focal scale per COLMAP camera of the photos with keypoints; with
    `pose_prior_scale`, each such photo's pose under a prior of that times its SfM rotation uncertainty (the keypoints then
    weighed with the narrower FIT_KERNEL_FRACTION kernel); with `distortion`, each radial camera's k1. Each parameter is
    held by the SfM's own uncertainty at the keypoints' noise (`intrinsics_priors`, `rotation_priors`): what the SfM fixed
    well barely moves. Every photo of a refined camera renders with it; photos without keypoints keep their pose.

    With `adjustment` (and poses fitted), where every camera has at most k1 (`bundle_adjustment.adjustable`) and the
    anchors fix the scale (`Anchoring.fix_scale`), the fit is the bundle adjustment instead (`adjusted_cameras`): anchors
    of one photo, or of photos from one spot, leave the scale a direction the adjuster would end anywhere along; there
    the prior fit moves only the anchored photos and the registration searches the scale (`scale_search`). `start` alone
    when nothing could be freed or the fit diverged; refused (`CameraFit.refused`) beyond the limits."""
    if adjustment and pose_prior_scale is not None and adjustable(anchoring.meta) and anchoring.fix_scale(start, grid_size):
        return adjusted_cameras(anchoring, start, focal, distortion)
    kernel = FIT_KERNEL_FRACTION * grid_size if pose_prior_scale is not None else KERNEL_CELLS
    term = anchoring.term(grid_size, 1.0, kernel)
    if not term or iterations <= 0:
        return CameraFit(start)
    focal_sigma, k1_sigma = intrinsics_priors(anchoring, kernel / grid_size) if focal or distortion else ({}, {})
    focal_free = freedom(focal_sigma, term.camera_ids) if focal else None
    k1_free = freedom(k1_sigma, term.camera_ids) if distortion else None
    pose_sigma = term.pose_sigma(rotation_priors(anchoring, pose_prior_scale), focal_sigma if focal else None) if pose_prior_scale is not None else None
    if focal_free is None and pose_sigma is None and k1_free is None:
        return CameraFit(start)
    fitted = fit_jointly(term, start, centre, iterations, focal_free, pose_sigma, k1_free)
    if fitted is None:
        return CameraFit(start)
    moved, free = fitted
    refused = implausibility(free, term.camera_of)
    if refused:
        return CameraFit(start, refused=refused)  # the Sim(3) was fitted with those cameras: neither is kept
    fit = CameraFit(moved)
    if free.log_focal is not None:
        change = {camera_id: float(torch.exp(value)) for camera_id, value, own in zip(term.camera_ids, free.log_focal, focal_free[1]) if own}
        fit.focal_scales = {p.name: p.focal_scale * change[int(p.camera.camera_id)] for p in anchoring.meta.photos if int(p.camera.camera_id) in change}
    if free.k1_delta is not None:
        cameras = anchoring.meta.reconstruction.cameras
        fit.radial_k1 = {
            camera_id: float(cameras[camera_id].params[radial_k1_index(cameras[camera_id])] + float(delta))
            for camera_id, delta, own in zip(term.camera_ids, free.k1_delta, k1_free[1]) if own
        }
    if free.pose_corrections is not None:
        rotations, centres = corrected_rotations_and_centres(term.rotations, term.centres, free.pose_corrections)
        translations = -torch.einsum("pij,pj->pi", rotations, centres)
        moved = free.pose_sigma[:, 0] > 0
        fit.poses = {name: torch.cat([r, t[:, None]], 1).numpy() for name, r, t, m in zip(term.names, rotations, translations, moved) if m}
    return fit


def adjusted_cameras(anchoring: Anchoring, start: Sim3, focal: bool, distortion: bool) -> CameraFit:
    """`fit_cameras` by `bundle_adjustment.adjust_with_anchors` from `start` (numpy Sim3, meta -> dataparser); `start`
    alone when the adjuster fails; refused when it moves a camera beyond the prior fit's limits (`beyond_limits`). The
    centre-shift allowance takes the meta-image's largest focal change, not the photo's own: the adjusted model is
    compared with the given one after the Sim(3) that maps one onto the other, which spreads one photo's depth change
    over all of them."""
    adjusted = adjust_with_anchors(anchoring.meta, anchoring.keypoints, anchoring.world_to_dataparser, start, focal, distortion, FIT_KERNEL_FRACTION)
    if adjusted is None:
        return CameraFit(start)
    transform, poses, focal_change, radial_k1 = adjusted
    cameras = anchoring.meta.reconstruction.cameras
    angles, shifts, depths = pose_changes(anchoring.meta, poses)
    depth_change = max((abs(np.log(change)) for change in focal_change.values()), default=0.0)
    refused = beyond_limits(
        list(focal_change.values()), [k1 - cameras[c].params[radial_k1_index(cameras[c])] for c, k1 in radial_k1.items()],
        list(angles), bool((shifts > depths * (np.radians(MAX_POSE_CHANGE_DEG) + depth_change)).any()),
    )
    if refused:
        return CameraFit(start, refused=refused)
    focal_scales = {p.name: p.focal_scale * focal_change[int(p.camera.camera_id)] for p in anchoring.meta.photos} if focal_change else {}
    return CameraFit(transform, focal_scales, poses, radial_k1)


def rotation_priors(anchoring: Anchoring, scale: float) -> dict[str, float]:
    """{photo name: prior standard deviation (degrees) of its rotation correction}: `scale` times how well the
    meta-image's SfM determined its orientation relative to the other photos (`relative_rotation_uncertainty`),
    at the noise as which the pose fit's kernel (FIT_KERNEL_FRACTION) weighs the keypoints (`keypoint_noise_px`)."""
    sides = {photo.name: max(photo.camera.width, photo.camera.height) for photo in anchoring.meta.photos}
    return {
        name: scale * sigma * keypoint_noise_px(sides[name], FIT_KERNEL_FRACTION)
        for name, sigma in relative_rotation_uncertainty(anchoring.meta.reconstruction).items() if name in sides
    }


def intrinsics_priors(anchoring: Anchoring, kernel_fraction: float) -> tuple[dict[int, float], dict[int, float]]:
    """({COLMAP camera id: prior relative standard deviation of its focal length}, {camera id: prior standard deviation
    of its k1}): the meta-image SfM's own uncertainties (`intrinsics_uncertainty`, at 1 px of noise) scaled to the noise
    as which a fit under the Cauchy kernel of `kernel_fraction` of the long side weighs the keypoints
    (`keypoint_noise_px`), as `rotation_priors` holds the poses: prior and keypoints then speak of the same noise."""
    focal, k1 = intrinsics_uncertainty(anchoring.meta.reconstruction)
    cameras = anchoring.meta.reconstruction.cameras
    noise = {camera_id: keypoint_noise_px(max(camera.width, camera.height), kernel_fraction) for camera_id, camera in cameras.items()}
    return {c: sigma * noise[c] for c, sigma in focal.items()}, {c: sigma * noise[c] for c, sigma in k1.items()}


def keypoint_noise_px(long_side: float, kernel_fraction: float) -> float:
    """The standard deviation per coordinate (pixels of a photo whose long side is `long_side`) as which a fit under the
    Cauchy kernel of `kernel_fraction` of the long side weighs each keypoint: near zero error rho(r / c) ~ r^2 / c^2, a
    Gaussian of c / sqrt(2) per coordinate (FIT_KERNEL_FRACTION: 2.8 px of a 640-px photo). The SfM covariances assume 1
    px of noise; the priors that hold the fitted cameras are scaled by this so that prior and keypoints speak of the same
    noise."""
    return kernel_fraction * long_side / np.sqrt(2.0)


def freedom(uncertainty: dict[int, float], camera_ids: list[int]) -> Optional[tuple[Tensor, Tensor]]:
    """([G] prior sigma per camera of `camera_ids` from the SfM's `uncertainty` {camera id: sigma}, [G] bool: free, the
    cameras it has a sigma for); None if none is free."""
    sigma = torch.tensor([uncertainty.get(camera_id, np.nan) for camera_id in camera_ids], dtype=torch.float64)
    free = torch.isfinite(sigma)
    return (torch.where(free, sigma, torch.ones_like(sigma)), free) if bool(free.any()) else None


def fit_jointly(
    term: KeypointTerm, start: Sim3, centre: np.ndarray, iterations: int,
    focal: Optional[tuple[Tensor, Tensor]] = None, pose_sigma: Optional[Tensor] = None,
    k1: Optional[tuple[Tensor, Tensor]] = None,
) -> Optional[tuple[Sim3, FreeCameras]]:
    """Levenberg-Marquardt (`least_squares.levenberg_marquardt`, at most `iterations`) on delta [7] about `centre` and,
    with `focal` ([G] prior sigmas, [G] bool free), the log focal scales of the cameras marked free, with `pose_sigma`
    [P', 6] the photos' pose corrections (in units of their prior), with `k1` ([G] prior sigmas, [G] bool free) the
    changes of the cameras' k1, each under its prior: (the numpy Sim3 meta -> dataparser, the fitted `FreeCameras`); None
    when it diverged. The problem is small and smooth but ill-conditioned (focal length against depth, a common turn
    of every photo against the Sim(3)): a Gauss-Newton method converges where first-order ones did not."""
    base = start.to_torch()
    centre_t = torch.from_numpy(np.asarray(centre, dtype=np.float64))
    cameras, photos = len(term.camera_ids), term.photos
    sizes = [7, cameras if focal is not None else 0, 6 * photos if pose_sigma is not None else 0, cameras if k1 is not None else 0]

    def unpack(x: Tensor) -> tuple[Tensor, FreeCameras]:
        delta, log_focal, corrections, k1_delta = torch.split(x, sizes)
        return delta, FreeCameras(
            log_focal * focal[1].double() if focal is not None else None, focal[0] if focal is not None else None,
            corrections.reshape(photos, 6) * pose_sigma if pose_sigma is not None else None, pose_sigma,
            k1_delta * k1[1].double() if k1 is not None else None, k1[0] if k1 is not None else None,
        )

    def residuals(x: Tensor) -> RobustResiduals:
        delta, free = unpack(x)
        return term.robust_residuals(Sim3.update(delta, centre_t) @ base, free)

    solution = levenberg_marquardt(residuals, torch.zeros(sum(sizes), dtype=torch.float64), iterations)
    if not bool(torch.isfinite(solution.x).all()):
        return None
    delta, free = unpack(solution.x)
    return (Sim3.update(delta, centre_t) @ base).numpy(), free


def beyond_limits(focal_scales: list[float], k1_changes: list[float], turns_deg: list[float], shifted_too_far: bool) -> str:
    """The first of a camera fit's changes that is not believed, as a phrase for the verdict ("" when all are within the
    limits): a focal scale outside [1 / (1 + MAX_FOCAL_CHANGE), 1 + MAX_FOCAL_CHANGE], a k1 change beyond MAX_K1_CHANGE,
    a photo turned beyond MAX_POSE_CHANGE_DEG, or a centre shifted beyond the allowance the caller measured
    (`shifted_too_far`)."""
    for scale in focal_scales:
        if abs(np.log(scale)) > np.log1p(MAX_FOCAL_CHANGE):
            return f"a focal length x{scale:.2f} (beyond {MAX_FOCAL_CHANGE:.0%})"
    for change in k1_changes:
        if abs(change) > MAX_K1_CHANGE:
            return f"a k1 change of {change:+.2f} (beyond {MAX_K1_CHANGE})"
    for turn in turns_deg:
        if turn > MAX_POSE_CHANGE_DEG:
            return f"a photo turned {turn:.1f}° (beyond {MAX_POSE_CHANGE_DEG:.0f}°)"
    if shifted_too_far:
        return f"a photo moved beyond its depth times {MAX_POSE_CHANGE_DEG:.0f}° and its focal change"
    return ""


def implausibility(free: FreeCameras, camera_of: Tensor) -> str:
    """`beyond_limits` of fitted cameras ("" when they are plausible): their focal scales, k1 changes and pose
    corrections (`camera_of` [P'] each photo's index into the cameras). A photo's centre shift is compared with its
    median point depth times MAX_POSE_CHANGE_DEG plus the depth change its camera's focal change implies
    (depth x |log focal scale|): a photo whose SfM focal length was some percent off stood as many percent nearer or
    farther in the SfM, and the fit must move it by that much to keep its image."""
    focal = torch.exp(free.log_focal).tolist() if free.log_focal is not None else []
    k1 = free.k1_delta.tolist() if free.k1_delta is not None else []
    turns, shifted = [], False
    if free.pose_corrections is not None:
        limit = np.radians(MAX_POSE_CHANGE_DEG)
        turn, shift = free.pose_corrections[:, :3].norm(dim=1), free.pose_corrections[:, 3:].norm(dim=1)
        depth_change = free.log_focal.abs()[camera_of] if free.log_focal is not None else torch.zeros_like(turn)
        # depth = the centre's sigma across the optical axis (index 3: depth x angle) / rotation sigma
        # (`KeypointTerm.pose_sigma`), so shift > depth x allowance reads as below;
        # photos not moved have sigma 0 and shift 0: 0 > 0 is False
        turns = torch.rad2deg(turn).tolist()
        shifted = bool((shift * free.pose_sigma[:, 0] > (limit + depth_change) * free.pose_sigma[:, 3]).any())
    return beyond_limits(focal, k1, turns, shifted)
