"""Synthetic landmark scenes with exact ground truth: a reference capture and in-the-wild meta-images.

Output layout (written atomically: a temporary sibling directory renamed into place at the end):

    <scene>/scene.json                      settings, scene unit, per-photo ground truth
    <scene>/reference/images/*.png          pseudo-synthetic renders (full coverage)
    <scene>/reference/colmap/sparse/0/      COLMAP model, nerfstudio's default layout:
                                            `ns-train ... colmap --data <scene>/reference` works as is
    <scene>/meta/<name>/images/*.png        in-the-wild photos of one side
    <scene>/meta/<name>/sparse/0/           COLMAP model in the meta-image's own frame (random Sim(3))
    <scene>/meta/<name>/gt_transform.json   Sim(3) meta -> reference: x_ref = scale * R @ x_meta + t
    <scene>/pairs/<name>/photos|renders/    each photo and the reference's look rendered at its true pose: the
                                            layout `sg-bench teacher` reads; scene.json's "gap" measures them

Scene unit: the reference world is scaled so that the median distance of the reference cameras to their
centroid is 1; errors (e.g. a registration's translation error) are stated in that unit.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import pycolmap
from rich.progress import Progress

from sg_nerfstudio.atomic import atomic_directory, check_new_output_directory
from sg_nerfstudio.errors import InputError, range_problem
from sg_nerfstudio.synthetic.appearance import (
    EARTH_LOOK, ReferenceLook, apply_camera_effects, draw_occluders, random_look, sun_lighting,
)
from sg_nerfstudio.synthetic.building import BuildingConfig, Surface, build_landmark, landmark_surfaces
from sg_nerfstudio.synthetic.capture import SIDE_AZIMUTH_DEG, Shot, meta_image_shots, reference_shots
from sg_nerfstudio.synthetic.raycast import raycast_shot

Array = np.ndarray
REFERENCE_BACKGROUND = np.array([0.80, 0.85, 0.90])
PHOTO_SOFTNESS = 0.04
"""Edge softness of the patterns in photos (metres): crisp, with the fine stone and paving texture."""


@dataclass
class MetaImageSpec:
    """One meta-image: photos of one side of the landmark."""

    name: str
    side: str
    n_photos: int


@dataclass
class SceneConfig:
    """Everything that defines a synthetic scene; the same config and seed give the same files."""

    seed: int = 0
    building: BuildingConfig = field(default_factory=BuildingConfig)
    reference_size: tuple[int, int] = (160, 120)
    """Reference render size (width, height) in pixels."""
    reference_fov_deg: float = 62.0
    n_ring: int = 36
    """Ground-level reference views on a ring around the landmark."""
    n_aerial: int = 24
    """Aerial reference views on a higher orbit."""
    ring_radius_ratio: float = 2.3
    """Ring radius / half-diagonal of the main body."""
    meta_images: tuple[str, ...] = ("front:16", "rear:12")
    """Meta-images as SIDE:N_PHOTOS, side one of front, rear, left, right (each side once); named after the side."""
    photo_size: tuple[int, int] = (160, 120)
    """Base photo size (width, height); photos vary around it and may be portrait."""
    photo_distance: tuple[float, float] = (0.65, 1.25)
    """Range of the photos' distance to the landmark's centre, in ring radii (lower: more close-ups of a facade)."""
    appearance_strength: float = 1.0
    """0 = photos lit and exposed like the reference, 1 = strong in-the-wild variation."""
    occluder_rate: float = 0.3
    """Fraction of photos with transient occluders."""
    occluder_coverage: tuple[float, float] = (0.15, 0.45)
    """Range of the image fraction hidden in an occluded photo."""
    distortion: float = 0.06
    """Largest |k1| of the SIMPLE_RADIAL photos (half of the photos are undistorted PINHOLE)."""
    meta_scale_range: tuple[float, float] = (0.25, 4.0)
    """Range of the random meta-image frame scale."""
    n_sparse_points: int = 4000
    """Largest number of points in each COLMAP model's sparse point cloud."""
    reference_look: ReferenceLook = field(default_factory=ReferenceLook)
    """How the reference's renders differ from the photos (appearance.ReferenceLook; EARTH_LOOK for gap scenes)."""


