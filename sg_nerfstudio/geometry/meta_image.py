"""A meta-image: photos plus the COLMAP model that bundles them, read with pycolmap and validated.

Layout: `<dir>/images/<name>` and a COLMAP model in `<dir>/sparse/0/` or `<dir>/sparse/` (COLMAP's own layout), or
in `<dir>/colmap/sparse/0/` (what nerfstudio's `ns-process-data` writes). Each photo is
undistorted to a pinhole image with the same focal length and principal point (any COLMAP camera
model: pixels are mapped through pycolmap's `cam_from_img` / `img_from_cam`), so the reference model can
be rendered with a pinhole camera and compared with it.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Optional

import cv2
import numpy as np
import pycolmap
from PIL import Image as PILImage

from sg_nerfstudio.errors import InputError, not_a_directory
from sg_nerfstudio.geometry.sim3 import Sim3

Array = np.ndarray
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp"}


class MetaImageError(InputError):
    """A meta-image directory that cannot be registered."""


@dataclass
class Photo:
    """One registered photo of a meta-image.

    Attributes:
        name: image name as in the COLMAP model.
        path: image file.
        camera: its pycolmap camera (any model, pixel convention: centre of the top-left pixel at 0.5).
        cam_from_world: [3, 4] world-to-camera (OpenCV) in the meta-image frame.
        points_camera: [M, 3] the sparse points it observes, in its camera frame (OpenCV, meta units).
        focal_scale: the registration's correction of the SfM focal length (`CameraFitSettings.focal`):
            the reference is rendered with the undistorted image's focal lengths times this (1: as SfM found them).
    """

    name: str
    path: Path
    camera: pycolmap.Camera
    cam_from_world: Array
    points_camera: Array
    focal_scale: float = 1.0

    @property
    def point_depths(self) -> Array:
        """[M] depths (camera z, meta units) of the sparse points it observes."""
        return self.points_camera[:, 2]

    @property
    def median_depth(self) -> float:
        """Median depth (meta units) of the sparse points it observes in front of it; NaN when it observes none."""
        depths = self.point_depths[self.point_depths > 0]
        return float(np.median(depths)) if len(depths) else float("nan")

    @property
    def centre(self) -> Array:
        return -self.cam_from_world[:, :3].T @ self.cam_from_world[:, 3]

    def pinhole_intrinsics(self) -> Array:
        """[3, 3] K of the undistorted image (same focal lengths and principal point)."""
        fx, fy, cx, cy = _focal_and_centre(self.camera)
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def intrinsics_at(self, width: int, height: int) -> Array:
        """[3, 3] K of the undistorted image resized to width x height pixels (where its pixels were observed)."""
        K = self.pinhole_intrinsics()
        K[0] *= width / self.camera.width
        K[1] *= height / self.camera.height
        return K

    def render_intrinsics_at(self, width: int, height: int) -> Array:
        """[3, 3] K the reference is rendered with for this photo at width x height: `intrinsics_at` with the focal
        lengths times `focal_scale` (principal point unchanged)."""
        K = self.intrinsics_at(width, height)
        K[0, 0] *= self.focal_scale
        K[1, 1] *= self.focal_scale
        return K

    def load_resized(self, long_side: int) -> tuple[Array, Array]:
        """The undistorted photo area-resized to `long_side` pixels on its long side, and the K to render the
        reference with for it (`render_intrinsics_at`): ([h, w, 3] uint8 RGB, [3, 3])."""
        image = self.load_undistorted()
        factor = long_side / max(image.shape[:2])
        width, height = max(1, round(image.shape[1] * factor)), max(1, round(image.shape[0] * factor))
        image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
        return image, self.render_intrinsics_at(width, height)

    def load_undistorted(self) -> Array:
        """[H, W, 3] uint8 RGB, undistorted to `pinhole_intrinsics()`; raises MetaImageError if unreadable."""
        # the stored pixel grid, as COLMAP saw it: OpenCV would otherwise turn a photo by its EXIF orientation tag
        bgr = cv2.imread(str(self.path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
        if bgr is None:
            raise MetaImageError(f"Photo {self.path} could not be read as an image.")
        height, width = bgr.shape[:2]  # equal to the camera's: checked by load_meta_image
        rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        if self.camera.model.name in ("SIMPLE_PINHOLE", "PINHOLE"):
            return rgb
        K = self.pinhole_intrinsics()
        us, vs = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
        rays = np.stack([(us.ravel() - K[0, 2]) / K[0, 0], (vs.ravel() - K[1, 2]) / K[1, 1], np.ones(us.size)], axis=1)
        distorted = self.camera.img_from_cam(rays)
        map_x = (distorted[:, 0] - 0.5).reshape(height, width).astype(np.float32)
        map_y = (distorted[:, 1] - 0.5).reshape(height, width).astype(np.float32)
        return cv2.remap(rgb, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


@dataclass
class MetaImage:
    name: str
    directory: Path
    model_path: Path
    photos: list[Photo]
    reconstruction: pycolmap.Reconstruction
    unlisted: list[str]
    """Image files in images/ that the model does not list (reported, not used)."""

    @property
    def centres(self) -> Array:
        """[P, 3] camera centres in the meta frame."""
        return np.stack([p.centre for p in self.photos])

    @property
    def poses(self) -> list[Array]:
        """[3, 4] world-to-camera (OpenCV) of every photo, meta frame."""
        return [p.cam_from_world for p in self.photos]

    def with_focal_scales(self, scales: dict[str, float]) -> "MetaImage":
        """A copy whose photos named in `scales` have that `focal_scale` (the others keep theirs)."""
        photos = [replace(p, focal_scale=float(scales[p.name])) if p.name in scales else p for p in self.photos]
        return replace(self, photos=photos)

    def with_poses(self, poses: dict[str, Array]) -> "MetaImage":
        """A copy whose photos named in `poses` have that [3, 4] cam_from_world (meta frame; the registration's
        per-photo pose correction, `CameraFitSettings.photo_poses`); the sparse points keep the depths and
        pixels the SfM observed."""
        photos = [replace(p, cam_from_world=np.asarray(poses[p.name], dtype=np.float64)) if p.name in poses else p for p in self.photos]
        return replace(self, photos=photos)

    def with_radial_distortion(self, k1: dict[int, float]) -> "MetaImage":
        """A copy whose COLMAP cameras named in `k1` (camera id -> value) have that first radial coefficient
        (`CameraFitSettings.distortion`); the model is copied, the photos get the new cameras."""
        if not k1:
            return self
        reconstruction = pycolmap.Reconstruction(self.reconstruction)
        for camera_id, value in k1.items():
            camera = reconstruction.cameras[camera_id]
            params = np.array(camera.params)
            params[radial_k1_index(camera)] = value
            camera.params = params
        photos = [replace(p, camera=copy.deepcopy(reconstruction.cameras[int(p.camera.camera_id)])) for p in self.photos]
        return replace(self, photos=photos, reconstruction=reconstruction)

    def camera_focal_scales(self) -> dict[int, float]:
        """COLMAP camera id -> the `focal_scale` of its photos, for the cameras whose photos were rescaled (photos
        that share a camera are rescaled together: `registration.anchored_start.camera_fit.fit_cameras`)."""
        return {int(p.camera.camera_id): p.focal_scale for p in self.photos if p.focal_scale != 1.0}

    def centroid_under(self, transform: Sim3) -> Array:
        """[3] centroid of the camera centres moved by `transform`."""
        return transform.apply(self.centres.mean(0))

    def look_at_under(self, transform: Sim3) -> Array:
        """[3] where the photos look, moved by `transform`: the mean over photos of the point on each optical
        axis at the median depth of the sparse points it observes (the camera centroid when no photo observes
        any). Rotating about it keeps the photographed scene where it is in every photo to first order, so
        rotation and translation change the images independently."""
        targets = []
        for photo in self.photos:
            depth = photo.median_depth
            if np.isfinite(depth):
                targets.append(photo.centre + depth * photo.cam_from_world[2, :3])
        return transform.apply(np.mean(targets, axis=0)) if targets else self.centroid_under(transform)


RADIAL_MODELS = {"SIMPLE_RADIAL", "RADIAL", "OPENCV"}
"""COLMAP camera models whose first extra parameter is the first radial distortion coefficient k1 (x_d = x (1 + k1 r^2 +
...)); the registration may refine it (`CameraFitSettings.distortion`)."""


def radial_k1_index(camera: pycolmap.Camera) -> Optional[int]:
    """Index of k1 in the camera's params, None for models without it (pinhole, fisheye and the others)."""
    return int(camera.extra_params_idxs()[0]) if camera.model.name in RADIAL_MODELS else None


