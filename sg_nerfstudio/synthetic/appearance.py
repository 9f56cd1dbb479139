"""In-the-wild appearance: lighting of the landmark and per-photo camera/occluder effects.

Reference renders get the scene's `ReferenceLook`: by default flat lighting on the smoothed albedo (the
pseudo-synthetic look); `EARTH_LOOK` adds what separates a Google Earth Studio render from a photo (a baked sun,
washed-out colours, haze, low texture resolution), calibrated on the paper's photo/render pairs
(docs/gap-scenes.md). Each photo of a meta-image gets its own sun, sky, exposure, white balance, gamma, sensor noise, blur and, for some
photos, textured transient occluders (people, vehicles, trees) drawn over part of the frame before the
camera effects.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial

import cv2
import numpy as np

from sg_nerfstudio.synthetic.building import value_noise

Array = np.ndarray


@dataclass
class PhotoLook:
    """Random photometric state of one photo (all drawn from `strength` in [0, 1])."""

    sun_direction: Array  # [3] unit vector towards the sun
    sun_strength: float
    sky: Array  # [3]
    exposure: float
    white_balance: Array  # [3]
    gamma: float
    noise_sigma: float
    blur_sigma: float


def flat_lighting(albedo: Array, normals: Array) -> Array:
    """Pseudo-synthetic shading: near-uniform, a slight darkening of downward-facing surfaces."""
    return np.clip(albedo * (0.92 + 0.08 * normals[:, 2:3]), 0.0, 1.0)


def sun_lighting(albedo: Array, normals: Array, look: PhotoLook) -> Array:
    """Lambertian sun plus sky ambient; both sides of a surface receive light (thin splats)."""
    direct = np.clip(normals @ look.sun_direction, 0.0, 1.0)[:, None]
    ambient = 0.55 + 0.1 * normals[:, 2:3]
    return np.clip(albedo * (ambient + look.sun_strength * direct), 0.0, 1.5)


@dataclass
class ReferenceLook:
    """How the reference model's renders look: the images the reference splat is trained on, and the renders at each
    photo's pose that `generator.py` writes as the scene's photo/render pairs. The defaults are the soft
    pseudo-synthetic look of every scene before gap scenes existed (same pixels)."""

    softness: float = 0.2
    """Edge softness of the patterns in metres (the texture's resolution on the model)."""
    sun_strength: float = 0.0
    """One sun baked into every reference view (0: flat lighting): a render's light is not the photo's."""
    sun_azimuth_deg: float = 135.0
    sun_elevation_deg: float = 35.0
    saturation: float = 1.0
    """Colour saturation of the albedo (1: as the photos', 0: grey)."""
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """Per-channel gain of the render."""
    haze: float = 0.0
    """Aerial haze: the share of a pixel replaced by the haze colour is 1 - exp(-haze * depth in scene units)."""
    haze_colour: tuple[float, float, float] = (0.78, 0.82, 0.86)
    detail_scale: float = 1.0
    """Resolution of the render relative to the image (1: full; 0.5: rendered at half size and scaled back up)."""
    texture_misalignment: float = 0.0
    """Largest displacement (metres) of the model's texture on its surfaces, smooth over MISALIGNMENT_CELL metres:
    a model built from aerial imagery drapes its texture on coarse geometry, so windows and edges sit a little off."""

    def shading(self):
        """The reference's Shading (`raycast.Shading`): flat, or flat plus the baked sun, on the re-coloured albedo."""
        return partial(_reference_shading, look=self)

    def texture_coordinates(self, uv: Array, surface_index: int) -> Array:
        """[n, 2] pattern coordinates (metres) where the model shows what lies at `uv` on surface `surface_index`: the
        same for every view (the error belongs to the model)."""
        if self.texture_misalignment <= 0:
            return uv
        offsets = [2.0 * value_noise(uv, MISALIGNMENT_CELL, 7919 * surface_index + axis) - 1.0 for axis in (1, 2)]
        return uv + self.texture_misalignment * np.stack(offsets, axis=1)

    def finish(self, image: Array, depth: Array) -> Array:
        """Haze, tint and texture resolution on a rendered [H, W, 3] image with its depth [H, W] (inf = sky)."""
        out = np.asarray(image, np.float64)
        if self.haze > 0:
            weight = 1.0 - np.exp(-self.haze * np.where(np.isfinite(depth), depth, 1e3))
            out = out * (1.0 - weight[..., None]) + np.asarray(self.haze_colour) * weight[..., None]
        out = out * np.asarray(self.tint)[None, None]
        if self.detail_scale < 1.0:
            height, width = out.shape[:2]
            small = (max(int(round(width * self.detail_scale)), 1), max(int(round(height * self.detail_scale)), 1))
            out = cv2.resize(cv2.resize(out.astype(np.float32), small, interpolation=cv2.INTER_AREA), (width, height), interpolation=cv2.INTER_LINEAR)
        return np.clip(out, 0.0, 1.0)


MISALIGNMENT_CELL = 6.0
"""Feature size (metres) of the texture misalignment: a storey or two."""


def _reference_shading(albedo: Array, normals: Array, look: ReferenceLook) -> Array:
    if look.saturation != 1.0:
        grey = albedo.mean(axis=1, keepdims=True)
        albedo = grey + look.saturation * (albedo - grey)
    if look.sun_strength <= 0:
        return flat_lighting(albedo, normals)
    elevation, azimuth = np.deg2rad(look.sun_elevation_deg), np.deg2rad(look.sun_azimuth_deg)
    sun = np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
    direct = np.clip(normals @ sun, 0.0, 1.0)[:, None]
    return np.clip(albedo * (0.6 + 0.08 * normals[:, 2:3] + look.sun_strength * direct), 0.0, 1.0)


EARTH_LOOK = ReferenceLook(
    softness=0.6, sun_strength=0.6, saturation=0.6, tint=(0.95, 0.98, 1.04), haze=0.25, detail_scale=0.5,
    texture_misalignment=1.0,
)
"""Google-Earth-like renders: calibrated so that generated photo/render pairs land in the range of the paper's own
pairs (SIFT share and teacher identifiability at the true pose; docs/gap-scenes.md)."""


def random_look(strength: float, rng: np.random.Generator) -> PhotoLook:
    elevation = np.deg2rad(rng.uniform(15, 70))
    azimuth = rng.uniform(0, 2 * np.pi)
    sun = np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
    overcast = rng.random() < 0.3
    sky = np.array([0.55, 0.7, 0.92]) if not overcast else np.array([0.78, 0.8, 0.82])
    sky = np.clip(sky + rng.normal(0, 0.05 * strength, 3), 0, 1)
    return PhotoLook(
        sun_direction=sun,
        sun_strength=(0.15 if overcast else 0.7) * strength,
        sky=sky,
        exposure=float(2.0 ** rng.normal(0.0, 0.5 * strength)),
        white_balance=np.exp(rng.normal(0.0, 0.12 * strength, 3)),
        gamma=float(np.exp(rng.normal(0.0, 0.2 * strength))),
        noise_sigma=0.015 * strength * rng.uniform(0.3, 1.0),
        blur_sigma=1.0 * strength * rng.uniform(0.0, 1.0),
    )


def apply_camera_effects(image: Array, look: PhotoLook, rng: np.random.Generator) -> Array:
    """Exposure, white balance, gamma, blur and noise on a linear [H, W, 3] image in [0, 1]."""
    out = image * look.exposure * look.white_balance[None, None]
    out = np.clip(out, 0.0, 1.0) ** look.gamma
    if look.blur_sigma > 0.3:
        out = cv2.GaussianBlur(out.astype(np.float32), (0, 0), look.blur_sigma)
    out = out + rng.normal(0.0, look.noise_sigma, out.shape)
    return np.clip(out, 0.0, 1.0)


def draw_occluders(image: Array, coverage: float, rng: np.random.Generator) -> tuple[Array, float]:
    """Paint textured people, vehicles and trees over the lower part of the photo until about `coverage`
    of it is hidden.

    Each occluder's colours are modulated by its own texture (clothing stripes, foliage, body panels and
    reflections; `occluder_texture`): real occluders have edges and texture inside, which a gradient- or
    DINO-based descriptor responds to as strongly as to the landmark, whereas flat shapes would leave
    gradient-free areas that such descriptors largely ignore.

    Args:
        image: [H, W, 3] linear radiance (>= 0), before the photo's camera effects (so occluders get the
            same exposure, white balance, blur and noise as the landmark).

    Returns:
        the image and the fraction of pixels actually covered.
    """
    height, width = image.shape[:2]
    canvas = image.astype(np.float64).copy()
    mask = np.zeros((height, width), np.uint8)
    scale = min(width, height)
    for _ in range(40):
        if mask.mean() / 255.0 >= coverage:
            break
        kind = rng.choice(["person", "vehicle", "tree"], p=[0.5, 0.25, 0.25])
        x = int(rng.uniform(0.05, 0.95) * width)
        ground = int(rng.uniform(0.75, 1.05) * height)
        color = tuple(int(c) for c in rng.integers(20, 230, 3))
        layer = np.zeros_like(mask)
        shape = np.zeros((height, width, 3), np.uint8)
        if kind == "person":
            h = int(rng.uniform(0.25, 0.6) * scale)
            w = max(h // 4, 2)
            for target in (shape, layer):
                value = color if target is shape else 255
                cv2.rectangle(target, (x - w // 2, ground - int(0.85 * h)), (x + w // 2, ground), value, -1)
                cv2.circle(target, (x, ground - int(0.92 * h)), max(w // 2, 1), value if target is layer else (200, 160, 130), -1)
            feature_size = max(w / 4, 1.5)
        elif kind == "vehicle":
            h = int(rng.uniform(0.15, 0.3) * scale)
            w = int(h * rng.uniform(1.8, 2.6))
            for target in (shape, layer):
                value = color if target is shape else 255
                cv2.rectangle(target, (x - w // 2, ground - h), (x + w // 2, ground - h // 5), value, -1)
                cv2.rectangle(target, (x - w // 3, ground - int(1.4 * h)), (x + w // 3, ground - h), value, -1)
                if target is shape:  # side windows
                    cv2.rectangle(target, (x - w // 3 + 2, ground - int(1.35 * h)), (x + w // 3 - 2, ground - int(1.05 * h)), (40, 50, 60), -1)
                for wheel in (x - w // 3, x + w // 3):
                    cv2.circle(target, (wheel, ground - h // 5), max(h // 5, 1), 255 if target is layer else (25, 25, 25), -1)
            feature_size = max(h / 6, 1.5)
        else:
            h = int(rng.uniform(0.4, 0.9) * scale)
            trunk = max(h // 12, 2)
            leaf = (int(rng.integers(20, 60)), int(rng.integers(80, 140)), int(rng.integers(20, 60)))
            blobs = [
                (x + int(rng.normal(0, h * 0.15)), ground - h // 2 - int(abs(rng.normal(h * 0.2, h * 0.1))), max(int(h * rng.uniform(0.12, 0.22)), 1))
                for _ in range(6)
            ]
            for target in (shape, layer):
                cv2.rectangle(target, (x - trunk, ground - h // 2), (x + trunk, ground), (70, 50, 35) if target is shape else 255, -1)
                for cx, cy, radius in blobs:
                    cv2.circle(target, (cx, cy), radius, leaf if target is shape else 255, -1)
            feature_size = max(h / 30, 1.0)
        inside = layer > 0
        texture = occluder_texture((height, width), kind, feature_size, rng)
        canvas[inside] = shape[inside] / 255.0 * texture[inside, None]
        mask = np.maximum(mask, layer)
    return canvas, float(mask.mean() / 255.0)


def occluder_texture(shape: tuple[int, int], kind: str, feature_size: float, rng: np.random.Generator) -> Array:
    """[H, W] brightness factor in about [0.35, 1.5] for one occluder.

    People: stripes of a random direction and period (clothing prints) over fine noise; trees: foliage
    speckle (band-limited noise at the leaf size); vehicles: broad body-panel shading plus a few
    reflections. `feature_size` is the texture's characteristic length in pixels.
    """
    height, width = shape

    def noise(length: float) -> Array:
        """Band-limited noise with unit standard deviation and features of about `length` pixels."""
        coarse = rng.normal(size=(max(int(height / length), 2), max(int(width / length), 2))).astype(np.float32)
        field = cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)
        return (field - field.mean()) / max(float(field.std()), 1e-6)

    if kind == "person":
        angle = rng.uniform(0, np.pi)
        period = feature_size * rng.uniform(1.5, 4.0)
        ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
        stripes = np.sign(np.sin(2 * np.pi * (xs * np.cos(angle) + ys * np.sin(angle)) / period))
        factor = 1.0 + 0.3 * stripes + 0.1 * noise(feature_size)
    elif kind == "tree":
        factor = 1.0 + 0.35 * noise(feature_size) + 0.15 * noise(4 * feature_size)
    else:
        factor = 1.0 + 0.2 * noise(8 * feature_size) + 0.25 * np.clip(noise(2 * feature_size) - 1.5, 0, None)
    return np.clip(factor, 0.35, 1.5).astype(np.float32)