GAP_PHOTO_DISTANCE = (0.5, 1.25)
"""Photo distances of gap scenes (ring radii): Internet photos include close-ups of a facade, where a coarse model's
render has the least to show."""

PRESETS: dict[str, SceneConfig] = {
    "default": SceneConfig(),
    # The paper's setting: the reference is a Google-Earth-like model (EARTH_LOOK), the photos include close-ups.
    "gap": SceneConfig(reference_look=EARTH_LOOK, photo_distance=GAP_PHOTO_DISTANCE),
    "tiny": SceneConfig(
        building=BuildingConfig(n_gaussians=4000, window_cols=4),
        reference_size=(48, 36), n_ring=10, n_aerial=6,
        meta_images=("front:5",), photo_size=(48, 36), n_sparse_points=800,
    ),
}


def _landmark(seed: int, metas: tuple[str, ...], occluders: float, appearance: float, **building) -> SceneConfig:
    return SceneConfig(
        seed=seed, building=BuildingConfig(palette_seed=seed, **building), meta_images=metas,
        occluder_rate=occluders, appearance_strength=appearance,
    )


SUITES: dict[str, dict[str, SceneConfig]] = {
    # `sg-make-scene --preset benchmark`: six landmarks of different shape (towers, roofs, proportions),
    # 2-3 meta-images each on different sides with 8-32 photos (186 in all: sg-bench's defaults run in 26
    # minutes on a 2-core CPU), occluder rates 0.1-0.45 and appearance strength 0.5-1.0. Each scene is what
    # `--preset default` writes, with other settings.
    "benchmark": {
        "cathedral": _landmark(101, ("front:16", "rear:10", "left:8"), 0.3, 1.0),
        "chapel": _landmark(102, ("front:10", "right:12"), 0.1, 0.6, width=18.0, depth=14.0, height=10.0, towers=1, roof="pitched", window_cols=4),
        "domed-hall": _landmark(103, ("rear:14", "left:10", "right:8"), 0.25, 0.8, width=26.0, depth=26.0, height=14.0, towers=0, roof="dome"),
        "fortress": _landmark(104, ("front:32", "rear:8"), 0.45, 0.9, width=36.0, depth=24.0, height=12.0, towers=2, roof="flat", tower_height_ratio=1.4),
        "bell-tower": _landmark(105, ("left:12", "front:8"), 0.2, 0.5, width=14.0, depth=12.0, height=12.0, towers=1, roof="pitched", tower_height_ratio=2.4, window_rows=4, window_cols=3),
        "town-hall": _landmark(106, ("front:20", "right:10", "rear:8"), 0.35, 1.0, width=40.0, depth=16.0, height=15.0, towers=0, roof="flat", window_rows=4, window_cols=8),
    },
    # Two tiny scenes: the benchmark pipeline end to end in the tests.
    "tiny-benchmark": {
        "tiny-a": replace(PRESETS["tiny"], seed=0, meta_images=("front:5",)),
        "tiny-b": replace(PRESETS["tiny"], seed=1, meta_images=("front:4", "rear:4"), building=replace(PRESETS["tiny"].building, towers=0, roof="dome")),
    },
}
"""Benchmark suites: several scenes written side by side (the layout `sg-bench` reads)."""
# `sg-make-scene --preset gap-benchmark`: the benchmark's landmarks in the paper's setting (the "gap" preset's reference
# look and photo distances): SIFT across photo and reference is as rare as on the paper's pairs (docs/gap-scenes.md).
SUITES["gap-benchmark"] = {
    name: replace(config, reference_look=EARTH_LOOK, photo_distance=GAP_PHOTO_DISTANCE) for name, config in SUITES["benchmark"].items()
}


class SceneGenerationError(InputError):
    """A scene cannot be generated from the given settings."""


def meta_image_specs(config: SceneConfig) -> list[MetaImageSpec]:
    """Parse `config.meta_images` ("side:n_photos") into specs, with one-sentence errors."""
    specs = []
    for entry in config.meta_images:
        side, _, count = entry.partition(":")
        if side not in SIDE_AZIMUTH_DEG or not count.isdigit():
            raise SceneGenerationError(
                f"Meta-image {entry!r} must be SIDE:N_PHOTOS with SIDE one of {', '.join(SIDE_AZIMUTH_DEG)}, e.g. front:16."
            )
        specs.append(MetaImageSpec(name=side, side=side, n_photos=int(count)))
    return specs


