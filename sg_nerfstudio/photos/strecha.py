"""Cameras in the Strecha multi-view benchmark format (fountain-P11, Herz-Jesu-P8, ...): one
`<photo name>.camera` text file per photo, for the photo's original size:

    K           3 lines (3x3 intrinsics, pixels)
    distortion  1 line (zeros: the published images are undistorted)
    R           3 lines: camera-to-world rotation
    t           1 line: camera centre in world coordinates
    w h         1 line: image size

A world point X is in the camera at x_cam = R^T (X - t), OpenCV axes. pycolmap has no reader for this
format, hence this one.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from sg_nerfstudio.errors import InputError, not_a_directory

Array = np.ndarray


class CameraFileError(InputError):
    """A camera file that is missing or not in the expected format."""


@dataclass(frozen=True)
class StrechaCamera:
    K: Array  # [3, 3] at (width, height)
    rotation_cam_to_world: Array  # [3, 3]
    centre: Array  # [3]
    width: int
    height: int

    def cam_from_world(self) -> Array:
        """[3, 4] OpenCV cam_from_world."""
        rotation = self.rotation_cam_to_world.T
        return np.concatenate([rotation, (-rotation @ self.centre)[:, None]], axis=1)

    def colmap_camera(self, width: int, height: int) -> pycolmap.Camera:
        """A PINHOLE camera for the photo resized to width x height (x and y scaled separately)."""
        sx, sy = width / self.width, height / self.height
        k = self.K
        return pycolmap.Camera(model="PINHOLE", width=width, height=height,
                               params=[k[0, 0] * sx, k[1, 1] * sy, k[0, 2] * sx, k[1, 2] * sy])


def read_strecha_camera(path: Path) -> StrechaCamera:
    try:
        rows = [line.split() for line in Path(path).read_text().splitlines() if line.strip()]
        values = [[float(v) for v in row] for row in rows]
        K = np.array(values[0:3])
        distortion = np.array(values[3])
        rotation = np.array(values[4:7])
        centre = np.array(values[7])
        width, height = (int(round(v)) for v in values[8][:2])
        if K.shape != (3, 3) or rotation.shape != (3, 3) or centre.shape != (3,):
            raise ValueError("wrong shapes")
    except Exception as error:
        raise CameraFileError(
            f"Camera file {path} is not in the Strecha format (K 3x3, distortion, R 3x3, t, w h; see "
            f"sg_nerfstudio/photos/strecha.py) ({type(error).__name__})."
        ) from None
    if not all(np.isfinite(values).all() for values in (K, distortion, rotation, centre)) or not np.all(K[[0, 1], [0, 1]] > 0):
        raise CameraFileError(f"Camera file {path} holds values that are not finite or focal lengths <= 0; expected a calibrated camera (K, R, t).")
    if np.abs(distortion).max() > 1e-9:
        raise CameraFileError(f"Camera file {path} has non-zero distortion {distortion.tolist()}; expected undistorted images (zeros).")
    if abs(np.linalg.det(rotation) - 1.0) > 1e-3:
        raise CameraFileError(f"Camera file {path} has a rotation with determinant {np.linalg.det(rotation):.4f}; expected a rotation (1).")
    return StrechaCamera(K, rotation, centre, width, height)


def read_strecha_cameras(folder: Path, photo_names: list[str]) -> dict[str, StrechaCamera]:
    """The camera of each photo: `<folder>/<photo name>.camera`."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CameraFileError(f"Camera folder {folder} {not_a_directory(folder)}; expected <photo name>.camera files (Strecha format).")
    missing = [name for name in photo_names if not (folder / f"{name}.camera").is_file()]
    if missing:
        raise CameraFileError(f"Camera folder {folder} has no {missing[0]}.camera ({len(missing)} photo(s) without a camera); expected one per photo.")
    return {name: read_strecha_camera(folder / f"{name}.camera") for name in photo_names}
