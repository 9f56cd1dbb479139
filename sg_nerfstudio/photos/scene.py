"""A benchmark scene from real photographs, in the layout `sg-bench` reads (bench/layout.py).

The paper evaluates on WikiEarth: a reference of pseudo-synthetic (Google Earth) renders covering the
landmark, and meta-images reconstructed by SfM from Internet photos, with ground truth. From one photo set
with cameras this builds the same kind of scene:

1. the solution: every photo's camera in one world frame, from given cameras (Strecha `.camera` files or a
   COLMAP model, `cameras=`) or else from SfM on all photos (photos it cannot place are left out, reported);
   scaled so that the median distance of the reference cameras to their centroid is 1 (the scene unit of
   the synthetic scenes, so thresholds and errors mean the same);
2. the split: photos ordered along the capture path (first principal axis of the camera centres); every
   `reference_every`-th photo (and the last) is the reference, the others form meta-images of `meta_size`
   consecutive photos (the last window is moved back to stay full, so two meta-images can share a photo);
3. the reference: its photos at `reference_size` with a pseudo-synthetic look (edge-preserving smoothing
   that removes fine texture, grey-world colour), its cameras from the solution, and a SIFT point cloud
   triangulated with those poses fixed (`initialisers.reference_cloud`) for the splat's initialisation; or, with
   `reference_kind="coarse-model"` (the paper's setting, where SIFT rarely matches photo and reference), renders of a
   coarse splat of those photos from their cameras and new ones (`photos.coarse_reference`), the SIFT cloud
   triangulated on the renders, and `pairs/<meta-image>/`: each meta photo with the model rendered at its true pose;
4. each meta-image: its photos at `photo_size` with a seeded in-the-wild look (exposure, white balance,
   gamma, blur, noise, JPEG quality; occluders on a share of photos: `synthetic.appearance`), reconstructed
   on its own by SfM (its own frame, scale, intrinsics and errors: `photos.sfm`), and the ground truth
   meta -> reference as the Sim(3) that maps its SfM cameras onto the solution's (`geometry.alignment`),
   with the per-camera residual recorded. The solution's cameras are first turned to the principal point the
   meta-image's SfM uses (`at_principal_point_of`): an SfM that holds the principal point at the image centre
   turns each camera by the angle between that point and the true one (0.48° for Strecha's fountain-P11, whose
   calibrated principal point is 15 / 17 px off the centre of a 3072-px photo), and a ground truth that compared
   orientations across the two conventions would hold every registration of such a model that far from the
   answer (docs/measurements.md "The principal point in the ground truth"). The plain alignment is recorded beside it,
   and so is a second, point-based truth (`point_truth`: the model's own points fitted to its tracks triangulated with
   the solution's cameras) with its distance from the first: a 3-photo SfM is not exactly a similarity of the
   solution, and the Sim(3) that places its cameras and the one that places its points differ by that much.

Written atomically; `scene.json` records the settings, the split, what was left out and why. The same photos and
settings give the same scene, byte for byte: every SfM runs on one thread (SFM_THREADS).
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Literal, Optional

import cv2
import numpy as np
import pycolmap
from PIL import Image
from scipy.spatial.transform import Rotation

from sg_nerfstudio.atomic import atomic_directory, check_new_output_directory
from sg_nerfstudio.errors import InputError, not_a_directory, range_problem
from sg_nerfstudio.geometry.alignment import CameraAlignment, align_cameras, camera_centres, camera_residuals
from sg_nerfstudio.geometry.sim3 import Sim3, rotation_angle_deg
from sg_nerfstudio.geometry.triangulation import track_observations, triangulate_track
from sg_nerfstudio.initialisers.estimate import similarity_from_centres
from sg_nerfstudio.initialisers.features import MatchSettings, SiftExtractor, SiftSettings
from sg_nerfstudio.initialisers.pipeline import silent_progress
from sg_nerfstudio.initialisers.reference_cloud import PairingSettings, ReferenceSource, ReferenceSourceError, build_reference_cloud
from sg_nerfstudio.photos.coarse_reference import (
    COARSE_RANGES, CoarseModel, CoarseModelSettings, median_depths, new_view_poses, render_view, train_coarse_model,
)
from sg_nerfstudio.photos.collection import capped_size, list_photos, prepare_photos
from sg_nerfstudio.photos.meta_images import write_model
from sg_nerfstudio.photos.sfm import SfmSettings, check_camera_model, reconstruct
from sg_nerfstudio.photos.strecha import read_strecha_cameras
from sg_nerfstudio.synthetic.appearance import apply_camera_effects, draw_occluders, random_look

Array = np.ndarray
Stage = Callable[[str], None]


class RealSceneError(InputError):
    """Photos or cameras that cannot make a benchmark scene."""


@dataclass(frozen=True)
class RealSceneSettings:
    """How a photo set becomes a benchmark scene (see the module docstring)."""

    reference_every: int = 2
    """Every k-th photo along the path (and the last) goes to the reference."""
    meta_size: int = 3
    """Photos per meta-image (>= 3)."""
    reference_size: int = 480
    """Long side of the reference images (pixels): what the reference is trained on."""
    photo_size: int = 640
    """Long side of the meta-image photos (pixels)."""
    reference_smoothing: float = 0.5
    """Strength of the pseudo-synthetic look of the reference (0 = the photos as they are)."""
    appearance_strength: float = 1.0
    """0 = meta photos as they are, 1 = strong in-the-wild variation (exposure, white balance, gamma, blur, noise)."""
    occluder_rate: float = 0.3
    """Share of meta photos with transient occluders."""
    occluder_coverage: tuple[float, float] = (0.1, 0.3)
    """Range of the image share an occluder hides."""
    jpeg_quality: tuple[int, int] = (60, 95)
    """Range of the meta photos' JPEG quality."""
    meta_camera_model: str = "SIMPLE_RADIAL"
    """COLMAP camera model of the meta-images' own SfM (one camera per photo): SIMPLE_RADIAL as `sg-meta-images` by
    default, OPENCV as nerfstudio's `ns-process-data` writes, RADIAL, PINHOLE, ... The solution the ground truth and the
    reference come from is not affected."""
    min_reference_points: int = 100
    """Fewer triangulated reference points than this cannot initialise a splat: refused."""
    reference_kind: Literal["filtered-photos", "coarse-model"] = "filtered-photos"
    """filtered-photos: the reference photos with the pseudo-synthetic look (`reference_smoothing`), which SIFT still
    matches to the meta photos; coarse-model: renders of a coarse model of them, the paper's setting (SIFT across
    photo and reference as rare as on the paper's pairs: photos/coarse_reference.py, docs/gap-scenes.md)."""
    coarse: CoarseModelSettings = CoarseModelSettings()
    """The coarse model and its look (reference_kind coarse-model only)."""
    seed: int = 0