def relative_focal_uncertainty(reconstruction: pycolmap.Reconstruction) -> dict[int, float]:
    """COLMAP camera id -> the standard deviation of its focal length relative to the focal length (sigma_f / f): how
    well the model's own SfM determined it. From pycolmap's covariance of a bundle adjustment of the model in which
    poses, points, focal lengths and distortion are free (principal points fixed, the gauge fixed by two cameras),
    evaluated at the model as it is (nothing is refined). The 3-photo models of real photos in docs/measurements.md "Per-photo focal
    lengths" give 4-10%, sg-demo's 16-photo synthetic one 0.4-1.7%. Cameras it cannot estimate are left out."""
    return intrinsics_uncertainty(reconstruction)[0]


def intrinsics_uncertainty(reconstruction: pycolmap.Reconstruction) -> tuple[dict[int, float], dict[int, float]]:
    """({camera id: sigma_f / f} as `relative_focal_uncertainty`, {camera id: standard deviation of k1} for the cameras
    of RADIAL_MODELS) from one covariance of the model's bundle adjustment. The models of 3-5 real photos give
    0.02-0.27 for k1, synthetic meta-images of 8-16 photos 0.004-0.01."""
    model = pycolmap.Reconstruction(reconstruction)  # the adjuster holds pointers into it: a copy, left untouched
    covariance = _sfm_covariance(model, pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)  # minimal (7 dof); three fixed points are not
    if covariance is None:
        return {}, {}
    focal, k1 = {}, {}
    for camera_id, camera in model.cameras.items():
        block = covariance.get_other_params_cov(camera.params)  # rows: the parameters that were free, in order
        if block is None:
            continue
        free = [i for i in range(len(camera.params)) if i not in set(camera.principal_point_idxs())]
        rows = [free.index(i) for i in camera.focal_length_idxs()]
        relative = [np.sqrt(block[r, r]) / camera.params[i] for r, i in zip(rows, camera.focal_length_idxs())]
        if np.all(np.isfinite(relative)) and min(relative) > 0:
            focal[int(camera_id)] = float(np.mean(relative))
        index = radial_k1_index(camera)
        if index is not None:
            sigma = float(np.sqrt(block[free.index(index), free.index(index)]))
            if np.isfinite(sigma) and sigma > 0:
                k1[int(camera_id)] = sigma
    return focal, k1


