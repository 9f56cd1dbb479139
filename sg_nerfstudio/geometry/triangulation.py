"""A COLMAP track triangulated again with cameras other than the ones its model was built with.

Two places replace a model's cameras and need its points to follow: the registration's aligned model, whose photos
carry the focal lengths, radial distortion and poses the registration fitted (`registration.merge`), and the
point-based ground truth of the real-photo benchmark scenes, which puts a meta-image's tracks into the calibrated
cameras (`photos.scene.point_truth`). pycolmap's LO-RANSAC triangulation does the work; this module only gathers a
track's observations and states the thresholds.

Frames: `cam_from_world` poses are [3, 4] OpenCV world-to-camera matrices in whatever world the caller's cameras are
in; pixels are COLMAP's (top-left pixel centre at 0.5) in each camera's own image.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import pycolmap

Array = np.ndarray

TRACK_PIXELS = 4.0
"""Reprojection threshold (pixels) of an observation under the new cameras: COLMAP's filter default."""


@dataclass(frozen=True)
class Triangulated:
    xyz: Array  # [3] in the cameras' world
    inliers: Array  # [K] bool over the track's observations


def triangulate_track(
    pixels: Array, cam_from_world: list[Array], cameras: list[pycolmap.Camera], min_angle_deg: float = 0.0,
    max_error_px: float = TRACK_PIXELS,
) -> Optional[Triangulated]:
    """The point that observations `pixels` [K, 2] (K >= 2) of cameras `cameras` at poses `cam_from_world` see, or None
    when fewer than two of them agree within `max_error_px` or their rays meet at less than `min_angle_deg`."""
    options = pycolmap.EstimateTriangulationOptions()
    options.min_tri_angle = np.radians(min_angle_deg)
    options.ransac.random_seed = 0
    options.ransac.max_error = max_error_px / min(camera.mean_focal_length() for camera in cameras)  # angular: radians
    poses = [pycolmap.Rigid3d(np.asarray(pose, dtype=np.float64)) for pose in cam_from_world]
    found = pycolmap.estimate_triangulation(np.asarray(pixels, dtype=np.float64), poses, list(cameras), options)
    if found is None:
        return None
    inliers = np.asarray(found["inliers"], dtype=bool)
    return Triangulated(np.asarray(found["xyz"], dtype=np.float64), inliers) if inliers.sum() >= 2 else None


def track_observations(model: pycolmap.Reconstruction, point: pycolmap.Point3D) -> tuple[list[tuple[int, int]], Array]:
    """([(image id, point2D index)] of the track's observations, [K, 2] their pixels) of `point` in `model`."""
    elements = [(e.image_id, e.point2D_idx) for e in point.track.elements]
    pixels = np.array([model.images[i].points2D[j].xy for i, j in elements], dtype=np.float64).reshape(-1, 2)
    return elements, pixels