SFM_THREADS = 1
"""Threads of every SfM run of the builder. pycolmap's multi-threaded mapper is not deterministic: three builds of
Strecha fountain-P11 with `--scene.reference-every 3 --scene.meta-size 3 --scene.photo-size 800 --scene.seed 41` on all
cores gave meta-image 0005-0008 ground truths whose own residual was 1.64°, 1.43° and 1.44° (point-based truth 0.315,
0.208, 0.209 away), so a benchmark scene rebuilt on another machine was another scene. On one thread three builds wrote
byte-identical models (8 s instead of 5 s for that scene; docs/measurements.md "Benchmark scenes that rebuild the
same")."""


@dataclass
class SolvedPhoto:
    """One photo in the solution: its camera at the working size and its pose in the reference world."""

    name: str
    camera: pycolmap.Camera
    cam_from_world: Array  # [3, 4] OpenCV


REAL_SCENE_RANGES = {
    "reference_every": dict(whole=True, minimum=2),  # 1 would leave no photo for meta-images
    "meta_size": dict(whole=True, minimum=3),  # a meta-image is an SfM model
    "reference_size": dict(whole=True, minimum=16), "photo_size": dict(whole=True, minimum=16),
    "reference_smoothing": dict(minimum=0), "appearance_strength": dict(minimum=0), "occluder_rate": dict(minimum=0, maximum=1),
    "occluder_coverage": dict(minimum=0, maximum=1), "jpeg_quality": dict(whole=True, minimum=1, maximum=100),
    "min_reference_points": dict(whole=True, minimum=1), "seed": dict(whole=True, minimum=0),
}
"""Every numeric setting of a real-photo scene and its range (`errors.range_problem`'s bounds; tuples: each entry)."""


def check_real_scene_ranges(settings: RealSceneSettings) -> None:
    """RealSceneError naming the first numeric setting that is not a finite number in its range."""
    for group, ranges, prefix in ((settings, REAL_SCENE_RANGES, "--scene."), (settings.coarse, COARSE_RANGES, "--scene.coarse.")):
        for name, bounds in ranges.items():
            value = getattr(group, name)
            for entry in value if isinstance(value, tuple) else (value,):
                problem = range_problem(entry, **bounds)
                if problem:
                    raise RealSceneError(f"Scene setting {prefix}{name.replace('_', '-')} must be {problem}, got {entry!r}.")
    for name in ("occluder_coverage", "jpeg_quality"):
        low, high = getattr(settings, name)
        if low > high:
            raise RealSceneError(f"Scene setting --scene.{name.replace('_', '-')} must list its lower bound first, got {low} {high}.")