def relative_rotation_uncertainty(reconstruction: pycolmap.Reconstruction) -> dict[str, float]:
    """Image name -> how well the model's own SfM determined that photo's orientation relative to the others: the median
    over the other photos of the standard deviation (degrees, root mean of the three axes' variances) of the rotation
    between the two cameras, from the same bundle-adjustment covariance as `relative_focal_uncertainty` (focal lengths
    and distortion free) with the gauge fixed by three points, so that every camera is free and the relative poses
    are gauge-invariant. The 3-photo models of real photos in docs/measurements.md "Per-photo poses" give 0.18-0.54°, sg-demo's
    12-16-photo synthetic ones 0.04-0.11°. Photos it cannot estimate are left out."""
    model = pycolmap.Reconstruction(reconstruction)
    covariance = _sfm_covariance(model, pycolmap.BundleAdjustmentGauge.THREE_POINTS)
    if covariance is None:
        return {}
    images = [model.images[image_id] for image_id in sorted(model.reg_image_ids())]
    uncertainty = {}
    for image in images:
        sigmas = []
        for other in images:
            if other.image_id == image.image_id:
                continue
            block = covariance.get_cam2_cov_from_cam1(image.image_id, image.cam_from_world(), other.image_id, other.cam_from_world())
            if block is not None and np.all(np.isfinite(block[:3, :3])):
                sigmas.append(np.degrees(np.sqrt(max(float(np.trace(block[:3, :3])), 0.0) / 3)))
        if sigmas and np.median(sigmas) > 0:
            uncertainty[image.name] = float(np.median(sigmas))
    return uncertainty


