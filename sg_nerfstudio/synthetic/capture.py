"""Camera rigs of the synthetic captures (rendered by `raycast.py`).

Poses are COLMAP-style `cam_from_world` rigid transforms (OpenCV camera: x right, y down, z forward)
held as pycolmap objects; intrinsics are pycolmap cameras, possibly with radial distortion, which the
ray caster follows exactly (each pixel's ray comes from `camera.cam_from_img`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

Array = np.ndarray


@dataclass
class Shot:
    """One image to render: its COLMAP camera and pose in the world frame of the scene."""

    name: str
    camera: pycolmap.Camera
    cam_from_world: pycolmap.Rigid3d


def look_at(eye: Array, target: Array, roll_deg: float = 0.0) -> pycolmap.Rigid3d:
    """cam_from_world of an OpenCV camera at `eye` looking at `target`, z-up world, optional roll."""
    forward = np.asarray(target, float) - np.asarray(eye, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-6:  # looking straight down/up
        right = np.array([1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rot = np.stack([right, down, forward])  # rows: camera axes in world coordinates
    roll = np.deg2rad(roll_deg)
    roll_rot = np.array([[np.cos(roll), -np.sin(roll), 0], [np.sin(roll), np.cos(roll), 0], [0, 0, 1]])
    rot = roll_rot @ rot
    return pycolmap.Rigid3d(pycolmap.Rotation3d(rot), -rot @ np.asarray(eye, float))


def pinhole_camera(camera_id: int, width: int, height: int, fov_x_deg: float, k1: float = 0.0) -> pycolmap.Camera:
    """A PINHOLE camera, or SIMPLE_RADIAL when k1 != 0, with the given horizontal field of view."""
    focal = 0.5 * width / np.tan(np.deg2rad(fov_x_deg) / 2)
    if k1 == 0.0:
        return pycolmap.Camera(model="PINHOLE", width=width, height=height, params=[focal, focal, width / 2, height / 2], camera_id=camera_id)
    return pycolmap.Camera(model="SIMPLE_RADIAL", width=width, height=height, params=[focal, width / 2, height / 2, k1], camera_id=camera_id)


def reference_shots(
    n_ring: int, n_aerial: int, ring_radius: float, ring_height: float, aerial_elevation_deg: float,
    target: Array, width: int, height: int, fov_x_deg: float, rng: np.random.Generator,
) -> list[Shot]:
    """Full coverage like a Google-Earth-Studio capture: a ground ring plus an aerial orbit, all one camera model."""
    shots = []
    for i in range(n_ring):
        azimuth = 2 * np.pi * i / n_ring + rng.uniform(-0.02, 0.02)
        eye = np.array([ring_radius * np.cos(azimuth), ring_radius * np.sin(azimuth), ring_height])
        shots.append(Shot(f"ring_{i:03d}.png", pinhole_camera(1, width, height, fov_x_deg), look_at(eye, target)))
    aerial_radius = 1.5 * ring_radius
    for i in range(n_aerial):
        azimuth = 2 * np.pi * (i + 0.5) / n_aerial
        elevation = np.deg2rad(aerial_elevation_deg + 10.0 * ((i % 3) - 1))
        eye = aerial_radius * np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
        shots.append(Shot(f"aerial_{i:03d}.png", pinhole_camera(1, width, height, fov_x_deg), look_at(eye, target * 0.5)))
    return shots


SIDE_AZIMUTH_DEG = {"front": -90.0, "right": 0.0, "rear": 90.0, "left": 180.0}


def meta_image_shots(
    side: str, n_photos: int, ring_radius: float, eye_height: float, facade_size: tuple[float, float],
    base_size: tuple[int, int], distortion: float, rng: np.random.Generator, name_prefix: str,
    distance_range: tuple[float, float] = (0.65, 1.25),
) -> list[Shot]:
    """Tourist photos of one side: ground-level viewpoints within +-40 deg of the facade normal, each
    with its own focal length, image size and orientation (landscape/portrait), some with radial distortion, at
    `distance_range` ring radii from the landmark's centre."""
    shots = []
    facade_width, facade_height = facade_size
    base_w, base_h = base_size
    sizes = [(base_w, base_h), (base_h, base_w), (int(base_w * 1.1) // 2 * 2, int(base_h * 1.1) // 2 * 2), (int(base_w * 0.9) // 2 * 2, int(base_h * 0.9) // 2 * 2)]
    side_azimuth = np.deg2rad(SIDE_AZIMUTH_DEG[side])
    for i in range(n_photos):
        azimuth = side_azimuth + np.deg2rad(rng.uniform(-40, 40))
        distance = ring_radius * rng.uniform(*distance_range)
        eye = np.array([distance * np.cos(azimuth), distance * np.sin(azimuth), eye_height * rng.uniform(0.7, 1.3)])
        along = np.array([-np.sin(side_azimuth), np.cos(side_azimuth), 0.0])
        target = along * rng.uniform(-0.25, 0.25) * facade_width + np.array([0, 0, rng.uniform(0.25, 0.6) * facade_height])
        width, height = sizes[rng.integers(len(sizes))]
        k1 = rng.uniform(-distortion, distortion) if rng.random() < 0.5 else 0.0
        camera = pinhole_camera(i + 1, width, height, rng.uniform(45, 72), k1=k1)
        shots.append(Shot(f"{name_prefix}_{i:03d}.png", camera, look_at(eye, target, roll_deg=rng.normal(0, 2.0))))
    return shots