def build_real_scene(
    photos: Path, output: Path, settings: RealSceneSettings, cameras: Optional[Path] = None,
    overwrite: bool = False, stage: Optional[Stage] = None, measure_pairs: Optional[Callable[[Path], dict]] = None,
) -> dict:
    """Write the scene (module docstring) into `output`; returns the manifest (scene.json). `measure_pairs` (a coarse-model
    reference only: `bench.gap.measure_gap`) fills its "gap" record from the photo/render pairs."""
    stage = stage or (lambda _: None)
    started = time.perf_counter()
    check_real_scene_ranges(settings)
    check_camera_model(settings.meta_camera_model, "--scene.meta-camera-model")
    if cameras is not None and not Path(cameras).is_dir():
        raise RealSceneError(
            f"Cameras {cameras} {not_a_directory(cameras)}; expected a COLMAP model directory or a folder of "
            "<photo name>.camera files (Strecha format)."
        )
    sources = list_photos(photos)
    check_new_output_directory(output, overwrite, inputs=[photos, cameras])
    with atomic_directory(output, overwrite=overwrite) as root:
        work = root / "work"
        stage(f"reading {len(sources)} photos")
        prepared = prepare_photos(sources, work / "clean", settings.photo_size)
        solution, solved_by = solve(prepared, work, cameras, settings, stage)
        ordered = order_along_path(solution)
        reference_names, meta_windows = split_photos(ordered, settings.reference_every, settings.meta_size)
        unit = scene_unit(np.stack([solution[n].cam_from_world for n in reference_names]))
        for photo in solution.values():
            photo.cam_from_world = np.concatenate([photo.cam_from_world[:, :3], photo.cam_from_world[:, 3:] * unit], axis=1)
        reference_photos = [solution[n] for n in reference_names]
        coarse = None
        if settings.reference_kind == "coarse-model":
            reference, coarse = write_coarse_reference(root / "reference", work, reference_photos, settings, stage)
        else:
            stage("reference: pseudo-synthetic images and triangulation")
            reference = write_reference(root / "reference", work, reference_photos, settings)
        rng = np.random.default_rng(settings.seed)
        metas = []
        for window in meta_windows:
            name = f"{Path(window[0]).stem}-{Path(window[-1]).stem}"
            stage(f"meta-image {name}: in-the-wild photos and SfM")
            metas.append(write_meta(root / "meta" / name, work / name, [solution[n] for n in window], settings, rng))
            if coarse is not None and metas[-1]["written"]:
                write_pairs(root / "pairs" / name, work / name / "images", [solution[n] for n in window], coarse, settings.coarse)
        if not any(m["written"] for m in metas):
            raise RealSceneError(
                f"No meta-image of {photos} could be reconstructed on its own ({metas[0]['why']}); expected overlapping photos."
            )
        manifest = {
            "generator": "sg_nerfstudio.photos.scene",
            "photos": str(Path(photos).resolve()),
            "cameras": str(Path(cameras).resolve()) if cameras else None,
            "solution": solved_by,
            "settings": asdict(settings),
            "scene_unit": "median distance of the reference cameras to their centroid = 1",
            "source_units_per_scene_unit": 1.0 / unit,
            "left_out": sorted(set(p.name for p in prepared) - set(solution)),
            "reference": reference,
            "meta_images": metas,
        }
        if coarse is None:
            manifest["gap"] = {"measured": False, "why": "a filtered-photos reference has no renders at the photos' poses"}
        else:
            stage("measuring the photo/reference gap")
            manifest["gap"] = measure_pairs(root / "pairs") if measure_pairs else {"measured": False, "why": "no measure was asked for"}
        shutil.rmtree(work)
        manifest["wall_time_s"] = round(time.perf_counter() - started, 2)
        (root / "scene.json").write_text(json.dumps(manifest, indent=2, default=float))
    return manifest


# ------------------------------------------------------------------------------------------- solution