SCENE_RANGES = {
    "seed": dict(whole=True, minimum=0), "reference_fov_deg": dict(above=0, below=180), "n_ring": dict(whole=True, minimum=0),
    "n_aerial": dict(whole=True, minimum=0), "ring_radius_ratio": dict(above=0), "appearance_strength": dict(minimum=0),
    "occluder_rate": dict(minimum=0, maximum=1), "occluder_coverage": dict(minimum=0, maximum=1), "distortion": dict(minimum=0, maximum=0.5),
    "meta_scale_range": dict(above=0), "n_sparse_points": dict(whole=True, minimum=1), "reference_size": dict(whole=True, minimum=16),
    "photo_size": dict(whole=True, minimum=16), "photo_distance": dict(above=0),
    "reference_look.softness": dict(minimum=0), "reference_look.sun_strength": dict(minimum=0),
    "reference_look.saturation": dict(minimum=0), "reference_look.tint": dict(minimum=0), "reference_look.haze": dict(minimum=0),
    "reference_look.haze_colour": dict(minimum=0, maximum=1), "reference_look.detail_scale": dict(above=0, maximum=1),
    "reference_look.texture_misalignment": dict(minimum=0),
    "building.width": dict(above=0), "building.depth": dict(above=0), "building.height": dict(above=0),
    "building.towers": dict(whole=True, minimum=0), "building.tower_height_ratio": dict(above=0),
    "building.window_rows": dict(whole=True, minimum=0), "building.window_cols": dict(whole=True, minimum=0),
    "building.ground_radius": dict(above=0), "building.ground_density": dict(minimum=0), "building.n_gaussians": dict(whole=True, minimum=100),
    "building.palette_seed": dict(whole=True, minimum=0), "building.unique_detail": dict(minimum=0),
}
"""Every numeric setting of a synthetic scene and its range (`errors.range_problem`'s bounds; tuples: each entry)."""


def validate(config: SceneConfig) -> None:
    """Raise SceneGenerationError with one sentence for settings that cannot produce a scene."""
    for path, bounds in SCENE_RANGES.items():
        group, _, name = path.rpartition(".")
        value = getattr(getattr(config, group) if group else config, name)
        for entry in value if isinstance(value, tuple) else (value,):
            problem = range_problem(entry, **bounds)
            if problem:
                raise SceneGenerationError(f"Scene setting --{name.replace('_', '-')} must be {problem}, got {entry!r}.")
    if any(low > high for low, high in (config.occluder_coverage, config.meta_scale_range, config.photo_distance)):
        raise SceneGenerationError("Scene ranges occluder_coverage, meta_scale_range and photo_distance must list their lower bound first.")
    specs = meta_image_specs(config)
    if config.n_ring + config.n_aerial < 3:
        raise SceneGenerationError(f"A reference capture needs at least 3 views, got n_ring + n_aerial = {config.n_ring + config.n_aerial}.")
    for spec in specs:
        if spec.n_photos < 3:
            raise SceneGenerationError(f"Meta-image '{spec.name}' needs at least 3 photos, got {spec.n_photos}.")
    names = [spec.name for spec in specs]
    if len(set(names)) != len(names):
        raise SceneGenerationError(f"Each side can hold one meta-image, got {list(config.meta_images)}.")
    if min(config.reference_size + config.photo_size) < 16:
        raise SceneGenerationError("Image sizes must be at least 16 pixels on each side.")
    if config.building.n_gaussians < 100:
        raise SceneGenerationError(f"The landmark needs at least 100 Gaussians, got {config.building.n_gaussians}.")
    if not config.building.unique_detail >= 0.0:  # also refuses NaN
        raise SceneGenerationError(f"unique_detail must be 0 or more, got {config.building.unique_detail}.")
    if not 0.0 <= config.occluder_rate <= 1.0:
        raise SceneGenerationError(f"occluder_rate must be in [0, 1], got {config.occluder_rate}.")


