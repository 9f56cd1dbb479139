"""Similarity transforms (Sim(3)): one value type, and the one function that moves a camera by it.

A `Sim3` maps x -> s R x + t and is held as its 4x4 matrix [[s R, t], [0, 1]] (float64). Registration
estimates `T: meta-image frame -> reference world`; the reference's `world -> dataparser` frame change
(dataparser_transforms.json) is a Sim3 too, so every frame change composes with `@`.

The matrix is a numpy array for I/O and a float64 torch tensor inside the optimiser (`Sim3.to_torch()`,
differentiable); every method works on both. `scale` may be carried along explicitly (the optimiser knows
it exactly as exp(log s) * s0) instead of being recovered from the determinant.

Cameras are COLMAP / OpenCV world-to-camera matrices `cam_from_world` [3, 4] (x right, y down, z
forward). A camera with centre C and camera-to-world rotation R_c, moved by T, has centre s R C + t and
camera-to-world rotation R R_c; intrinsics are unchanged (`move_camera`).

During optimisation the transform is `U(delta) o T0` (`Sim3.update`), where delta = (omega, nu, log s) in
R^7 acts about a fixed centre c (the centroid of the meta-image cameras under T0, optimisation frame):

    U(delta) x = exp(log s) R(omega) (x - c) + c + nu,     R(omega) = exp([omega]_x)

so rotation and translation are decoupled (no lever arm through a far-away origin) and delta = 0 is the
identity.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Union

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from torch import Tensor

from sg_nerfstudio.errors import InputError

Array = np.ndarray
Matrix = Union[Array, Tensor]
CONVENTION = "x_reference = scale * R @ x_meta + translation"


class TransformFileError(InputError):
    """A transform file (init, ground truth) that does not hold a similarity."""


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


def _cat(parts: list[Matrix], axis: int) -> Matrix:
    return torch.cat(parts, dim=axis) if isinstance(parts[0], Tensor) else np.concatenate(parts, axis=axis)


def _last_row(like: Matrix) -> Matrix:
    if isinstance(like, Tensor):
        return torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=like.dtype, device=like.device)
    return np.array([[0.0, 0.0, 0.0, 1.0]], dtype=like.dtype)


@dataclass(frozen=True, eq=False)
class Sim3:
    """x -> scale * rotation @ x + translation, as the 4x4 `matrix` (numpy or torch float64).

    Build one with `Sim3.from_matrix` (checked), `Sim3.from_parts`, `Sim3.identity()`, `Sim3.read_json`.
    """

    matrix: Matrix
    known_scale: Optional[Union[float, Tensor]] = None
    """The scale when the caller knows it exactly (the optimiser); else it is the cube root of det(linear)."""

    # ------------------------------------------------------------------------------------ construction

    @classmethod
    def from_matrix(cls, matrix) -> "Sim3":
        """A checked Sim3 from a 4x4 matrix (list or array); raises ValueError if it is not a similarity."""
        matrix = np.array(matrix, dtype=np.float64)
        decompose(matrix)
        return cls(matrix)

    @classmethod
    def from_parts(cls, scale: float, rotation: Array, translation: Array) -> "Sim3":
        matrix = np.eye(4)
        matrix[:3, :3] = scale * np.asarray(rotation, dtype=np.float64)
        matrix[:3, 3] = np.asarray(translation, dtype=np.float64)
        return cls(matrix)

    @classmethod
    def identity(cls) -> "Sim3":
        return cls(np.eye(4))

    @classmethod
    def translation_by(cls, offset: Array) -> "Sim3":
        return cls.from_parts(1.0, np.eye(3), offset)

    @classmethod
    def scaling_about(cls, factor: float, centre: Array) -> "Sim3":
        """A scaling by `factor` that keeps `centre` [3] where it is."""
        return cls.from_parts(float(factor), np.eye(3), np.zeros(3)).about(centre)

    @classmethod
    def random(cls, rng: np.random.Generator, rotation_deg: float, translation: float, scale_fraction: float) -> "Sim3":
        """A Sim(3) with exactly these magnitudes in random directions: rotation by `rotation_deg` about a
        random axis, translation of length `translation`, scale 1 +- scale_fraction (random sign)."""
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        scale = 1.0 + scale_fraction * (1 if rng.random() < 0.5 else -1)
        rotation = Rotation.from_rotvec(axis * math.radians(rotation_deg)).as_matrix()
        return cls.from_parts(scale, rotation, direction * translation)

    @classmethod
    def update(cls, delta: Tensor, centre: Tensor) -> "Sim3":
        """U(delta) about `centre` [3] (see the module docstring); differentiable in delta [7] (float64)."""
        rotation = torch.linalg.matrix_exp(_skew(delta[:3]))
        scale = torch.exp(delta[6])
        linear = scale * rotation
        translation = centre + delta[3:6] - linear @ centre
        top = torch.cat([linear, translation[:, None]], dim=1)
        return cls(torch.cat([top, _last_row(top)], dim=0), scale)

    @classmethod
    def read_json(cls, path: Path, what: str) -> "Sim3":
        """The "matrix" of a JSON file (transform.json / gt_transform.json format, or a bare 4x4 list).

        Raises TransformFileError naming `what` and `path` when it is missing, unreadable or not a similarity."""
        path = Path(path)
        if not path.is_file():
            raise TransformFileError(f"{what} {path} does not exist; expected a JSON file with a 4x4 \"matrix\".")
        try:
            record = json.loads(path.read_text())
            matrix = np.asarray(record["matrix"] if isinstance(record, dict) else record, dtype=np.float64)
        except Exception as error:
            raise TransformFileError(f"{what} {path} is not JSON with a 4x4 \"matrix\" ({type(error).__name__}).") from None
        try:
            return cls.from_matrix(matrix)
        except ValueError as error:
            raise TransformFileError(f"{what} {path} is not a valid similarity transform: {error}.") from None

    # ------------------------------------------------------------------------------------ parts

    @property
    def linear(self) -> Matrix:
        """[3, 3] scale * rotation."""
        return self.matrix[:3, :3]

    @property
    def translation(self) -> Matrix:
        """[3]"""
        return self.matrix[:3, 3]

    @property
    def scale(self) -> Union[float, Tensor]:
        if self.known_scale is not None:
            return self.known_scale
        if isinstance(self.matrix, Tensor):
            return torch.linalg.det(self.linear).abs() ** (1.0 / 3.0)
        return decompose(self.matrix)[0]

    @property
    def rotation(self) -> Matrix:
        """[3, 3]"""
        return self.linear / self.scale

    def quaternion_wxyz(self) -> list[float]:
        return [float(v) for v in Rotation.from_matrix(np.asarray(self.rotation)).as_quat(scalar_first=True)]

    def rotation_angle_deg(self) -> float:
        """Geodesic angle of the rotation part, degrees."""
        return rotation_angle_deg(np.asarray(self.rotation))

    # ------------------------------------------------------------------------------------ algebra

    def __matmul__(self, other: "Sim3") -> "Sim3":
        """Composition: (self @ other)(x) = self(other(x))."""
        if not isinstance(other, Sim3):
            return NotImplemented
        scale = None
        if self.known_scale is not None and other.known_scale is not None:
            scale = self.known_scale * other.known_scale
        return Sim3(self.matrix @ other.matrix, scale)

    def inverse(self) -> "Sim3":
        scale, rotation, translation = decompose(np.asarray(self.matrix))
        return Sim3.from_parts(1.0 / scale, rotation.T, -(rotation.T @ translation) / scale)

    def about(self, centre: Array) -> "Sim3":
        """This transform applied about `centre` [3] instead of the origin: T(c) o self o T(-c)."""
        return Sim3.translation_by(centre) @ self @ Sim3.translation_by(-np.asarray(centre))

    def apply(self, points: Matrix) -> Matrix:
        """[..., 3] points -> [..., 3] moved points."""
        return points @ self.linear.T + self.translation

    def move_camera(self, cam_from_world: Matrix) -> Matrix:
        """[3, 4] OpenCV world-to-camera of a camera moved by this transform (same type and dtype as the input).

        Differentiable through a torch matrix (the registration's pose gradient flows through here)."""
        rotation_cw = cam_from_world[:, :3]
        centre = -rotation_cw.T @ cam_from_world[:, 3]
        new_centre = self.linear @ centre + self.translation
        new_rotation_cw = rotation_cw @ (self.linear / self.scale).T
        return _cat([new_rotation_cw, (-new_rotation_cw @ new_centre)[:, None]], axis=1)

    # ------------------------------------------------------------------------------------ conversion

    def to_torch(self) -> "Sim3":
        """The same transform as a float64 torch matrix, with its scale known."""
        return Sim3(torch.from_numpy(np.asarray(self.matrix, dtype=np.float64)), torch.tensor(self.scale, dtype=torch.float64))

    def numpy(self) -> "Sim3":
        """The same transform as a detached float64 numpy matrix."""
        matrix = self.matrix.detach().cpu().numpy() if isinstance(self.matrix, Tensor) else self.matrix
        return Sim3(np.array(matrix, dtype=np.float64))

    def __array__(self, dtype=None, copy=None):
        return np.asarray(self.numpy().matrix, dtype=dtype)

    def as_record(self) -> dict:
        """JSON record: convention, matrix, scale, rotation_wxyz, translation (transform.json's format)."""
        scale, _, translation = decompose(np.asarray(self))
        return {
            "convention": CONVENTION,
            "matrix": np.asarray(self).tolist(),
            "scale": scale,
            "rotation_wxyz": self.quaternion_wxyz(),
            "translation": translation.tolist(),
        }

    def __repr__(self) -> str:
        scale, rotation, translation = decompose(np.asarray(self))
        return f"Sim3(scale={scale:.6g}, rotation={rotation_angle_deg(rotation):.4g} deg, translation={np.round(translation, 6).tolist()})"


def rotation_angle_deg(rotation: Array) -> float:
    """Geodesic angle of a rotation matrix, degrees."""
    cos = (np.trace(rotation) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def perturbed(truth: Sim3, centres: Array, rng: np.random.Generator, rotation_deg: float, translation: float, scale_fraction: float) -> Sim3:
    """`truth` followed by a random Sim3 of exactly these magnitudes applied about the centroid of the cameras
    `centres` [P, 3] (meta frame) under `truth`: the benchmarks' and the demo's perturbed start."""
    noise = Sim3.random(rng, rotation_deg, translation, scale_fraction)
    return noise.about(truth.apply(centres.mean(0))) @ truth


def _skew(omega: Tensor) -> Tensor:
    zero = torch.zeros_like(omega[0])
    return torch.stack([
        torch.stack([zero, -omega[2], omega[1]]),
        torch.stack([omega[2], zero, -omega[0]]),
        torch.stack([-omega[1], omega[0], zero]),
    ])