def solve(prepared, work: Path, cameras: Optional[Path], settings: RealSceneSettings, stage: Stage) -> tuple[dict[str, SolvedPhoto], str]:
    """Every photo's camera (at its working size) and pose in one world frame, and where they came from."""
    names = [p.name for p in prepared]
    sizes = {p.name: p.size for p in prepared}
    if cameras is None:
        stage("solution: SfM on all photos")
        result = reconstruct(work / "clean", names, work / "solution", SfmSettings(seed=settings.seed, threads=SFM_THREADS))
        if not result.models:
            raise RealSceneError(f"SfM on all {len(names)} photos formed no model; expected overlapping photos of one place (or give --cameras).")
        model = result.models[0]
        solved = {
            model.images[i].name: SolvedPhoto(model.images[i].name, model.cameras[model.images[i].camera_id], model.images[i].cam_from_world().matrix())
            for i in model.reg_image_ids()
        }
        return solved, f"pycolmap SfM on all photos ({len(solved)} of {len(names)} registered)"
    cameras = Path(cameras)
    if (cameras / "images.bin").is_file() or (cameras / "images.txt").is_file():
        return _from_colmap(cameras, names, sizes), f"COLMAP model {cameras}"
    strecha = read_strecha_cameras(cameras, names)
    solved = {}
    for name, camera in strecha.items():
        width, height = sizes[name]
        if abs(camera.width / camera.height - width / height) > 0.01:
            raise RealSceneError(f"Camera of {name} is {camera.width}x{camera.height} but the photo is {width}x{height} after EXIF rotation; expected the same aspect ratio.")
        solved[name] = SolvedPhoto(name, camera.colmap_camera(width, height), camera.cam_from_world())
    return solved, f"Strecha cameras {cameras}"


def _from_colmap(path: Path, names: list[str], sizes: dict) -> dict[str, SolvedPhoto]:
    try:
        model = pycolmap.Reconstruction(str(path))
    except Exception as error:
        raise RealSceneError(f"COLMAP model {path} could not be read ({error}).") from None
    solved = {}
    for image_id in model.reg_image_ids():
        image = model.images[image_id]
        if image.name in sizes:
            camera = pycolmap.Camera(model.cameras[image.camera_id].todict())
            width, height = sizes[image.name]
            if abs(camera.width / camera.height - width / height) > 0.01:
                raise RealSceneError(
                    f"COLMAP model {path} says {image.name} is {camera.width}x{camera.height} but the photo is {width}x{height} "
                    "after EXIF rotation; expected the same aspect ratio."
                )
            camera.rescale(*sizes[image.name])
            solved[image.name] = SolvedPhoto(image.name, camera, image.cam_from_world().matrix())
    if len(solved) < 3:
        raise RealSceneError(f"COLMAP model {path} places {len(solved)} of the photos; expected most of them (images named as the photo files).")
    return solved


def order_along_path(solution: dict[str, SolvedPhoto]) -> list[str]:
    """Photo names sorted along the first principal axis of their camera centres (ties: by name)."""
    names = sorted(solution)
    centres = camera_centres(np.stack([solution[n].cam_from_world for n in names]))
    centred = centres - centres.mean(0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][0]
    position = centred @ axis
    if position[0] > position[-1]:  # keep the direction of the file names where they follow the path
        position = -position
    return [names[i] for i in np.lexsort((np.arange(len(names)), np.round(position, 9)))]


def split_photos(ordered: list[str], every: int, meta_size: int) -> tuple[list[str], list[list[str]]]:
    """Reference photos and meta-image windows along the path (module docstring, step 2)."""
    reference = ordered[::every]
    if ordered[-1] not in reference:
        reference.append(ordered[-1])
    rest = [name for name in ordered if name not in reference]
    if len(reference) < 3 or len(rest) < meta_size:
        raise RealSceneError(
            f"{len(ordered)} placed photos split into {len(reference)} reference and {len(rest)} meta-image photos; expected at "
            f"least 3 reference photos and {meta_size} for a meta-image (use more photos, or a smaller --meta-size)."
        )
    windows = []
    for start in range(0, len(rest), meta_size):
        start = min(start, len(rest) - meta_size)
        window = rest[start:start + meta_size]
        if not windows or window != windows[-1]:
            windows.append(window)
    return reference, windows


def scene_unit(cam_from_world: Array) -> float:
    """Factor that makes the median distance of these cameras [N, 3, 4] to their centroid 1."""
    centres = camera_centres(cam_from_world)
    spread = float(np.median(np.linalg.norm(centres - centres.mean(0), axis=1)))
    if spread <= 0:
        raise RealSceneError("The reference cameras all sit at one point; expected a capture that moves around the landmark.")
    return 1.0 / spread


# ------------------------------------------------------------------------------------------ reference


