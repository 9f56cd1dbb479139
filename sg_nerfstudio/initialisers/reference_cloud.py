"""A SIFT point cloud of the reference, triangulated by pycolmap with the reference poses held fixed.

The reference COLMAP model's own points may come from another feature type (or none at all), so the
photos cannot be matched against them. Instead: SIFT on every reference image, verified matches between
reference pairs (see retrieval.py), a pycolmap Database with the reference cameras, frames and images
under their own ids, and `pycolmap.triangulate_points` (COLMAP's point_triangulator: poses and
intrinsics fixed). Each reference keypoint then knows its 3D point, in the reference *world* frame.

Cache: `<cache dir>/reference/<sha256>/` (sparse model + database), keyed by the reference images'
bytes, the model's cameras and poses, and the SIFT and matching settings; created atomically.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pycolmap

from sg_nerfstudio.atomic import atomic_directory
from sg_nerfstudio.errors import InputError
from sg_nerfstudio.geometry.meta_image import decoded_size, holds_colmap_model, model_below
from sg_nerfstudio.initialisers.features import ImageFeatures, MatchSettings, SiftExtractor, VerifiedMatcher
from sg_nerfstudio.initialisers.retrieval import reference_pairs

Array = np.ndarray
Progress = Callable[[str, int], Callable[[], None]]
"""progress(description, total) -> advance(): how long stages report progress."""


class ReferenceSourceError(InputError):
    """A reference COLMAP model or image folder that cannot be used."""


@dataclass(frozen=True)
class ReferenceSource:
    """The reference's COLMAP reconstruction (its world frame is the reference world) and its images."""

    colmap_path: Path
    images_path: Path

    def load(self) -> pycolmap.Reconstruction:
        """The reconstruction, validated: every registered image exists in `images_path`."""
        model = Path(self.colmap_path)
        if not holds_colmap_model(model):
            below = model_below(model)
            raise ReferenceSourceError(
                f"Reference COLMAP model {model} was not found; expected a folder with cameras, images and points3D (.bin or .txt)"
                + (f" (this one has a model in {below})." if below else ".")
            )
        try:
            reconstruction = pycolmap.Reconstruction(str(model))
        except Exception as error:
            raise ReferenceSourceError(f"Reference COLMAP model {model} could not be read ({error}).") from None
        if reconstruction.num_reg_images() < 2:
            raise ReferenceSourceError(f"Reference COLMAP model {model} has {reconstruction.num_reg_images()} registered images; expected at least 2.")
        missing = [im.name for im in reconstruction.images.values() if not (Path(self.images_path) / im.name).is_file()]
        if missing:
            raise ReferenceSourceError(
                f"{len(missing)} images of reference model {model} are missing from {self.images_path} (e.g. {missing[0]}); "
                "expected the images the model was built from."
            )
        for image in reconstruction.images.values():
            _check_image_size(Path(self.images_path) / image.name, reconstruction.cameras[image.camera_id])
        return reconstruction


def _check_image_size(path: Path, camera: pycolmap.Camera) -> None:
    """Keypoints are only valid with the camera when the file has the camera's size."""
    try:
        size = decoded_size(path)
    except Exception as error:
        raise ReferenceSourceError(f"Reference image {path} could not be read as an image ({error}); expected a complete JPEG or PNG.") from None
    if size != (camera.width, camera.height):
        raise ReferenceSourceError(
            f"Reference image {path} is {size[0]}x{size[1]} pixels but its COLMAP camera says {camera.width}x{camera.height}; "
            "expected the full-resolution images the model was built from."
        )


@dataclass
class ReferenceCloud:
    """SIFT features of the reference images and their triangulated 3D points (reference world frame).

    Attributes:
        reconstruction: the reference model with the SIFT points (poses and cameras as given).
        image_ids: registered reference image ids, sorted.
        features: image id -> its SIFT features (keypoint i is point2D i of the image).
        point_ids: image id -> [N] int64 point3D id per keypoint, -1 where none was triangulated.
    """

    reconstruction: pycolmap.Reconstruction
    image_ids: list[int]
    features: dict[int, ImageFeatures]
    point_ids: dict[int, Array]

    def camera(self, image_id: int) -> pycolmap.Camera:
        return self.reconstruction.cameras[self.reconstruction.images[image_id].camera_id]

    def xyz(self, point_ids: Array) -> Array:
        """[M, 3] world positions of the given point3D ids."""
        return np.array([self.reconstruction.points3D[int(i)].xyz for i in point_ids]).reshape(-1, 3)


@dataclass(frozen=True)
class PairingSettings:
    exhaustive_limit: int = 100
    """Reference sets up to this size are matched exhaustively (pairs and photo-to-reference)."""
    reference_neighbours: int = 20
    """Above the limit: each reference image is matched with this many co-visible images."""


