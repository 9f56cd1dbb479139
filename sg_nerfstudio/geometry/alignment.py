"""The similarity that maps one set of cameras onto another: ground truth for meta-images reconstructed on
their own, from the same photos' cameras in the reference solution.

Camera centres alone fix a Sim(3) only when they are not collinear, and photos walked along one facade are
nearly collinear; so the rotation comes from the camera orientations (chordal L2 mean of R_tgt^T R_src over
the cameras, projected onto SO(3)), and scale and translation from the centres with that rotation fixed
(least squares). With frames x_tgt = s R x_src + t, a camera cam_from_world [R_c | t_c] in the source frame
becomes [R_c R^T | ...] in the target frame (`Sim3.move_camera`), so R = R_c,tgt^T R_c,src for every camera.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sg_nerfstudio.errors import InputError
from sg_nerfstudio.geometry.sim3 import Sim3

Array = np.ndarray


class AlignmentError(InputError):
    """Cameras that do not determine a similarity."""


@dataclass(frozen=True)
class CameraAlignment:
    transform: Sim3  # source frame -> target frame
    rotation_residual_deg: Array  # [N] per camera, after alignment
    centre_residual: Array  # [N] per camera, target units


def camera_centres(cam_from_world: Array) -> Array:
    """[N, 3] centres of [N, 3, 4] OpenCV cam_from_world poses."""
    rotations, translations = cam_from_world[:, :, :3], cam_from_world[:, :, 3]
    return -np.einsum("nji,nj->ni", rotations, translations)


def align_cameras(source: Array, target: Array) -> CameraAlignment:
    """The Sim(3) source -> target that best maps the cameras `source` [N, 3, 4] onto `target` [N, 3, 4]."""
    source, target = np.asarray(source, np.float64), np.asarray(target, np.float64)
    if source.shape != target.shape or source.ndim != 3 or source.shape[1:] != (3, 4):
        raise AlignmentError(f"Camera alignment needs two [N, 3, 4] pose sets of one size, got {source.shape} and {target.shape}.")
    mean = np.einsum("nji,njk->ik", target[:, :, :3], source[:, :, :3])
    u, _, vt = np.linalg.svd(mean)
    rotation = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    src_centres, tgt_centres = camera_centres(source), camera_centres(target)
    rotated = (src_centres - src_centres.mean(0)) @ rotation.T
    spread = float((rotated**2).sum())
    if len(source) < 2 or spread < 1e-12:
        raise AlignmentError(f"Camera alignment needs at least 2 cameras at distinct centres, got {len(source)}.")
    scale = float((rotated * (tgt_centres - tgt_centres.mean(0))).sum() / spread)
    if scale <= 0:
        raise AlignmentError("The two camera sets are not related by a similarity with positive scale (their centres run in opposite directions).")
    translation = tgt_centres.mean(0) - scale * rotation @ src_centres.mean(0)
    transform = Sim3.from_parts(scale, rotation, translation)
    return CameraAlignment(transform, *camera_residuals(transform, source, target))


def camera_residuals(transform: Sim3, source: Array, target: Array) -> tuple[Array, Array]:
    """[N] rotation (degrees) and centre (target units) differences of the cameras `source` [N, 3, 4] moved
    by `transform` from the cameras `target` [N, 3, 4]."""
    source, target = np.asarray(source, np.float64), np.asarray(target, np.float64)
    linear, translation = np.asarray(transform.linear, np.float64), np.asarray(transform.translation, np.float64)
    moved_rotations = source[:, :, :3] @ (linear / float(transform.scale)).T  # as Sim3.move_camera, for all at once
    moved_centres = camera_centres(source) @ linear.T + translation
    cos = (np.einsum("nij,nij->n", moved_rotations, target[:, :, :3]) - 1.0) / 2.0  # trace(moved @ target^T)
    rotation = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return rotation, np.linalg.norm(moved_centres - camera_centres(target), axis=1)