def pseudo_synthetic(image: Image.Image, strength: float) -> Image.Image:
    """The flat, texture-poor look of a mesh render: edge-preserving smoothing and grey-world colour."""
    rgb = np.asarray(image, dtype=np.float32) / 255.0
    rgb = rgb * (rgb.mean() / np.maximum(rgb.reshape(-1, 3).mean(0), 1e-3))[None, None]
    out = np.clip(rgb * 255.0, 0, 255).astype(np.uint8)
    if strength > 0:
        sigma_s = min(200.0, 0.05 * max(image.size) * strength)
        bgr = cv2.edgePreservingFilter(cv2.cvtColor(out, cv2.COLOR_RGB2BGR), flags=cv2.RECURS_FILTER, sigma_s=sigma_s, sigma_r=min(1.0, 0.3 * strength))
        out = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    return Image.fromarray(out)


def write_reference(directory: Path, work: Path, photos: list[SolvedPhoto], settings: RealSceneSettings) -> dict:
    """reference/images/*.png (the photos with the pseudo-synthetic look) and reference/colmap/sparse/0 (solution
    poses, triangulated SIFT points)."""
    images = directory / "images"
    images.mkdir(parents=True)
    views = []
    for photo in photos:
        clean = Image.open(work / "clean" / photo.name)
        size = capped_size(clean.size, settings.reference_size)
        name = f"{Path(photo.name).stem}.png"
        pseudo_synthetic(clean.resize(size, Image.Resampling.LANCZOS), settings.reference_smoothing).save(images / name)
        views.append((name, _rescaled(photo.camera, size), photo.cam_from_world))
    cloud = triangulate_posed(images, work / "reference_cloud", views, settings.min_reference_points, f"the {len(photos)} reference photos")
    (directory / "colmap" / "sparse" / "0").mkdir(parents=True)
    cloud.write_binary(str(directory / "colmap" / "sparse" / "0"))
    return {"path": "reference", "kind": "filtered-photos", "images": [v[0] for v in views], "n_points3D": int(cloud.num_points3D())}


def write_coarse_reference(
    directory: Path, work: Path, photos: list[SolvedPhoto], settings: RealSceneSettings, stage: Stage,
) -> tuple[dict, CoarseModel]:
    """reference/images/*.png rendered from a coarse model of the reference photos (photos/coarse_reference.py) at their
    cameras and new ones, and reference/colmap/sparse/0 (those poses, SIFT points triangulated on the renders); returns
    the record and the model (for the photo/render pairs)."""
    coarse = settings.coarse
    source = work / "coarse_source"
    (source / "images").mkdir(parents=True)
    stage("coarse model: triangulating the reference photos")
    views = []
    for photo in photos:
        clean = Image.open(work / "clean" / photo.name)
        size = capped_size(clean.size, settings.reference_size)
        name = f"{Path(photo.name).stem}.png"
        clean.resize(size, Image.Resampling.LANCZOS).save(source / "images" / name)
        views.append((name, _rescaled(photo.camera, size), photo.cam_from_world))
    cloud = triangulate_posed(source / "images", work / "coarse_cloud", views, settings.min_reference_points, f"the {len(photos)} reference photos")
    for image_id in cloud.reg_image_ids():  # the model trains at its texture resolution
        image = cloud.images[image_id]
        path = source / "images" / image.name
        with Image.open(path) as photo:
            small = capped_size(photo.size, coarse.train_size)
            shrunk = photo.resize(small, Image.Resampling.LANCZOS)
        shrunk.save(path)
        cloud.cameras[image.camera_id] = _rescaled(cloud.cameras[image.camera_id], small)
    (source / "colmap" / "sparse" / "0").mkdir(parents=True)
    cloud.write_binary(str(source / "colmap" / "sparse" / "0"))
    poses = np.stack([photo.cam_from_world for photo in photos])
    depths = median_depths(poses, np.stack([p.xyz for p in cloud.points3D.values()]))
    stage(f"coarse model: training {coarse.steps} steps on the reference photos at {coarse.train_size} px")
    model = train_coarse_model(source, work / "coarse_model", coarse, settings.seed, float(np.median(depths)))
    for index, pose in enumerate(new_view_poses(poses, depths, coarse.lift * model.depth, coarse.new_views)):
        gap, within = divmod(index, coarse.new_views)
        name = f"view-{Path(photos[gap].name).stem}-{Path(photos[gap + 1].name).stem}-{within + 1}.png"
        views.append((name, views[gap][1], pose))
    stage(f"coarse model: rendering {len(views)} reference views")
    images = directory / "images"
    images.mkdir(parents=True)
    for name, camera, pose in views:
        render_view(model, camera, pose, coarse).save(images / name)
    rendered = triangulate_posed(images, work / "reference_cloud", views, settings.min_reference_points, "the coarse model's renders", RENDERS_HINT)
    (directory / "colmap" / "sparse" / "0").mkdir(parents=True)
    rendered.write_binary(str(directory / "colmap" / "sparse" / "0"))
    record = {
        "path": "reference", "kind": "coarse-model", "images": [v[0] for v in views], "n_points3D": int(rendered.num_points3D()),
        "coarse_model": {
            "gaussians": model.gaussians, "train_s": round(model.train_s, 2), "photo_points3D": int(cloud.num_points3D()),
            "scene_depth": round(model.depth, 4),
        },
    }
    return record, model


