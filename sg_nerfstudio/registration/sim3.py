"""Similarity transforms (Sim(3)) and the registration's 7-parameter update.

A Sim(3) `T` is held as a 4x4 matrix [[s R, t], [0, 1]] (float64 numpy for I/O, torch inside the
optimiser) and maps x -> s R x + t. Registration estimates `T: meta-image frame -> reference world`.

During optimisation the transform is `U(delta) o T0`, where `delta = (omega, nu, log s)` in R^7 acts about
a fixed centre c (the centroid of the meta-image cameras under T0, in the optimisation frame):

    U(delta) x = exp(log s) R(omega) (x - c) + c + nu,     R(omega) = exp([omega]_x)

so rotation and translation are decoupled (no lever arm through a far-away origin) and delta = 0 is the
identity.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from torch import Tensor

Array = np.ndarray


def sim3_matrix(scale: float, rotation: Array, translation: Array) -> Array:
    """[4, 4] matrix of x -> scale * rotation @ x + translation."""
    matrix = np.eye(4)
    matrix[:3, :3] = scale * np.asarray(rotation, dtype=np.float64)
    matrix[:3, 3] = np.asarray(translation, dtype=np.float64)
    return matrix


def decompose(matrix: Array) -> tuple[float, Array, Array]:
    """(scale, rotation [3, 3], translation [3]) of a Sim(3) matrix; raises ValueError if it is not one."""
    matrix = np.asarray(matrix, dtype=np.float64)
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise ValueError("expected a finite 4x4 matrix")
    if not np.allclose(matrix[3], [0, 0, 0, 1], atol=1e-9):
        raise ValueError("the last row must be [0, 0, 0, 1]")
    linear = matrix[:3, :3]
    det = np.linalg.det(linear)
    if det <= 0:
        raise ValueError("the scale must be positive (determinant of the 3x3 block is not > 0)")
    scale = float(np.cbrt(det))
    rotation = linear / scale
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-5):
        raise ValueError("the 3x3 block is not a scaled rotation")
    return scale, rotation, matrix[:3, 3].copy()


def invert(matrix: Array) -> Array:
    scale, rotation, translation = decompose(matrix)
    return sim3_matrix(1.0 / scale, rotation.T, -(rotation.T @ translation) / scale)


def quaternion_wxyz(rotation: Array) -> list[float]:
    return [float(v) for v in Rotation.from_matrix(rotation).as_quat(scalar_first=True)]


def rotation_angle_deg(rotation: Array) -> float:
    """Geodesic angle of a rotation matrix, degrees."""
    cos = (np.trace(rotation) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def skew(omega: Tensor) -> Tensor:
    zero = torch.zeros_like(omega[0])
    return torch.stack([
        torch.stack([zero, -omega[2], omega[1]]),
        torch.stack([omega[2], zero, -omega[0]]),
        torch.stack([-omega[1], omega[0], zero]),
    ])


def update_matrix(delta: Tensor, centre: Tensor) -> Tensor:
    """[4, 4] matrix of U(delta) about `centre` (see module docstring); differentiable in delta [7]."""
    rotation = torch.linalg.matrix_exp(skew(delta[:3]))
    linear = torch.exp(delta[6]) * rotation
    translation = centre + delta[3:6] - linear @ centre
    top = torch.cat([linear, translation[:, None]], dim=1)
    bottom = torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=delta.dtype)
    return torch.cat([top, bottom], dim=0)


def perturbation(rng: np.random.Generator, rotation_deg: float, translation: float, scale_fraction: float) -> Array:
    """A Sim(3) with exactly these magnitudes in random directions: rotation by `rotation_deg` about a
    random axis, translation of length `translation`, scale 1 +- scale_fraction (random sign)."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    scale = 1.0 + scale_fraction * (1 if rng.random() < 0.5 else -1)
    rotation = Rotation.from_rotvec(axis * math.radians(rotation_deg)).as_matrix()
    return sim3_matrix(scale, rotation, direction * translation)


def about_point(transform: Array, centre: Array) -> Array:
    """The Sim(3) `transform` applied about `centre` instead of the origin: T(c) o transform o T(-c)."""
    return sim3_matrix(1.0, np.eye(3), centre) @ transform @ sim3_matrix(1.0, np.eye(3), -np.asarray(centre))