def random_sim3(rng: np.random.Generator, scale_range: tuple[float, float]) -> pycolmap.Sim3d:
    """A random similarity: uniform rotation, log-uniform scale, translation of a few scene units."""
    quat = rng.normal(size=4)
    quat /= np.linalg.norm(quat)
    scale = float(np.exp(rng.uniform(np.log(scale_range[0]), np.log(scale_range[1]))))
    return pycolmap.Sim3d(scale, pycolmap.Rotation3d(quat), rng.normal(0.0, 2.0, 3))


def scale_shots(shots: list[Shot], factor: float) -> list[Shot]:
    """Shots in a world scaled by `factor` about the origin (camera centres scale, rotations do not)."""
    return [
        replace(shot, cam_from_world=pycolmap.Rigid3d(shot.cam_from_world.rotation, shot.cam_from_world.translation * factor))
        for shot in shots
    ]


def scene_unit_factor(shots: list[Shot]) -> float:
    """Factor that makes the median distance of these cameras to their centroid equal to 1."""
    centres = np.stack([shot.cam_from_world.inverse().translation for shot in shots])
    return 1.0 / float(np.median(np.linalg.norm(centres - centres.mean(0), axis=1)))


@dataclass
class RenderedShot:
    shot: Shot
    image: Array  # [H, W, 3] float in [0, 1]
    depth: Array  # [H, W] expected depth along camera z, inf where empty
    metadata: dict