def write_pairs(directory: Path, styled: Path, photos: list[SolvedPhoto], model: CoarseModel, coarse: CoarseModelSettings) -> None:
    """pairs/<meta-image>/photos/ (its in-the-wild photos) and renders/ (the coarse model in the reference's look at each
    photo's solution camera, at the photo's size): the layout `sg-bench teacher` reads."""
    (directory / "photos").mkdir(parents=True)
    (directory / "renders").mkdir(parents=True)
    for photo in photos:
        shutil.copy2(styled / photo.name, directory / "photos" / photo.name)
        render_view(model, photo.camera, photo.cam_from_world, coarse).save(directory / "renders" / f"{Path(photo.name).stem}.png")


PHOTOS_HINT = "photos with more overlap or texture"
RENDERS_HINT = f"{PHOTOS_HINT}; for a coarse model, more --scene.coarse.steps or a larger --scene.coarse.train-size"


def triangulate_posed(
    images: Path, work: Path, views: list[tuple[str, pycolmap.Camera, Array]], min_points: int, what: str, hint: str = PHOTOS_HINT,
) -> pycolmap.Reconstruction:
    """SIFT points of `images` triangulated with every view's (image name, camera at the image's size, cam_from_world
    [3, 4]) held fixed (`initialisers.reference_cloud`); RealSceneError naming `what` and what to change (`hint`) with
    fewer than `min_points`."""
    model = pycolmap.Reconstruction()
    for index, (name, camera, pose) in enumerate(views, start=1):
        camera = pycolmap.Camera(camera.todict())
        camera.camera_id = index
        model.add_camera_with_trivial_rig(camera)
        rigid = pycolmap.Rigid3d(pycolmap.Rotation3d(pose[:, :3]), pose[:, 3])
        model.add_image_with_trivial_frame(pycolmap.Image(name=name, camera_id=index, image_id=index), rigid)
    (work / "poses").mkdir(parents=True)
    model.write_binary(str(work / "poses"))
    try:
        cloud = build_reference_cloud(
            ReferenceSource(work / "poses", images), SiftExtractor(SiftSettings()), MatchSettings(), PairingSettings(),
            work / "cloud", silent_progress,
        )
    except ReferenceSourceError:  # no two images share enough verified matches (its sentence names a staging path)
        raise RealSceneError(
            f"Triangulating {what} gave no 3D points: no two of them share enough verified SIFT matches; expected at least "
            f"{min_points} points to initialise the splat ({hint})."
        ) from None
    points = cloud.reconstruction.num_points3D()
    if points < min_points:
        raise RealSceneError(
            f"Triangulating {what} gave {points} 3D points; expected at least {min_points} to initialise the splat ({hint})."
        )
    return cloud.reconstruction


def _rescaled(camera: pycolmap.Camera, size: tuple[int, int]) -> pycolmap.Camera:
    rescaled = pycolmap.Camera(camera.todict())
    rescaled.rescale(*size)
    return rescaled


# ---------------------------------------------------------------------------------------- meta-images


def in_the_wild(image: Image.Image, settings: RealSceneSettings, rng: np.random.Generator) -> tuple[Image.Image, dict]:
    """A photo with a random look (and maybe occluders) applied in linear light; returns it and what was done."""
    linear = (np.asarray(image, dtype=np.float64) / 255.0) ** 2.2
    coverage = 0.0
    if rng.random() < settings.occluder_rate:
        linear, coverage = draw_occluders(linear, rng.uniform(*settings.occluder_coverage), rng)
    look = random_look(settings.appearance_strength, rng)
    styled = apply_camera_effects(linear, look, rng) ** (1 / 2.2)
    record = {"occluded_fraction": round(coverage, 4), "exposure": round(look.exposure, 4), "gamma": round(look.gamma, 4)}
    return Image.fromarray(np.clip(styled * 255 + 0.5, 0, 255).astype(np.uint8)), record