def build_reference_cloud(
    source: ReferenceSource,
    extractor: SiftExtractor,
    matching: MatchSettings,
    pairing: PairingSettings,
    cache_dir: Path,
    progress: Progress,
) -> ReferenceCloud:
    """Extract, match and triangulate the reference (or load all of it from the cache)."""
    reconstruction = source.load()
    image_ids = sorted(i for i, im in reconstruction.images.items() if im.has_pose)
    advance = progress("SIFT on reference images", len(image_ids))
    features = {}
    for image_id in image_ids:
        features[image_id] = extractor(Path(source.images_path) / reconstruction.images[image_id].name)
        advance()
    image_keys = [extractor.key(Path(source.images_path) / reconstruction.images[i].name) for i in image_ids]
    key = _cloud_key(reconstruction, image_ids, image_keys, matching, pairing)
    target = Path(cache_dir) / "reference" / key
    if not (target / "sparse" / "images.bin").exists():
        _triangulate(reconstruction, image_ids, features, source, matching, pairing, target, progress)
    triangulated = pycolmap.Reconstruction(str(target / "sparse"))
    return ReferenceCloud(triangulated, image_ids, features, _point_ids_per_keypoint(triangulated, image_ids, features))


def _cloud_key(reconstruction, image_ids, image_keys: list[str], matching, pairing) -> str:
    """sha256 over the images' feature keys (their bytes + SIFT settings), the cameras and poses, and the
    matching and pairing settings."""
    digest = hashlib.sha256(json.dumps({"matching": asdict(matching), "pairing": asdict(pairing), "version": 1}, sort_keys=True).encode())
    for image_id, image_key in zip(image_ids, image_keys):
        image = reconstruction.images[image_id]
        camera = reconstruction.cameras[image.camera_id]
        digest.update(f"{image_id}:{image.name}:{image_key}:{camera.model.name}:{camera.width}x{camera.height}".encode())
        digest.update(np.round(image.cam_from_world().matrix(), 9).tobytes())
        digest.update(np.round(np.asarray(camera.params, dtype=np.float64), 9).tobytes())
    return digest.hexdigest()


def _triangulate(reconstruction, image_ids, features, source, matching, pairing, target: Path, progress: Progress) -> None:
    pairs = reference_pairs(reconstruction, image_ids, pairing.exhaustive_limit, pairing.reference_neighbours)
    matcher = VerifiedMatcher(matching)
    advance = progress("Matching reference pairs", len(pairs))
    verified = {}
    for id1, id2 in pairs:
        matches = matcher.match(features[id1], _camera(reconstruction, id1), features[id2], _camera(reconstruction, id2))
        if len(matches):
            verified[(id1, id2)] = matches
        advance()
    if not verified:
        raise ReferenceSourceError(
            f"No pair of reference images in {source.colmap_path} has {matching.min_pair_inliers} verified SIFT matches; "
            "expected overlapping, textured reference images."
        )
    advance = progress("Triangulating the reference (poses fixed)", 1)
    with atomic_directory(target, overwrite=True) as staging:
        database = staging / "database.db"
        _write_database(database, reconstruction, image_ids, features, verified)
        fixed = pycolmap.Reconstruction(reconstruction)
        (staging / "sparse").mkdir()
        options = pycolmap.IncrementalPipelineOptions()
        options.triangulation.random_seed = matching.seed
        options.num_threads = 1
        pycolmap.triangulate_points(fixed, str(database), str(source.images_path), str(staging / "sparse"),
                                    clear_points=True, options=options, refine_intrinsics=False)
        if not (staging / "sparse" / "images.bin").exists():
            fixed.write_binary(str(staging / "sparse"))
    advance()


def _camera(reconstruction: pycolmap.Reconstruction, image_id: int) -> pycolmap.Camera:
    return reconstruction.cameras[reconstruction.images[image_id].camera_id]


def _write_database(path: Path, reconstruction, image_ids, features, verified) -> None:
    """A COLMAP database whose camera, rig, frame and image ids are the reconstruction's."""
    database = pycolmap.Database.open(str(path))
    try:
        for camera in reconstruction.cameras.values():
            database.write_camera(camera, use_camera_id=True)
        for rig in reconstruction.rigs.values():
            database.write_rig(rig, use_rig_id=True)
        for frame in reconstruction.frames.values():
            database.write_frame(frame, use_frame_id=True)
        for image_id in image_ids:
            image = pycolmap.Image(name=reconstruction.images[image_id].name, camera_id=reconstruction.images[image_id].camera_id, image_id=image_id)
            image.frame_id = reconstruction.images[image_id].frame_id
            database.write_image(image, use_image_id=True)
            database.write_keypoints(image_id, features[image_id].keypoints)
            database.write_descriptors(image_id, features[image_id].colmap_descriptors())
        for (id1, id2), matches in verified.items():
            database.write_matches(id1, id2, matches)
            geometry = pycolmap.TwoViewGeometry()
            geometry.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
            geometry.inlier_matches = matches
            database.write_two_view_geometry(id1, id2, geometry)
    finally:
        database.close()


def _point_ids_per_keypoint(reconstruction: pycolmap.Reconstruction, image_ids: list[int], features: dict[int, ImageFeatures]) -> dict[int, Array]:
    point_ids = {}
    for image_id in image_ids:
        image = reconstruction.images[image_id]
        ids = np.full(len(features[image_id]), -1, dtype=np.int64)
        if image.num_points2D() == len(ids):
            for index, point in enumerate(image.points2D):
                if point.has_point3D():
                    ids[index] = point.point3D_id
        point_ids[image_id] = ids
    return point_ids
