"""Registration errors as the paper defines them (section 5.1).

For a meta-image and a transform T (meta -> reference world), each photo's camera is moved by T and by
the ground truth; ΔR is the RMS over photos of the geodesic angle between the two camera rotations
(degrees), ΔT the RMS distance between the two camera centres (reference scene units). A meta-image is
*accurate* (MTA) when ΔR < 5° and ΔT < 0.2, an *outlier* (O%) when ΔR > 10° or ΔT > 0.5.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sg_nerfstudio.registration.sim3 import decompose, rotation_angle_deg

Array = np.ndarray
ACCURATE = (5.0, 0.2)
OUTLIER = (10.0, 0.5)


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


def pose_errors(cam_from_meta: list[Array], transform: Array, ground_truth: Array) -> PoseErrors:
    """Errors of `transform` against `ground_truth` (both [4, 4] meta -> reference) over the photos.

    Args:
        cam_from_meta: [3, 4] world-to-camera matrices of the photos in the meta frame.
    """
    _, rotation, _ = decompose(transform)
    _, rotation_gt, _ = decompose(ground_truth)
    angles, distances = [], []
    for pose in cam_from_meta:
        centre = np.append(-pose[:, :3].T @ pose[:, 3], 1.0)
        world_from_cam = pose[:, :3].T
        estimated, truth = rotation @ world_from_cam, rotation_gt @ world_from_cam
        angles.append(rotation_angle_deg(estimated.T @ truth))
        distances.append(float(np.linalg.norm((transform @ centre)[:3] - (ground_truth @ centre)[:3])))
    return PoseErrors(
        rotation_deg=float(np.sqrt(np.mean(np.square(angles)))),
        translation=float(np.sqrt(np.mean(np.square(distances)))),
        per_photo_rotation_deg=angles,
        per_photo_translation=distances,
    )