def write_meta(directory: Path, work: Path, photos: list[SolvedPhoto], settings: RealSceneSettings, rng: np.random.Generator) -> dict:
    """One meta-image: styled photos, their own SfM, gt_transform.json; a record of what happened."""
    styled = work / "images"
    styled.mkdir(parents=True)
    looks = {}
    for photo in photos:
        image, looks[photo.name] = in_the_wild(Image.open(work.parent / "clean" / photo.name), settings, rng)
        quality = int(rng.integers(settings.jpeg_quality[0], settings.jpeg_quality[1] + 1))
        looks[photo.name]["jpeg_quality"] = quality
        image.save(styled / photo.name, format="JPEG", quality=quality)
    names = [p.name for p in photos]
    record = {"name": directory.name, "photos": names, "looks": looks, "written": False}
    result = reconstruct(styled, names, work / "sfm", SfmSettings(camera_model=settings.meta_camera_model, min_model_size=3, seed=settings.seed, threads=SFM_THREADS))
    if not result.models:
        record["why"] = "; ".join(f"{n}: {r}" for n, r in result.unregistered())
        return record
    model = result.models[0]
    ids = sorted(model.reg_image_ids(), key=lambda i: model.images[i].name)
    truth, alignment = ground_truth(model, {p.name: p for p in photos})
    truth["point_based"] = point_truth(model, {p.name: p for p in photos}, alignment.transform)
    write_model(model, styled, directory)
    (directory / "gt_transform.json").write_text(json.dumps(truth, indent=2))
    record.update(
        written=True, path=f"meta/{directory.name}", n_photos=len(ids), n_points3D=int(model.num_points3D()),
        left_out=[{"photo": n, "reason": r} for n, r in result.unregistered()],
        gt_residual_rotation_deg_max=float(alignment.rotation_residual_deg.max()),
        gt_residual_centre_max=float(alignment.centre_residual.max()),
        point_truth_delta_R_deg=truth["point_based"].get("delta_R_deg"), point_truth_delta_T=truth["point_based"].get("delta_T"),
    )
    return record


def ground_truth(model: pycolmap.Reconstruction, solution: dict[str, SolvedPhoto]) -> tuple[dict, CameraAlignment]:
    """(the gt_transform.json record, the `geometry.alignment` result) of a meta-image's SfM `model` against the
    `solution` cameras of its photos (module docstring, step 4): the Sim(3) meta -> reference that maps the model's
    cameras onto the solution's turned to the model's principal points, its per-camera residual, each turn, and the
    plain alignment to the solution's cameras as given."""
    ids = sorted(model.reg_image_ids(), key=lambda i: model.images[i].name)
    source = np.stack([model.images[i].cam_from_world().matrix() for i in ids])
    solved = [solution[model.images[i].name] for i in ids]
    given = np.stack([photo.cam_from_world for photo in solved])
    target = np.stack([at_principal_point_of(p.cam_from_world, p.camera, model.cameras[model.images[i].camera_id]) for p, i in zip(solved, ids)])
    alignment, plain = align_cameras(source, target), align_cameras(source, given)
    record = alignment.transform.as_record() | {
        "residual_rotation_deg": alignment.rotation_residual_deg.round(4).tolist(),
        "residual_centre": alignment.centre_residual.round(5).tolist(),
        "principal_point_turn_deg": [round(rotation_angle_deg(t[:, :3] @ g[:, :3].T), 4) for g, t in zip(given, target)],
        "given_principal_point": plain.transform.as_record() | {"residual_rotation_deg": plain.rotation_residual_deg.round(4).tolist()},
    }
    return record, alignment


POINT_TRUTH_MIN_ANGLE_DEG = 1.5
"""Smallest triangulation angle of a track the point-based truth uses (COLMAP's filter default): below it the depth is noise."""
POINT_TRUTH_MIN_POINTS = 20
"""Fewer agreeing points than this give no point-based truth."""
POINT_TRUTH_AGREEMENT = 0.05
"""A triangulated track agrees with the similarity when it lands within this fraction of the points' spread (median
distance to their median) of the model's point: tracks of a few photos are triangulated to about a percent of it."""


