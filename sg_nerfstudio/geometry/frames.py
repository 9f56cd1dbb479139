"""Camera-frame conventions in one place.

- COLMAP `cam_from_world` [3, 4]: world-to-camera, OpenCV axes (x right, y down, z forward). Every pose
  of ours is held this way; `Sim3.move_camera` moves one between frames.
- gsplat / our rasterizer `viewmats` [C, 4, 4]: the same, as homogeneous matrices (`viewmat`).
- nerfstudio `Cameras.camera_to_worlds` [C, 3, 4]: camera-to-world, OpenGL axes (x right, y up, z back),
  in the dataparser frame. Converted only at nerfstudio's border (`opengl_camera_to_world`,
  `viewmats_from_camera_to_worlds`).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

Array = np.ndarray
_OPENGL_TO_OPENCV = torch.tensor([1.0, -1.0, -1.0])


def viewmat(cam_from_world: Tensor) -> Tensor:
    """[4, 4] homogeneous world-to-camera from [3, 4] (same dtype; differentiable)."""
    bottom = torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=cam_from_world.dtype, device=cam_from_world.device)
    return torch.cat([cam_from_world, bottom], dim=0)


def camera_to_world(cam_from_world: Array) -> Array:
    """[3, 4] OpenCV camera-to-world (rotation and centre) of an OpenCV world-to-camera [3, 4]."""
    rotation = cam_from_world[:, :3].T
    return np.concatenate([rotation, (-rotation @ cam_from_world[:, 3])[:, None]], axis=1)


def opengl_camera_to_world(cam_from_world: Array) -> Array:
    """[3, 4] nerfstudio `Cameras.camera_to_worlds` (OpenGL axes) of an OpenCV world-to-camera [3, 4]."""
    pose = camera_to_world(cam_from_world)
    pose[:, :3] = pose[:, :3] * np.array([1.0, -1.0, -1.0])[None, :]
    return pose


def viewmats_from_camera_to_worlds(camera_to_worlds: Tensor) -> Tensor:
    """OpenCV world-to-camera matrices [C, 4, 4] from nerfstudio OpenGL camera-to-world [C, 3, 4].

    Differentiable (the model renders nerfstudio's cameras through it); the inverse is analytic.
    """
    rotation = camera_to_worlds[:, :3, :3] * _OPENGL_TO_OPENCV.to(camera_to_worlds)[None, None, :]
    translation = camera_to_worlds[:, :3, 3:4]
    rotation_inv = rotation.transpose(1, 2)
    top = torch.cat([rotation_inv, -rotation_inv @ translation], dim=2)  # [C, 3, 4]
    bottom = torch.zeros_like(top[:, :1, :])
    bottom[:, 0, 3] = 1.0
    return torch.cat([top, bottom], dim=1)