def _sfm_covariance(model: pycolmap.Reconstruction, gauge: pycolmap.BundleAdjustmentGauge) -> Optional[pycolmap.BACovariance]:
    """pycolmap's covariance of a bundle adjustment of `model` (poses, points, focal lengths and distortion free,
    principal points fixed) under `gauge`, at the model as it is; None where it cannot be estimated."""
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length, options.refine_principal_point, options.refine_extra_params = True, False, True
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in model.reg_image_ids():
        config.add_image(image_id)
    config.fix_gauge(gauge)
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(options, config, model)
    covariance_options = pycolmap.BACovarianceOptions()
    covariance_options.params = pycolmap.BACovarianceOptionsParams.ALL
    return pycolmap.estimate_ba_covariance(covariance_options, model, adjuster)


def _focal_and_centre(camera: pycolmap.Camera) -> tuple[float, float, float, float]:
    return (
        float(camera.focal_length_x), float(camera.focal_length_y),
        float(camera.principal_point_x), float(camera.principal_point_y),
    )


def holds_colmap_model(directory: Path) -> bool:
    """Whether `directory` holds a COLMAP model (its images file, binary or text)."""
    return (Path(directory) / "images.bin").exists() or (Path(directory) / "images.txt").exists()


COLMAP_LAYOUTS = (Path("sparse") / "0", Path("sparse"), Path("colmap") / "sparse" / "0", Path("colmap") / "sparse")
"""Where a COLMAP model sits under a folder, first found first: COLMAP's own layout (and `sg-meta-images`'), then
nerfstudio's (`ns-process-data`)."""


def model_below(folder: Path) -> Optional[Path]:
    """The first of COLMAP_LAYOUTS under `folder` that holds a COLMAP model, or None."""
    return next((Path(folder) / layout for layout in COLMAP_LAYOUTS if holds_colmap_model(Path(folder) / layout)), None)


def find_model(directory: Path) -> Path:
    model = model_below(directory)
    if model is None:
        raise MetaImageError(
            f"No COLMAP model in {directory}: expected one of {', '.join(str(directory / layout) for layout in COLMAP_LAYOUTS)} "
            "holding cameras/images/points3D (.bin or .txt)."
        )
    return model


def sibling_models(model_path: Path) -> list[Path]:
    """The other models beside `model_path` where it is `sparse/<n>` (COLMAP's mapper writes one per part of the photo
    collection it could connect: sparse/0, sparse/1, ...), sorted by name; [] otherwise."""
    model_path = Path(model_path)
    if model_path.parent.name != "sparse":
        return []
    return sorted(p for p in model_path.parent.iterdir() if p.is_dir() and p != model_path and holds_colmap_model(p))


MODEL_FILES = ("cameras", "images", "points3D")
"""The files every COLMAP model has (.bin or .txt); rigs and frames, which COLMAP 3.12 adds, pycolmap makes up when absent."""


def check_model_files(model_path: Path) -> None:
    """MetaImageError naming the files of MODEL_FILES missing from a COLMAP model folder (pycolmap itself names all five
    it reads, present or not)."""
    missing = [name for name in MODEL_FILES if not any((model_path / f"{name}{suffix}").is_file() for suffix in (".bin", ".txt"))]
    if missing:
        given = "binary" if (model_path / "images.bin").is_file() else "text"
        names = " and ".join(f"{name}.{'bin' if given == 'binary' else 'txt'}" for name in missing)
        raise MetaImageError(f"COLMAP model {model_path} has no {names}; expected cameras, images and points3D of one {given} model there.")