def point_truth(model: pycolmap.Reconstruction, solution: dict[str, SolvedPhoto], camera_truth: Sim3) -> dict:
    """A second ground truth from the meta-image's own 3D points, and how far it is from the camera-based one.

    Every track of the model (its keypoints in two or more photos) is triangulated again with the `solution`'s cameras
    of its photos, fixed (`geometry.triangulation`, tracks under POINT_TRUTH_MIN_ANGLE_DEG dropped), and the
    Sim(3) meta -> reference that maps the model's points onto those is fitted robustly (pycolmap's LO-RANSAC, then
    least squares on the tracks that agree, POINT_TRUTH_AGREEMENT).

    The camera-based truth (`ground_truth`) places the model's cameras where the solution's are; this one places its
    points. Where a 3-photo SfM is not a similarity of the solution (a focal length a few percent off stretches its
    depth; a principal point held at the centre turns its cameras) the two differ, and no single Sim(3) does both
    better than that. sg-bench scores registrations against the camera-based truth (the paper's ΔR / ΔT measure
    cameras) and reports the difference beside it (docs/measurements.md "Two ground truths").

    Returns {"matrix", "points", "inliers", "delta_R_deg", "delta_T"} (the two truths' RMS difference over the model's
    cameras, as `registration.metrics` measures a registration), or {"why"} when too few tracks agree."""
    ids = sorted(model.reg_image_ids(), key=lambda i: model.images[i].name)
    solved_photos = {i: solution[model.images[i].name] for i in ids}
    own, solved = [], []
    for point in model.points3D.values():
        elements, pixels = track_observations(model, point)
        if len(elements) < 2 or any(image_id not in solved_photos for image_id, _ in elements):
            continue
        photos = [solved_photos[image_id] for image_id, _ in elements]
        found = triangulate_track(pixels, [p.cam_from_world for p in photos], [p.camera for p in photos], POINT_TRUTH_MIN_ANGLE_DEG)
        if found is not None:
            own.append(point.xyz)
            solved.append(found.xyz)
    if len(own) < POINT_TRUTH_MIN_POINTS:
        return {"why": f"only {len(own)} of {model.num_points3D()} tracks triangulate with the solution's cameras"}
    own, solved = np.array(own), np.array(solved)
    spread = float(np.median(np.linalg.norm(solved - np.median(solved, axis=0), axis=1)))
    fitted = similarity_from_centres(own, solved, max_error=POINT_TRUTH_AGREEMENT * spread)
    if fitted is None or fitted[1].sum() < POINT_TRUTH_MIN_POINTS:
        return {"why": f"fewer than {POINT_TRUTH_MIN_POINTS} of {len(own)} triangulated tracks agree on one similarity"}
    inliers = fitted[1]
    refit = pycolmap.estimate_sim3d(own[inliers], solved[inliers])  # least squares on the inliers (RANSAC's model is a sample's)
    transform = Sim3.from_matrix(np.vstack([refit.matrix(), [0.0, 0.0, 0.0, 1.0]]) if refit is not None else fitted[0])
    source = np.stack([model.images[i].cam_from_world().matrix() for i in ids])
    rotation, centre = camera_residuals(transform, source, np.stack([camera_truth.move_camera(pose) for pose in source]))
    return transform.as_record() | {
        "points": len(own), "inliers": int(inliers.sum()),
        "delta_R_deg": round(float(np.sqrt(np.mean(rotation**2))), 4), "delta_T": round(float(np.sqrt(np.mean(centre**2))), 5),
    }


def at_principal_point_of(cam_from_world: Array, camera: pycolmap.Camera, sfm_camera: pycolmap.Camera) -> Array:
    """[3, 4] the solution's camera `cam_from_world` (OpenCV, world -> camera) with intrinsics `camera`, turned about its
    centre so that its optical axis is the ray `camera` puts through `sfm_camera`'s principal point (taken as the same
    fraction of the image size): about the orientation an SfM that holds the principal point there finds for that
    photo. A shift of the principal point and a turn of the camera differ by the turn's perspective (at fountain-P11's
    offset, 4.8 px at the centre of a 640-px photo against up to 6.3 px at its edge), which the SfM spreads over its
    other parameters. Unchanged where both principal points agree."""
    pixel = np.array([[sfm_camera.principal_point_x * camera.width / sfm_camera.width, sfm_camera.principal_point_y * camera.height / sfm_camera.height]])
    ray = np.append(np.asarray(camera.cam_from_img(pixel), dtype=np.float64).reshape(2), 1.0)  # in the solution's camera frame
    turn, _ = Rotation.align_vectors([[0.0, 0.0, 1.0]], [ray / np.linalg.norm(ray)])  # the shortest turn taking the ray to the axis
    rotation = turn.as_matrix() @ cam_from_world[:, :3]
    centre = -cam_from_world[:, :3].T @ cam_from_world[:, 3]
    return np.concatenate([rotation, (-rotation @ centre)[:, None]], axis=1)
