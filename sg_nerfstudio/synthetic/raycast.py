"""Exact rendering of the landmark's analytic surfaces by ray casting, with per-pixel procedural patterns.

The generator's photos and reference images are rendered here rather than by splatting the landmark's
Gaussians: a splat can only carry one colour, so at a few tens of thousands of Gaussians every window
edge and stone joint is blurred to the splat size (about half a metre), and SIFT finds almost nothing to
match between photos and reference renders, at any image resolution. Ray casting evaluates each
surface's pattern at the exact point a pixel sees, so detail is limited by the pixels only, as in a
real photo.

Why by hand: the surfaces are a few dozen planar patches (some trimmed by a mask), a disc and a
hemisphere, each with a pattern function of its own (u, v) coordinates in metres. A mesh ray caster
(Open3D, trimesh/embree) would need the patches triangulated and the hits mapped back to (u, v) and
to the pattern; the closed-form intersections are a few lines of numpy each.

Frames: the surfaces live in the generator's metric world frame (metres, z up); shots are in scene
units, `metres_per_unit` converts. Pixels follow COLMAP's convention (centre of the top-left pixel at
(0.5, 0.5)) and rays come from the shot's pycolmap camera, so distorted cameras are rendered exactly.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from sg_nerfstudio.synthetic.building import Surface
from sg_nerfstudio.synthetic.capture import Shot

Array = np.ndarray
Shading = Callable[[Array, Array], Array]
"""(albedo [n, 3], outward normals [n, 3]) -> linear radiance [n, 3]."""


def subpixel_grid(width: int, height: int, samples_per_side: int) -> Array:
    """[height * width * s * s, 2] sample positions (COLMAP pixel convention), s x s stratified per pixel,
    ordered pixel-major (all samples of pixel 0 first)."""
    offsets = (np.arange(samples_per_side) + 0.5) / samples_per_side
    sub_x, sub_y = np.meshgrid(offsets, offsets)
    cols, rows = np.meshgrid(np.arange(width), np.arange(height))
    x = cols.reshape(-1, 1) + sub_x.reshape(1, -1)
    y = rows.reshape(-1, 1) + sub_y.reshape(1, -1)
    return np.stack([x.ravel(), y.ravel()], axis=1)


def world_rays(shot: Shot, pixels: Array, metres_per_unit: float) -> tuple[Array, Array]:
    """Camera centre [3] (metres) and ray directions [n, 3] (world, scaled so that t is the camera-z depth
    in metres) through the given pixel positions [n, 2] of the shot's camera."""
    rays_camera = np.hstack([shot.camera.cam_from_img(pixels), np.ones((len(pixels), 1))])
    rotation = shot.cam_from_world.rotation.matrix()
    centre = -rotation.T @ shot.cam_from_world.translation * metres_per_unit
    return centre, rays_camera @ rotation


def cast(surfaces: list[Surface], centre: Array, rays: Array) -> tuple[Array, Array, Array, Array]:
    """Nearest hit of each ray among the surfaces.

    Returns:
        t [n] (inf where nothing is hit), index of the surface hit [n] (-1 where none), pattern
        coordinates uv [n, 2] and outward normals [n, 3] of the hits (undefined where none).
    """
    n = len(rays)
    t_best, which = np.full(n, np.inf), np.full(n, -1)
    uv, normals = np.zeros((n, 2)), np.zeros((n, 3))
    for index, surface in enumerate(surfaces):
        t, surface_uv, surface_normals = surface.intersect(centre, rays)
        closer = t < t_best
        t_best[closer], which[closer] = t[closer], index
        uv[closer], normals[closer] = surface_uv[closer], surface_normals[closer]
    return t_best, which, uv, normals


def raycast_shot(
    surfaces: list[Surface], shading: Shading, softness: float, shot: Shot, background: Array,
    metres_per_unit: float, samples_per_side: int = 3, texture_coordinates: Callable[[Array, int], Array] | None = None,
) -> tuple[Array, Array]:
    """Render one shot of the surfaces, supersampled s x s per pixel and box-filtered.

    Args:
        shading: turns the patterns' albedo and the surface normals into radiance (flat or sun lighting).
        softness: edge softness of the patterns in metres (sharp for photos, soft for reference renders).
        background: [3] radiance where no surface is hit (sky).
        texture_coordinates: (uv [n, 2], surface index) -> the uv whose pattern is shown (a model's misplaced texture);
            None shows each point's own pattern.

    Returns:
        image [H, W, 3] in [0, 1.5] (linear radiance) and depth [H, W] along the camera's z axis in scene
        units, inf where fewer than half of a pixel's samples hit the landmark.
    """
    width, height, s2 = shot.camera.width, shot.camera.height, samples_per_side**2
    centre, rays = world_rays(shot, subpixel_grid(width, height, samples_per_side), metres_per_unit)
    t, which, uv, normals = cast(surfaces, centre, rays)
    radiance = np.tile(np.asarray(background, np.float64), (len(rays), 1))
    for index, surface in enumerate(surfaces):
        hit = which == index
        if hit.any():
            shown = uv[hit] if texture_coordinates is None else texture_coordinates(uv[hit], index)
            radiance[hit] = shading(surface.pattern(shown, softness), normals[hit])
    image = radiance.reshape(height, width, s2, 3).mean(axis=2)
    t = t.reshape(height, width, s2)
    hits = np.isfinite(t)
    with np.errstate(invalid="ignore", divide="ignore"):
        depth = np.where(hits, t, 0.0).sum(axis=2) / hits.sum(axis=2) / metres_per_unit
    return image, np.where(hits.mean(axis=2) >= 0.5, depth, np.inf)