def load_meta_image(directory: Path, min_photos: int = 3) -> MetaImage:
    """Read and validate a meta-image; every problem is one MetaImageError sentence."""
    directory = Path(directory)
    if not directory.is_dir():
        raise MetaImageError(f"Meta-image directory {directory} {not_a_directory(directory)}; expected a directory holding images/ and a COLMAP model (sparse/0).")
    model_path = find_model(directory)
    check_model_files(model_path)
    try:
        reconstruction = pycolmap.Reconstruction(str(model_path))
    except Exception as error:
        raise MetaImageError(f"COLMAP model {model_path} could not be read ({error}); expected a valid model.") from None
    images_dir = directory / "images"
    if not images_dir.is_dir():
        raise MetaImageError(f"Meta-image {directory} has no images/ folder next to its COLMAP model.")

    listed = {image.name for image in reconstruction.images.values()}
    on_disk = {str(p.relative_to(images_dir)) for p in images_dir.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES}
    missing = sorted(listed - on_disk)
    if missing:
        raise MetaImageError(
            f"{len(missing)} photos listed by {model_path} are missing from {images_dir}: {', '.join(missing[:5])}"
            + (" ..." if len(missing) > 5 else "") + "."
        )
    extra = sorted(on_disk - listed)

    photos = []
    for image in sorted(reconstruction.images.values(), key=lambda im: im.name):
        if not image.has_pose:
            continue
        camera = reconstruction.cameras[image.camera_id]
        if not camera.is_perspective:
            raise MetaImageError(f"Photo {image.name} uses camera model {camera.model.name}; expected a perspective model.")
        pose = image.cam_from_world().matrix()
        points = np.array([reconstruction.points3D[p.point3D_id].xyz for p in image.points2D if p.has_point3D()]).reshape(-1, 3)
        _check_finite(image.name, model_path, camera, pose, points)
        _check_size(images_dir / image.name, camera)
        photos.append(Photo(image.name, images_dir / image.name, camera, pose, points @ pose[:, :3].T + pose[:, 3]))
    if len(photos) < min_photos:
        raise MetaImageError(
            f"Meta-image {directory} has {len(photos)} registered photos; at least {min_photos} are needed."
        )
    return MetaImage(directory.name, directory, model_path, photos, reconstruction, extra)


def decoded_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file, after decoding all of it (a JPEG at an eighth of its size: libjpeg still reads
    every byte, at a fraction of the cost).

    A truncated JPEG fails here (PIL raises "image file is truncated"), where OpenCV and pycolmap, which read the photos
    later, only print "Premature end of JPEG file" and fill the missing rows with grey, which would then be
    registered as if they were the photo."""
    with PILImage.open(path) as handle:
        size = handle.size
        handle.draft(handle.mode, (max(1, size[0] // 8), max(1, size[1] // 8)))  # JPEG only; other formats ignore it
        handle.load()
        return size


def _check_finite(name: str, model_path: Path, camera: pycolmap.Camera, pose: Array, points: Array) -> None:
    """A photo's camera, pose and observed points as numbers a registration can use (a NaN, an infinity or a focal
    length <= 0 would otherwise surface as an error deep inside pycolmap or a NaN transform)."""
    focal = np.asarray(camera.params)[camera.focal_length_idxs()]
    if not np.all(np.isfinite(camera.params)) or not np.all(focal > 0):
        raise MetaImageError(
            f"Photo {name} of {model_path} has camera parameters {np.asarray(camera.params).tolist()} ({camera.model.name}); "
            "expected finite values and positive focal lengths."
        )
    if not np.all(np.isfinite(pose)):
        raise MetaImageError(f"Photo {name} of {model_path} has a pose that is not finite; expected a finite rotation and translation.")
    if not np.all(np.isfinite(points)):
        raise MetaImageError(f"Photo {name} of {model_path} observes 3D points that are not finite; expected finite point coordinates.")


def _check_size(path: Path, camera: pycolmap.Camera) -> None:
    try:
        width, height = decoded_size(path)
    except Exception as error:
        raise MetaImageError(f"Photo {path} could not be read as an image ({error}); expected a complete JPEG or PNG.") from None
    if (width, height) != (camera.width, camera.height):
        raise MetaImageError(
            f"Photo {path} is {width}x{height} pixels but its COLMAP camera says {camera.width}x{camera.height}; "
            "expected the size the model was built from."
        )
