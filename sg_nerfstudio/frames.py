"""Camera-frame conventions in one place.

- nerfstudio `Cameras.camera_to_worlds` [C, 3, 4]: OpenGL camera axes (x right, y up, z back), in the
  dataparser frame.
- gsplat / our rasterizer `viewmats` [C, 4, 4]: world-to-camera, OpenCV axes (x right, y down, z forward).
- COLMAP `cam_from_world`: world-to-camera, OpenCV axes (same as viewmats, 3x4).
"""

from __future__ import annotations

import torch
from torch import Tensor

_OPENGL_TO_OPENCV = torch.tensor([1.0, -1.0, -1.0])


def viewmats_from_camera_to_worlds(camera_to_worlds: Tensor) -> Tensor:
    """OpenCV world-to-camera matrices [C, 4, 4] from nerfstudio OpenGL camera-to-world [C, 3, 4].

    Differentiable (registration optimises the pose through it); the inverse is analytic.
    """
    rotation = camera_to_worlds[:, :3, :3] * _OPENGL_TO_OPENCV.to(camera_to_worlds)[None, None, :]
    translation = camera_to_worlds[:, :3, 3:4]
    rotation_inv = rotation.transpose(1, 2)
    top = torch.cat([rotation_inv, -rotation_inv @ translation], dim=2)  # [C, 3, 4]
    bottom = torch.zeros_like(top[:, :1, :])
    bottom[:, 0, 3] = 1.0
    return torch.cat([top, bottom], dim=1)
