"""A procedural landmark (church-like building on a paved square): analytic surfaces with patterns.

World frame: z up, ground plane z = 0, the main body centred on the origin, its *front* facade facing
-y. Units are metres before the generator rescales the scene (see `generator.py`).

Each `Surface` (planar patches, the ground disc, a dome) can be sampled (points with their (u, v)),
intersected by rays (`raycast.py` renders the photos and reference images this way) and coloured by its
pattern, a function of (u, v) in metres and an edge softness: windows, doors, cornices, stone blocks,
weathering and one-off decals (plaques, signs, plants) that make places distinguishable for SIFT. Soft
edges without the finest texture give the "pseudo-synthetic" look of Google-Earth-like reference renders.

`build_landmark` also gives the landmark as surface-aligned 3D Gaussians (flat discs whose third local
axis is the surface normal): their centres are the candidate points of the synthetic COLMAP models, and
the splats are the realistic test load of the rasterizer benchmark.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Literal

import numpy as np
from scipy.spatial.transform import Rotation

Array = np.ndarray


@dataclass
class BuildingConfig:
    """Shape and detail of the procedural landmark."""

    width: float = 30.0
    """Extent of the main body along x (front facade width), metres."""
    depth: float = 20.0
    """Extent of the main body along y."""
    height: float = 16.0
    """Eave height of the main body."""
    towers: int = 2
    """Square towers at the front corners: 0, 1 or 2."""
    tower_height_ratio: float = 1.8
    """Tower height / body height."""
    roof: Literal["pitched", "dome", "flat"] = "pitched"
    """Roof of the main body."""
    window_rows: int = 3
    """Rows of windows on the long facades (detail)."""
    window_cols: int = 6
    """Columns of windows on the front/rear facades (detail)."""
    ground_radius: float = 55.0
    """Radius of the textured ground disc."""
    ground_density: float = 0.25
    """Gaussians (surface points) per square metre on the ground relative to the building surfaces."""
    n_gaussians: int = 20000
    """Total number of Gaussians of the splat form; their centres are the candidate points of the scene's
    COLMAP point clouds (the images are ray-cast from the surfaces, see raycast.py)."""
    palette_seed: int = 0
    """Seed of the colour palette and pattern jitter."""
    unique_detail: float = 1.0
    """Scales what makes one place of the landmark look unlike another: the rate of one-off decals (`decals`: 1 =
    FACADE_DECAL_RATE of the facade cells, GROUND_DECAL_RATE of the ground's) and the amplitude of the weathering
    (`weathering`). 0 leaves rows of identical windows, told apart only by the tone of single stone blocks where a
    photo is sharp enough to see them: a repetitive facade, where a registration may find a minimum one window away."""


@dataclass
class GaussianScene:
    """Gaussians of the landmark, all [N, ...] numpy float64 arrays in the world frame.

    Attributes:
        means: [N, 3] centres.
        quats: [N, 4] (w, x, y, z) rotations whose third axis is the surface normal.
        scales: [N, 3] standard deviations along the local axes.
        opacities: [N] in (0, 1].
    """

    means: Array
    quats: Array
    scales: Array
    opacities: Array

    def scaled(self, factor: float) -> "GaussianScene":
        """The same scene with all lengths multiplied by `factor` (about the world origin)."""
        return GaussianScene(
            means=self.means * factor, quats=self.quats, scales=self.scales * factor, opacities=self.opacities,
        )


@dataclass
class SurfaceSamples:
    points: Array  # [n, 3]
    normals: Array  # [n, 3]
    tangents: Array  # [n, 3] first in-plane axis
    uv: Array  # [n, 2] pattern coordinates in metres


Pattern = Callable[[Array, float], Array]  # (uv [n, 2], edge softness in metres) -> rgb [n, 3]
Intersect = Callable[[Array, Array], tuple[Array, Array, Array]]
"""(ray origin [3], directions [n, 3]) -> ray parameter t [n] (inf where missed), uv [n, 2], outward normals [n, 3]."""


@dataclass
class Surface:
    """A piece of the landmark: `sample(n, rng)` draws points uniformly over `area`, `intersect` finds
    where rays hit it (same uv as the samples), `pattern` colours it."""

    name: str
    area: float
    sample: Callable[[int, np.random.Generator], SurfaceSamples]
    pattern: Pattern
    intersect: Intersect
    density: float = 1.0


def _smoothstep_inside(signed_distance: Array, softness: float) -> Array:
    """1 inside (negative distance), 0 outside, with a soft edge of width `softness`."""
    return 1.0 / (1.0 + np.exp(np.clip(signed_distance / max(softness, 1e-3), -50, 50)))


def _hash_noise(ij: Array, seed: int) -> Array:
    """Deterministic per-cell noise in [0, 1) for integer cell coordinates [n, 2]."""
    h = (ij[:, 0].astype(np.int64) * 73856093) ^ (ij[:, 1].astype(np.int64) * 19349663) ^ (seed * 83492791)
    return ((h % 1000003) / 1000003.0).astype(np.float64)


def value_noise(uv: Array, cell: float, seed: int) -> Array:
    """Smooth noise in [0, 1) with features of about `cell` metres: hashed lattice values, smoothstep-interpolated."""
    scaled = uv / cell
    corner = np.floor(scaled)
    frac = scaled - corner
    weight = frac * frac * (3 - 2 * frac)
    value = np.zeros(len(uv))
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        w = (weight[:, 0] if dx else 1 - weight[:, 0]) * (weight[:, 1] if dy else 1 - weight[:, 1])
        value += w * _hash_noise(corner + np.array([dx, dy]), seed)
    return value


WEATHERING_OCTAVES = ((4.0, 0.16), (2.0, 0.12), (1.0, 0.1), (0.5, 0.08))
"""(feature size in metres, amplitude) of the weathering of every surface: stains, repairs, moss and
uneven tone that make real stonework unique from place to place (no two windows look the same)."""


def weathering(uv: Array, softness: float, seed: int, strength: float = 1.0) -> Array:
    """[n] brightness factor around 1 from `WEATHERING_OCTAVES`, amplitudes times `strength`; octaves finer than
    `softness` are left out (a soft, pseudo-synthetic render keeps the large stains only)."""
    factor = np.ones(len(uv))
    for octave, (cell, amplitude) in enumerate(WEATHERING_OCTAVES):
        if cell >= softness:
            factor += strength * amplitude * (2 * value_noise(uv, cell, seed * 31 + octave) - 1)
    return factor


DECAL_CELL = 1.6
"""Metres: the decals of a surface sit on a grid of this pitch, at most one per cell."""
FACADE_DECAL_RATE = 0.35
"""Fraction of a facade's decal cells that hold a decal (at `BuildingConfig.unique_detail` 1)."""
GROUND_DECAL_RATE = 0.15
"""Fraction of the ground's decal cells that hold a decal (at `BuildingConfig.unique_detail` 1)."""


def decals(uv: Array, color: Array, softness: float, seed: int, rate: float = FACADE_DECAL_RATE) -> Array:
    """Scatter non-repeating details over a pattern: plaques, signs, lamps, plants, patches of repair.

    Repeated windows and pilasters give SIFT nothing to tell apart; real facades and squares are full of
    one-off details. In a fraction `rate` of the cells of a `DECAL_CELL` grid sits one disc or square of
    its own size (0.3-1.4 m across), position and colour, dark or light, so that it contrasts with
    whatever lies under it.

    Args:
        uv: [n, 2] pattern coordinates in metres; color: [n, 3] the pattern's colour there.

    Returns:
        [n, 3] colours with the decals painted over.
    """
    cell = np.floor(uv / DECAL_CELL)
    draws = [_hash_noise(cell, seed * 7 + k) for k in range(7)]
    present = draws[0] < rate
    radius = 0.15 + draws[1] * (0.45 * DECAL_CELL - 0.15)
    centre = cell * DECAL_CELL + radius[:, None] + np.stack([draws[2], draws[3]], axis=1) * (DECAL_CELL - 2 * radius[:, None])
    offset = uv - centre
    distance = np.where(draws[4] < 0.5, np.hypot(offset[:, 0], offset[:, 1]), np.max(np.abs(offset), axis=1)) - radius
    weight = present * _smoothstep_inside(distance, max(softness, 0.02))
    tone = np.where(draws[5] < 0.5, 0.15 + 0.25 * draws[6], 0.85 + 0.15 * draws[6])
    hue = np.stack([_hash_noise(cell, seed * 7 + 7 + c) for c in range(3)], axis=1)
    decal_color = tone[:, None] * (0.6 + 0.4 * hue)
    return color * (1 - weight[:, None]) + decal_color * weight[:, None]


def _mix(base: Array, color: Array, weight: Array) -> Array:
    return base * (1 - weight[:, None]) + np.asarray(color)[None] * weight[:, None]


@dataclass
class FacadeStyle:
    """Layout of one facade; the differences between sides make front and rear distinguishable."""

    wall: Array
    trim: Array
    glass: Array
    rows: int
    cols: int
    door: bool = False
    rose_window: bool = False
    window_shape: Literal["arched", "tall", "square"] = "arched"
    floors: list[float] = field(default_factory=list)
    unique_detail: float = 1.0
    """`BuildingConfig.unique_detail` for this facade."""


def facade_pattern(width: float, height: float, style: FacadeStyle, seed: int) -> Pattern:
    """Pattern of a facade of size width x height; uv = (along the wall, up the wall) in metres."""

    def pattern(uv: Array, softness: float) -> Array:
        u, v = uv[:, 0], uv[:, 1]
        blocks = np.stack([np.floor(u / 1.2 + 0.5 * (np.floor(v / 0.6) % 2)), np.floor(v / 0.6)], axis=1)
        stone = 0.92 + 0.16 * _hash_noise(blocks, seed) if softness < 0.2 else np.ones_like(u)
        color = style.wall[None] * stone[:, None]
        for level in style.floors:  # cornices
            color = _mix(color, style.trim, _smoothstep_inside(np.abs(v - level * height) - 0.35, softness))
        cell_w, cell_h = width / style.cols, height / max(style.rows + 1, 1)
        col_idx = np.clip(np.floor(u / cell_w), 0, style.cols - 1)
        du = u - (col_idx + 0.5) * cell_w
        pilaster = _smoothstep_inside(np.abs(np.abs(du) - 0.5 * cell_w) - 0.08 * cell_w, softness)
        color = _mix(color, style.trim * 0.95, pilaster)
        for row in range(style.rows):
            vc = (row + 1.0) * cell_h
            half_w = {"arched": 0.2, "tall": 0.13, "square": 0.25}[style.window_shape] * cell_w
            half_h = {"arched": 0.28, "tall": 0.38, "square": 0.22}[style.window_shape] * cell_h
            box = np.maximum(np.abs(du) - half_w, np.abs(v - vc) - half_h)
            if style.window_shape == "arched":
                arch = np.hypot(du, v - (vc + half_h)) - half_w
                box = np.minimum(box, np.where(v > vc + half_h, arch, box))
            inside = _smoothstep_inside(box, softness)
            if style.door and row == 0:
                inside = inside * (np.abs(u - width / 2) > 0.12 * width)
            color = _mix(color, style.glass, inside)
        if style.door:
            du_door, half = u - width / 2, 0.09 * width
            top = 0.3 * height
            door = np.maximum(np.abs(du_door) - half, v - top)
            door = np.minimum(door, np.where(v > top, np.hypot(du_door, v - top) - half, door))
            color = _mix(color, style.trim, _smoothstep_inside(door - 0.6, softness))
            color = _mix(color, np.array([0.18, 0.11, 0.07]), _smoothstep_inside(door, softness))
        if style.rose_window:
            r = np.hypot(u - width / 2, v - 0.72 * height)
            radius = 0.11 * width
            rings = 0.5 + 0.5 * np.cos(r / radius * 4 * np.pi)
            rose = np.array([0.25, 0.2, 0.45])[None] * (0.6 + 0.4 * rings[:, None])
            weight = _smoothstep_inside(r - radius, softness)
            color = color * (1 - weight[:, None]) + rose * weight[:, None]
            color = _mix(color, style.trim, _smoothstep_inside(np.abs(r - radius) - 0.25, softness))
        aged = color * weathering(uv, softness, seed, style.unique_detail)[:, None]
        color = decals(uv, aged, softness, seed, rate=FACADE_DECAL_RATE * style.unique_detail)
        return np.clip(color, 0.0, 1.0)

    return pattern


def ground_pattern(seed: int, body_half_extent: Array, unique_detail: float = 1.0) -> Pattern:
    """Paved square with tiles of varying tone, a path to the front door, grass further out."""

    def pattern(uv: Array, softness: float) -> Array:
        x, y = uv[:, 0], uv[:, 1]
        tiles = np.stack([np.floor(x / 3.0), np.floor(y / 3.0)], axis=1)
        tone = 0.85 + 0.3 * _hash_noise(tiles, seed + 1) if softness < 0.2 else np.ones_like(x)
        paving = np.array([0.62, 0.58, 0.52])[None] * tone[:, None]
        joints = np.minimum(np.abs(x / 3.0 - np.round(x / 3.0)), np.abs(y / 3.0 - np.round(y / 3.0))) * 3.0
        paving = _mix(paving, np.array([0.4, 0.38, 0.35]), _smoothstep_inside(joints - 0.12, softness))
        path = _smoothstep_inside(np.maximum(np.abs(x) - 4.0, y + body_half_extent[1]), softness)
        paving = _mix(paving, np.array([0.72, 0.66, 0.55]), path * (y < 0))
        radius = np.hypot(x, y)
        grass_tone = 0.8 + 0.4 * _hash_noise(np.floor(uv / 1.5), seed + 2) if softness < 0.2 else np.ones_like(x)
        grass = np.array([0.3, 0.45, 0.2])[None] * grass_tone[:, None]
        outer = 1.6 * float(np.max(body_half_extent)) + 6.0
        weight = 1.0 - _smoothstep_inside(radius - outer, max(softness, 0.5))
        color = paving * (1 - weight[:, None]) + grass * weight[:, None]
        aged = color * weathering(uv, softness, seed + 3, unique_detail)[:, None]
        color = decals(uv, aged, softness, seed + 3, rate=GROUND_DECAL_RATE * unique_detail)
        return np.clip(color, 0.0, 1.0)

    return pattern


def plain_pattern(color: Array, stripe_period: float, stripe_color: Array, axis: int, seed: int) -> Pattern:
    """Roof tiles / dome ribs: a base colour with stripes along one pattern axis."""

    def pattern(uv: Array, softness: float) -> Array:
        phase = np.abs(uv[:, axis] / stripe_period - np.round(uv[:, axis] / stripe_period)) * stripe_period
        out = _mix(np.repeat(np.asarray(color)[None], len(uv), 0), stripe_color, _smoothstep_inside(phase - 0.2 * stripe_period, softness))
        if softness < 0.2:
            out = out * (0.9 + 0.2 * _hash_noise(np.floor(uv / 0.8), seed))[:, None]
        return np.clip(out * weathering(uv, softness, seed + 5)[:, None], 0.0, 1.0)

    return pattern


def _stratified_unit_square(n: int, rng: np.random.Generator) -> Array:
    """n points in [0,1]^2, jittered on a near-square grid (even coverage, no clumps)."""
    side = max(int(np.ceil(np.sqrt(n))), 1)
    cells = rng.permutation(side * side)[:n]
    return (np.stack([cells % side, cells // side], axis=1) + rng.random((n, 2))) / side


def planar_patch(
    name: str, origin: Array, u_axis: Array, v_axis: Array, size: tuple[float, float], pattern: Pattern,
    keep: Callable[[Array], Array] | None = None, density: float = 1.0,
) -> Surface:
    """Rectangle origin + a*size[0]*u + b*size[1]*v; `keep(uv)` optionally trims it (gables, pyramids)."""
    origin, u_axis, v_axis = (np.asarray(a, dtype=np.float64) for a in (origin, u_axis, v_axis))
    normal = np.cross(u_axis, v_axis)
    normal /= np.linalg.norm(normal)
    fraction = 1.0
    if keep is not None:  # estimate the kept fraction once for the area
        probe = _stratified_unit_square(4096, np.random.default_rng(0)) * np.asarray(size)
        fraction = float(np.mean(keep(probe)))

    def sample(n: int, rng: np.random.Generator) -> SurfaceSamples:
        uv = np.zeros((0, 2))
        while len(uv) < n:
            cand = _stratified_unit_square(int(n / max(fraction, 0.05)) + 8, rng) * np.asarray(size)
            if keep is not None:
                cand = cand[keep(cand)]
            uv = np.concatenate([uv, cand])
        uv = uv[rng.permutation(len(uv))[:n]]
        points = origin[None] + uv[:, :1] * u_axis[None] + uv[:, 1:] * v_axis[None]
        return SurfaceSamples(points, np.repeat(normal[None], n, 0), np.repeat(u_axis[None], n, 0), uv)

    def intersect(centre: Array, rays: Array) -> tuple[Array, Array, Array]:
        t = _ray_plane(centre, rays, origin, normal)
        relative = centre[None] + np.where(np.isfinite(t), t, 0.0)[:, None] * rays - origin[None]
        uv = np.stack([relative @ u_axis, relative @ v_axis], axis=1)
        hit = np.isfinite(t) & np.all((uv >= 0) & (uv <= np.asarray(size)), axis=1)
        if keep is not None:
            hit[hit] = keep(uv[hit])
        return np.where(hit, t, np.inf), uv, np.repeat(normal[None], len(rays), 0)

    if abs(u_axis @ v_axis) > 1e-9 or abs(np.linalg.norm(u_axis) - 1) > 1e-9 or abs(np.linalg.norm(v_axis) - 1) > 1e-9:
        raise ValueError(f"Surface {name}: the pattern axes must be orthonormal.")
    return Surface(name, size[0] * size[1] * fraction, sample, pattern, intersect, density)


def _ray_plane(centre: Array, rays: Array, origin: Array, normal: Array) -> Array:
    """Ray parameter t [n] where rays [n, 3] from `centre` meet the plane (inf if parallel or behind)."""
    denominator = rays @ normal
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((origin - centre) @ normal) / denominator
    return np.where(np.isfinite(t) & (t > 1e-9), t, np.inf)


def ground_disc(radius: float, pattern: Pattern, density: float) -> Surface:
    def sample(n: int, rng: np.random.Generator) -> SurfaceSamples:
        a = _stratified_unit_square(n, rng)
        r, theta = radius * np.sqrt(a[:, 0]), 2 * np.pi * a[:, 1]
        points = np.stack([r * np.cos(theta), r * np.sin(theta), np.zeros(n)], axis=1)
        normals = np.repeat(np.array([[0.0, 0.0, 1.0]]), n, 0)
        tangents = np.repeat(np.array([[1.0, 0.0, 0.0]]), n, 0)
        return SurfaceSamples(points, normals, tangents, points[:, :2].copy())

    def intersect(centre: Array, rays: Array) -> tuple[Array, Array, Array]:
        up = np.array([0.0, 0.0, 1.0])
        t = _ray_plane(centre, rays, np.zeros(3), up)
        xy = centre[None, :2] + np.where(np.isfinite(t), t, 0.0)[:, None] * rays[:, :2]
        hit = np.isfinite(t) & (np.hypot(xy[:, 0], xy[:, 1]) <= radius)
        return np.where(hit, t, np.inf), xy, np.repeat(up[None], len(rays), 0)

    return Surface("ground", np.pi * radius**2, sample, pattern, intersect, density)


def dome(centre: Array, radius: float, pattern: Pattern) -> Surface:
    centre = np.asarray(centre, dtype=np.float64)

    def sample(n: int, rng: np.random.Generator) -> SurfaceSamples:
        a = _stratified_unit_square(n, rng)
        z, phi = a[:, 0], 2 * np.pi * a[:, 1]  # uniform z gives uniform area on a sphere
        ring = np.sqrt(1 - z**2)
        normals = np.stack([ring * np.cos(phi), ring * np.sin(phi), z], axis=1)
        tangents = np.stack([-np.sin(phi), np.cos(phi), np.zeros(n)], axis=1)
        uv = np.stack([phi * radius, z * radius], axis=1)
        return SurfaceSamples(centre[None] + radius * normals, normals, tangents, uv)

    def intersect(origin: Array, rays: Array) -> tuple[Array, Array, Array]:
        offset = origin - centre
        a, b, c = np.sum(rays * rays, axis=1), 2 * rays @ offset, offset @ offset - radius**2
        discriminant = b * b - 4 * a * c
        root = np.sqrt(np.maximum(discriminant, 0.0))
        t = np.full(len(rays), np.inf)
        for candidate in ((-b + root) / (2 * a), (-b - root) / (2 * a)):  # the nearer valid root wins
            z = offset[2] + candidate * rays[:, 2]
            valid = (discriminant >= 0) & (candidate > 1e-9) & (z >= 0) & (candidate < t)
            t[valid] = candidate[valid]
        normals = (offset[None] + np.where(np.isfinite(t), t, 0.0)[:, None] * rays) / radius
        phi = np.mod(np.arctan2(normals[:, 1], normals[:, 0]), 2 * np.pi)
        return t, np.stack([phi * radius, normals[:, 2] * radius], axis=1), normals

    return Surface("dome", 2 * np.pi * radius**2, sample, pattern, intersect)


def box_walls(
    prefix: str, centre_xy: tuple[float, float], size_xy: tuple[float, float], z0: float, height: float,
    styles: dict[str, FacadeStyle], seed: int,
) -> list[Surface]:
    """Four outward-facing walls of an axis-aligned box; `styles` keyed front/rear/left/right."""
    cx, cy = centre_xy
    hx, hy = size_xy[0] / 2, size_xy[1] / 2
    up = np.array([0.0, 0.0, 1.0])
    walls = {  # origin (bottom-left seen from outside), along-wall axis, wall length
        "front": ([cx - hx, cy - hy, z0], [1.0, 0, 0], 2 * hx),
        "rear": ([cx + hx, cy + hy, z0], [-1.0, 0, 0], 2 * hx),
        "left": ([cx - hx, cy + hy, z0], [0, -1.0, 0], 2 * hy),
        "right": ([cx + hx, cy - hy, z0], [0, 1.0, 0], 2 * hy),
    }
    surfaces = []
    for side, (origin, axis, length) in walls.items():
        pattern = facade_pattern(length, height, styles[side], seed + len(surfaces))
        surfaces.append(planar_patch(f"{prefix}_{side}", np.array(origin), np.array(axis), up, (length, height), pattern))
    return surfaces


def landmark_surfaces(config: BuildingConfig) -> list[Surface]:
    """All surfaces of the landmark described by `config`."""
    rng = np.random.default_rng(config.palette_seed)
    stone = np.array([0.78, 0.72, 0.62]) * (0.85 + 0.3 * rng.random(3))
    trim = np.clip(stone * 1.15 + 0.05, 0, 1)
    glass = np.array([0.12, 0.16, 0.24])
    w, d, h = config.width, config.depth, config.height
    floors = [0.33, 0.66]
    styles = {
        "front": FacadeStyle(stone, trim, glass, rows=2, cols=config.window_cols, door=True, rose_window=True, floors=floors, unique_detail=config.unique_detail),
        "rear": FacadeStyle(stone * 0.95, trim, glass, rows=config.window_rows, cols=max(config.window_cols - 2, 2), window_shape="tall", floors=[0.5], unique_detail=config.unique_detail),
        "left": FacadeStyle(stone, trim, glass, rows=config.window_rows, cols=max(int(config.window_cols * d / w), 2), floors=floors, unique_detail=config.unique_detail),
        "right": FacadeStyle(stone * 1.03, trim, glass, rows=config.window_rows, cols=max(int(config.window_cols * d / w), 2), window_shape="square", floors=floors, unique_detail=config.unique_detail),
    }
    surfaces = box_walls("body", (0.0, 0.0), (w, d), 0.0, h, styles, config.palette_seed)
    ground = ground_pattern(config.palette_seed, np.array([w / 2, d / 2]), config.unique_detail)
    surfaces.append(ground_disc(config.ground_radius, ground, config.ground_density))
    roof_color, roof_stripe = np.array([0.45, 0.22, 0.16]), np.array([0.32, 0.15, 0.11])
    surfaces += _roof(config, roof_color, roof_stripe, stone, trim)
    surfaces += _towers(config, stone, trim, glass, roof_color)
    return surfaces


def _roof(config: BuildingConfig, roof_color: Array, roof_stripe: Array, stone: Array, trim: Array) -> list[Surface]:
    w, d, h, seed = config.width, config.depth, config.height, config.palette_seed
    if config.roof == "flat":
        return [planar_patch("roof", [-w / 2, -d / 2, h], [1.0, 0, 0], [0, 1.0, 0], (w, d), plain_pattern(roof_color, 1.0, roof_stripe, 0, seed))]
    if config.roof == "dome":
        flat = planar_patch("roof", [-w / 2, -d / 2, h], [1.0, 0, 0], [0, 1.0, 0], (w, d), plain_pattern(stone * 0.9, 2.0, trim, 0, seed))
        radius = 0.42 * min(w, d)
        ribs = plain_pattern(np.array([0.35, 0.5, 0.48]), radius * np.pi / 8, np.array([0.75, 0.7, 0.55]), 0, seed)
        return [flat, dome([0.0, 0.0, h], radius, ribs)]
    # pitched: ridge along y at x = 0, rising by half the width * 0.6
    rise = 0.3 * w
    slope = np.hypot(w / 2, rise)
    tiles = plain_pattern(roof_color, 0.9, roof_stripe, 1, seed)
    left = planar_patch("roof_left", [-w / 2, d / 2, h], [0, -1.0, 0], [w / 2 / slope, 0, rise / slope], (d, slope), tiles)
    right = planar_patch("roof_right", [w / 2, -d / 2, h], [0, 1.0, 0], [-w / 2 / slope, 0, rise / slope], (d, slope), tiles)
    gable_style = FacadeStyle(stone, trim, np.array([0.12, 0.16, 0.24]), rows=1, cols=1, window_shape="tall", unique_detail=config.unique_detail)

    def triangle(uv: Array) -> Array:
        return uv[:, 1] <= rise * (1 - np.abs(uv[:, 0] - w / 2) / (w / 2))

    front = planar_patch("gable_front", [-w / 2, -d / 2, h], [1.0, 0, 0], [0, 0, 1.0], (w, rise), facade_pattern(w, rise, gable_style, seed + 11), keep=triangle)
    rear = planar_patch("gable_rear", [w / 2, d / 2, h], [-1.0, 0, 0], [0, 0, 1.0], (w, rise), facade_pattern(w, rise, gable_style, seed + 12), keep=triangle)
    return [left, right, front, rear]


def _towers(config: BuildingConfig, stone: Array, trim: Array, glass: Array, roof_color: Array) -> list[Surface]:
    w, d, h = config.width, config.depth, config.height
    side = 0.22 * w
    tower_h = config.tower_height_ratio * h
    surfaces: list[Surface] = []
    for index in range(min(config.towers, 2)):
        cx = (-1 if index == 0 else 1) * (w / 2 - side / 2)
        cy = -d / 2 - side / 2 + 0.3 * side  # protrudes from the front
        style = FacadeStyle(stone * 1.02, trim, glass, rows=4, cols=1, window_shape="tall", floors=[0.25, 0.5, 0.75], unique_detail=config.unique_detail)
        surfaces += box_walls(f"tower{index}", (cx, cy), (side, side), 0.0, tower_h, {k: style for k in ("front", "rear", "left", "right")}, config.palette_seed + 20 + index)
        spire_h = 0.6 * side
        slant = np.hypot(side / 2, spire_h)
        pattern = plain_pattern(roof_color * 0.8, 0.7, roof_color * 0.6, 1, config.palette_seed)

        def pyramid_face(uv: Array, _s=side, _slant=slant) -> Array:
            return np.abs(uv[:, 0] - _s / 2) <= (_s / 2) * (1 - uv[:, 1] / _slant)

        corners = [
            ([cx - side / 2, cy - side / 2, tower_h], [1.0, 0, 0], [0, side / 2 / slant, spire_h / slant]),
            ([cx + side / 2, cy + side / 2, tower_h], [-1.0, 0, 0], [0, -side / 2 / slant, spire_h / slant]),
            ([cx - side / 2, cy + side / 2, tower_h], [0, -1.0, 0], [side / 2 / slant, 0, spire_h / slant]),
            ([cx + side / 2, cy - side / 2, tower_h], [0, 1.0, 0], [-side / 2 / slant, 0, spire_h / slant]),
        ]
        for k, (origin, u_axis, v_axis) in enumerate(corners):
            surfaces.append(planar_patch(f"tower{index}_spire{k}", origin, u_axis, v_axis, (side, slant), pattern, keep=pyramid_face))
    return surfaces


def rotation_to_quat(rot: Array) -> Array:
    """(w, x, y, z) quaternions of rotation matrices [n, 3, 3]."""
    return Rotation.from_matrix(rot).as_quat(scalar_first=True)


def build_landmark(config: BuildingConfig, seed: int) -> GaussianScene:
    """Sample `config.n_gaussians` surface Gaussians over the landmark (density-weighted by area)."""
    rng = np.random.default_rng(seed)
    surfaces = landmark_surfaces(config)
    weights = np.array([s.area * s.density for s in surfaces])
    counts = np.floor(weights / weights.sum() * config.n_gaussians).astype(int)
    counts[np.argmax(weights)] += config.n_gaussians - counts.sum()
    parts = []
    for surface, count in zip(surfaces, counts):
        if count == 0:
            continue
        samples = surface.sample(int(count), rng)
        spacing = np.sqrt(surface.area / count)
        bitangent = np.cross(samples.normals, samples.tangents)
        rot = np.stack([samples.tangents, bitangent, samples.normals], axis=2)  # columns: local axes
        tangent_sigma = 0.55 * spacing * np.exp(rng.normal(0.0, 0.15, (count, 2)))
        scales = np.concatenate([tangent_sigma, 0.08 * tangent_sigma.mean(1, keepdims=True)], axis=1)
        parts.append(dict(
            means=samples.points, quats=rotation_to_quat(rot), scales=scales,
            opacities=np.full(count, 0.97),
        ))
    return GaussianScene(**{key: np.concatenate([p[key] for p in parts]) for key in parts[0]})
