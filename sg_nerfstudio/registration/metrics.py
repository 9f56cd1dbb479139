"""Registration errors as the paper defines them (section 5.1).

For a meta-image and a transform T (meta -> reference world), each photo's camera is moved by T and by
the ground truth (`Sim3.move_camera`); ΔR is the RMS over photos of the geodesic angle between the two camera rotations
(degrees), ΔT the RMS distance between the two camera centres (reference scene units). A meta-image is
*accurate* (MTA) when ΔR < 5° and ΔT < 0.2, an *outlier* (O%) when ΔR > 10° or ΔT > 0.5.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sg_nerfstudio.geometry.frames import camera_to_world
from sg_nerfstudio.geometry.sim3 import Sim3, rotation_angle_deg

Array = np.ndarray
ACCURATE = (5.0, 0.2)
"""(ΔR degrees, ΔT scene units) below which a result is accurate: the paper's thresholds (MTA)."""
OUTLIER = (10.0, 0.5)
"""(ΔR degrees, ΔT scene units) beyond either of which a result is an outlier: the paper's definition (O%)."""


@dataclass
class PoseErrors:
    rotation_deg: float  # ΔR, RMS over photos
    translation: float  # ΔT, RMS over photos
    per_photo_rotation_deg: list[float]
    per_photo_translation: list[float]

    def accurate(self, rotation_deg: float = ACCURATE[0], translation: float = ACCURATE[1]) -> bool:
        return self.rotation_deg < rotation_deg and self.translation < translation

    def outlier(self, rotation_deg: float = OUTLIER[0], translation: float = OUTLIER[1]) -> bool:
        return self.rotation_deg > rotation_deg or self.translation > translation

    def as_dict(self) -> dict:
        return {
            "delta_R_deg": self.rotation_deg,
            "delta_T": self.translation,
            "accurate": self.accurate(),
            "outlier": self.outlier(),
            "per_photo_delta_R_deg": self.per_photo_rotation_deg,
            "per_photo_delta_T": self.per_photo_translation,
        }


def pose_errors(cam_from_meta: list[Array], transform: Sim3, ground_truth: Sim3) -> PoseErrors:
    """Errors of `transform` against `ground_truth` (both meta -> reference world) over the photos.

    Args:
        cam_from_meta: [3, 4] world-to-camera matrices (OpenCV) of the photos in the meta frame.
    """
    angles, distances = [], []
    for pose in cam_from_meta:
        estimated, truth = transform.move_camera(pose), ground_truth.move_camera(pose)
        angles.append(rotation_angle_deg(estimated[:, :3] @ truth[:, :3].T))
        distances.append(float(np.linalg.norm(camera_to_world(estimated)[:, 3] - camera_to_world(truth)[:, 3])))
    return PoseErrors(
        rotation_deg=float(np.sqrt(np.mean(np.square(angles)))),
        translation=float(np.sqrt(np.mean(np.square(distances)))),
        per_photo_rotation_deg=angles,
        per_photo_translation=distances,
    )