def sparse_tracks(
    points: Array, renders: list[RenderedShot], max_points: int, rng: np.random.Generator, min_track: int = 2
) -> tuple[Array, list[list[tuple[int, Array]]]]:
    """Pick up to `max_points` surface points seen by >= `min_track` shots, like an SfM point cloud.

    A point is seen by a shot when it projects inside the image and its depth agrees with the rendered
    surface depth there (within 5%), i.e. the landmark does not hide it.

    Returns:
        the kept points [M, 3] and, per point, a list of (shot index, pixel [2]) observations.
    """
    visible = np.zeros((len(renders), len(points)), bool)
    pixels = np.zeros((len(renders), len(points), 2))
    for index, rendered in enumerate(renders):
        pose = rendered.shot.cam_from_world
        cam_points = points @ pose.rotation.matrix().T + pose.translation
        in_front = cam_points[:, 2] > 1e-3
        pixels[index, in_front] = rendered.shot.camera.img_from_cam(cam_points[in_front])
        h, w = rendered.depth.shape
        cols, rows = np.floor(pixels[index, :, 0]).astype(int), np.floor(pixels[index, :, 1]).astype(int)
        inside = in_front & (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
        surface_depth = np.full(len(points), -np.inf)
        surface_depth[inside] = rendered.depth[rows[inside], cols[inside]]
        visible[index] = inside & (np.abs(cam_points[:, 2] - surface_depth) < 0.05 * cam_points[:, 2])
    tracked = np.nonzero(visible.sum(0) >= min_track)[0]
    chosen = np.sort(rng.choice(tracked, min(max_points, len(tracked)), replace=False))
    observations = [[(int(s), pixels[s, p]) for s in np.nonzero(visible[:, p])[0]] for p in chosen]
    return points[chosen], observations


def build_reconstruction(renders: list[RenderedShot], points: Array, observations, shared_camera: bool) -> pycolmap.Reconstruction:
    """A COLMAP reconstruction of the rendered shots (world frame of the shots) with the given tracks."""
    keypoints: list[list[Array]] = [[] for _ in renders]
    tracks = []
    for obs in observations:
        track = []
        for shot_index, pixel in obs:
            track.append((shot_index, len(keypoints[shot_index])))
            keypoints[shot_index].append(pixel)
        tracks.append(track)
    recon = pycolmap.Reconstruction()
    for index, rendered in enumerate(renders):
        camera_id = 1 if shared_camera else index + 1
        if not recon.exists_camera(camera_id):
            camera = pycolmap.Camera(rendered.shot.camera.todict())
            camera.camera_id = camera_id
            recon.add_camera_with_trivial_rig(camera)
        kps = np.array(keypoints[index], dtype=np.float64).reshape(-1, 2)
        image = pycolmap.Image(name=rendered.shot.name, keypoints=kps, camera_id=camera_id, image_id=index + 1)
        recon.add_image_with_trivial_frame(image, rendered.shot.cam_from_world)
    for xyz, track in zip(points, tracks):
        shot_index, kp_index = track[0]
        pixel = keypoints[shot_index][kp_index]
        img = renders[shot_index].image
        color = (img[min(int(pixel[1]), img.shape[0] - 1), min(int(pixel[0]), img.shape[1] - 1)] * 255).astype(np.uint8)
        colmap_track = pycolmap.Track()
        for s_index, k_index in track:
            colmap_track.add_element(s_index + 1, k_index)
        recon.add_point3D(xyz, colmap_track, color)
    return recon


def write_images(renders: list[RenderedShot], directory: Path) -> None:
    directory.mkdir(parents=True, exist_ok=True)
    for rendered in renders:
        bgr = cv2.cvtColor((rendered.image * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR)
        if not cv2.imwrite(str(directory / rendered.shot.name), bgr):
            raise SceneGenerationError(f"Could not write image {directory / rendered.shot.name}.")


def pose_matrix(pose: pycolmap.Rigid3d) -> list[list[float]]:
    return pose.matrix().tolist()


def sim3_record(sim3: pycolmap.Sim3d) -> dict:
    """JSON form of a Sim(3) meta -> reference."""
    matrix = np.eye(4)
    matrix[:3] = sim3.matrix()
    quat_xyzw = sim3.rotation.quat
    return {
        "convention": "x_reference = scale * R @ x_meta + translation",
        "matrix": matrix.tolist(),
        "scale": float(sim3.scale),
        "rotation_wxyz": [float(quat_xyzw[3]), *map(float, quat_xyzw[:3])],
        "translation": [float(v) for v in sim3.translation],
    }


MeasurePairs = Callable[[Path], dict]
"""The pairs folder of a scene -> its gap record (`bench.gap.measure_gap`, which `sg-make-scene` passes)."""


def generate_scene(
    config: SceneConfig, output: Path, overwrite: bool = False, progress: Progress | None = None, measure_pairs: MeasurePairs | None = None,
) -> dict:
    """Generate the scene into `output` (atomically) and return the manifest written to scene.json; `measure_pairs`
    fills its "gap" record before anything is moved into place."""
    validate(config)
    output = Path(output)
    check_new_output_directory(output, overwrite)
    with atomic_directory(output, overwrite=overwrite) as staging:
        return _generate_into(config, staging, progress, measure_pairs)


def _generate_into(config: SceneConfig, root: Path, progress: Progress | None, measure_pairs: MeasurePairs | None) -> dict:
    started = time.perf_counter()
    rng = np.random.default_rng(config.seed)
    b = config.building
    scene_m = build_landmark(b, seed=config.seed)
    half_diagonal = 0.5 * float(np.hypot(b.width, b.depth))
    ring_radius = config.ring_radius_ratio * half_diagonal
    target = np.array([0.0, 0.0, 0.5 * b.height])
    ref_shots_m = reference_shots(
        config.n_ring, config.n_aerial, ring_radius, 0.12 * b.height, 40.0, target,
        *config.reference_size, config.reference_fov_deg, rng,
    )
    unit = scene_unit_factor(ref_shots_m)
    scene = scene_m.scaled(unit)
    surfaces = landmark_surfaces(b)
    ref_shots = scale_shots(ref_shots_m, unit)

    specs = meta_image_specs(config)
    total = len(ref_shots) + sum(spec.n_photos for spec in specs)
    task = progress.add_task("rendering", total=total) if progress else None

    def advance() -> None:
        if progress is not None:
            progress.advance(task)

    ref_renders = []
    for shot in ref_shots:
        image, depth = reference_render(config.reference_look, surfaces, shot, unit)
        ref_renders.append(RenderedShot(shot, image, depth, {}))
        advance()
    write_images(ref_renders, root / "reference" / "images")
    points, observations = sparse_tracks(scene.means, ref_renders, config.n_sparse_points, rng)
    ref_recon = build_reconstruction(ref_renders, points, observations, shared_camera=True)
    (root / "reference" / "colmap" / "sparse" / "0").mkdir(parents=True)
    ref_recon.write_binary(str(root / "reference" / "colmap" / "sparse" / "0"))

    manifest = {
        "generator": "sg_nerfstudio.synthetic",
        "config": _jsonable(asdict(config)),
        "scene_unit": "median distance of the reference cameras to their centroid = 1",
        "metres_per_unit": 1.0 / unit,
        "n_gaussians": int(len(scene.means)),
        "reference": {"path": "reference", "n_images": len(ref_renders), "n_points3D": int(ref_recon.num_points3D())},
        "meta_images": [],
    }
    for spec in specs:
        manifest["meta_images"].append(
            _generate_meta_image(spec, config, scene, surfaces, ring_radius, unit, rng, root, advance)
        )
    manifest["gap"] = measure_pairs(root / "pairs") if measure_pairs else {"measured": False, "why": "no measure was asked for"}
    manifest["wall_time_s"] = round(time.perf_counter() - started, 2)
    (root / "scene.json").write_text(json.dumps(manifest, indent=2))
    return manifest


def reference_render(look: ReferenceLook, surfaces: list[Surface], shot: Shot, unit: float) -> tuple[Array, Array]:
    """The reference model rendered at `shot` in `look`: image [H, W, 3] in [0, 1] and depth [H, W] (scene units)."""
    image, depth = raycast_shot(
        surfaces, look.shading(), look.softness, shot, REFERENCE_BACKGROUND, 1.0 / unit, texture_coordinates=look.texture_coordinates
    )
    return look.finish(image, depth), depth


def _generate_meta_image(spec, config, scene, surfaces: list[Surface], ring_radius, unit, rng, root, advance) -> dict:
    b = config.building
    facade = (b.width if spec.side in ("front", "rear") else b.depth, b.height)
    shots = scale_shots(
        meta_image_shots(
            spec.side, spec.n_photos, ring_radius, 1.7, facade, config.photo_size, config.distortion, rng, spec.name, config.photo_distance
        ),
        unit,
    )
    renders, pair_renders = [], []
    for shot in shots:
        look = random_look(config.appearance_strength, rng)
        image, depth = raycast_shot(surfaces, partial(sun_lighting, look=look), PHOTO_SOFTNESS, shot, look.sky, 1.0 / unit)
        coverage = 0.0
        if rng.random() < config.occluder_rate:
            image, coverage = draw_occluders(image, rng.uniform(*config.occluder_coverage), rng)
        image = apply_camera_effects(image, look, rng)
        metadata = {
            "name": shot.name,
            "occluded_fraction": round(coverage, 4),
            "exposure": round(look.exposure, 4),
            "camera_model": shot.camera.model.name,
            "cam_from_world_reference": pose_matrix(shot.cam_from_world),
        }
        renders.append(RenderedShot(shot, image, depth, metadata))
        pair_renders.append(RenderedShot(shot, reference_render(config.reference_look, surfaces, shot, unit)[0], depth, {}))
        advance()
    directory = root / "meta" / spec.name
    write_images(renders, directory / "images")
    write_images(renders, root / "pairs" / spec.name / "photos")
    write_images(pair_renders, root / "pairs" / spec.name / "renders")
    points, observations = sparse_tracks(scene.means, renders, config.n_sparse_points, rng)
    recon = build_reconstruction(renders, points, observations, shared_camera=False)
    gt_meta_to_ref = random_sim3(rng, config.meta_scale_range)
    recon.transform(gt_meta_to_ref.inverse())
    (directory / "sparse" / "0").mkdir(parents=True)
    recon.write_binary(str(directory / "sparse" / "0"))
    (directory / "gt_transform.json").write_text(json.dumps(sim3_record(gt_meta_to_ref), indent=2))
    return {
        "name": spec.name,
        "side": spec.side,
        "path": f"meta/{spec.name}",
        "n_photos": len(renders),
        "n_points3D": int(recon.num_points3D()),
        "photos": [r.metadata for r in renders],
    }


def read_scene_config(scene: Path) -> SceneConfig:
    """The SceneConfig a scene was generated with (from its scene.json)."""
    record = json.loads((Path(scene) / "scene.json").read_text())["config"]
    values = {key: tuple(value) if isinstance(value, list) else value for key, value in record.items()}
    values["building"] = BuildingConfig(**record["building"])
    if "reference_look" in record:  # scenes written before gap scenes have the default look
        values["reference_look"] = ReferenceLook(**{k: tuple(v) if isinstance(v, list) else v for k, v in record["reference_look"].items()})
    return SceneConfig(**values)


def _jsonable(value):
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    return value
