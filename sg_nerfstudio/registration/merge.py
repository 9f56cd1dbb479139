"""Assembly ("puzzle-solving", paper section 3): every aligned meta-image in one COLMAP model.

Each meta-image is registered on its own; once all are in the reference world frame they form one
reconstruction. `ns-register-meta` given several meta-images writes it to `<output-dir>/merged/`:

    cameras.bin, images.bin, points3D.bin, rigs.bin, frames.bin
                 images named "<meta-image>/<photo name>" (and "reference/<name>" with --merge-reference),
                 cameras, images and points renumbered, tracks kept
    merge.json   which meta-images were merged with their transforms and verdicts, which were not and why

pycolmap does the I/O; only the renumbering is ours (pycolmap has no merge of reconstructions that do
not share images).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np
import pycolmap

from sg_nerfstudio.atomic import atomic_directory
from sg_nerfstudio.geometry.sim3 import Sim3
from sg_nerfstudio.geometry.triangulation import track_observations, triangulate_track


@dataclass
class MergePart:
    """One reconstruction already in the reference world frame, and the prefix its image names get."""

    prefix: str
    reconstruction: pycolmap.Reconstruction
    transform: Optional[Sim3] = None  # meta -> reference world that put it there (None: the reference)
    verdict: Optional[str] = None  # the registration's verdict label (None: the reference)
    verdict_reasons: list[str] = field(default_factory=list)


def aligned_reconstruction(
    reconstruction: pycolmap.Reconstruction, transform: Sim3, focal_scales: Optional[dict[int, float]] = None,
    poses: Optional[dict[str, np.ndarray]] = None, retriangulate: bool = False,
) -> pycolmap.Reconstruction:
    """A copy of `reconstruction` with cameras and points moved by `transform` (pycolmap moves them: the same
    camera motion as `Sim3.move_camera`, which the tests check against it); per camera id in `focal_scales`, that
    camera's focal lengths times the scale (`MetaImage.camera_focal_scales`: what the registration fitted); per image
    name in `poses`, that [3, 4] cam_from_world in the reference world (`RegistrationResult.photo_poses`). With
    `retriangulate`, every track is triangulated again with the new cameras (`retriangulated`): the SfM's points fit
    its own focal lengths, distortion and poses, and under fitted ones they reproject pixels away."""
    moved = pycolmap.Reconstruction(reconstruction)
    moved.transform(pycolmap.Sim3d(transform.scale, pycolmap.Rotation3d(np.asarray(transform.rotation)), np.asarray(transform.translation)))
    for camera_id, scale in (focal_scales or {}).items():
        camera = moved.cameras[camera_id]
        params = np.array(camera.params)
        params[list(camera.focal_length_idxs())] *= scale
        camera.params = params
    for name, pose in (poses or {}).items():
        image = moved.find_image_with_name(name)
        moved.frames[image.frame_id].set_cam_from_world(image.camera_id, pycolmap.Rigid3d(np.asarray(pose, dtype=np.float64)))
    return retriangulated(moved) if retriangulate else moved


def retriangulated(model: pycolmap.Reconstruction) -> pycolmap.Reconstruction:
    """`model` (changed in place) with every point triangulated again from its track with the model's cameras
    (`geometry.triangulation.triangulate_track`); observations beyond its threshold leave the track, and a point whose
    track keeps fewer than two is deleted."""
    for point_id in list(model.point3D_ids()):
        point = model.points3D[point_id]
        elements, pixels = track_observations(model, point)
        images = [model.images[image_id] for image_id, _ in elements]
        found = triangulate_track(pixels, [image.cam_from_world().matrix() for image in images], [model.cameras[image.camera_id] for image in images])
        if found is None:
            model.delete_point3D(point_id)
            continue
        point.xyz = found.xyz
        for (image_id, index), inlier in zip(elements, found.inliers):
            if not inlier:
                model.delete_observation(image_id, index)
    return model


def merge_reconstructions(parts: list[MergePart]) -> pycolmap.Reconstruction:
    """One reconstruction holding every registered image and 3D point of `parts`.

    Image names become "<prefix>/<name>"; camera, image and point ids are renumbered from 1 in the order of
    `parts`; each image keeps its keypoints so every track is carried over with remapped image ids.
    """
    merged = pycolmap.Reconstruction()
    for part in parts:
        camera_ids = _copy_cameras(part.reconstruction, merged)
        image_ids = _copy_images(part, merged, camera_ids)
        _copy_points(part.reconstruction, merged, image_ids)
    return merged


def _copy_cameras(source: pycolmap.Reconstruction, merged: pycolmap.Reconstruction) -> dict[int, int]:
    mapping = {}
    for old_id, camera in sorted(source.cameras.items()):
        copy = pycolmap.Camera(camera.todict())
        copy.camera_id = merged.num_cameras() + 1
        merged.add_camera_with_trivial_rig(copy)
        mapping[old_id] = copy.camera_id
    return mapping


def _copy_images(part: MergePart, merged: pycolmap.Reconstruction, camera_ids: dict[int, int]) -> dict[int, int]:
    mapping = {}
    for old_id in sorted(part.reconstruction.reg_image_ids()):
        image = part.reconstruction.image(old_id)
        keypoints = np.array([point.xy for point in image.points2D], dtype=np.float64).reshape(-1, 2)
        new_id = merged.num_images() + 1
        copy = pycolmap.Image(name=f"{part.prefix}/{image.name}", keypoints=keypoints, camera_id=camera_ids[image.camera_id], image_id=new_id)
        merged.add_image_with_trivial_frame(copy, image.cam_from_world())
        mapping[old_id] = new_id
    return mapping


def _copy_points(source: pycolmap.Reconstruction, merged: pycolmap.Reconstruction, image_ids: dict[int, int]) -> None:
    for _, point in sorted(source.points3D.items()):
        track = pycolmap.Track()
        for element in point.track.elements:
            if element.image_id in image_ids:
                track.add_element(image_ids[element.image_id], element.point2D_idx)
        if track.length() > 0:
            merged.add_point3D(point.xyz, track, point.color)


def write_merged(target: Path, parts: list[MergePart], not_merged: dict[str, str], overwrite: bool = False) -> Path:
    """Write the merged model of `parts` and merge.json (listing `not_merged`: name -> reason) atomically."""
    merged = merge_reconstructions(parts)
    record = {
        "convention": "every camera and point in the reference model's world frame; image names '<source>/<name>'",
        "merged": [
            {"source": part.prefix, "images": part.reconstruction.num_reg_images(), "points3D": part.reconstruction.num_points3D(),
             "transform": None if part.transform is None else np.asarray(part.transform).tolist(),
             "verdict": part.verdict, "verdict_reasons": part.verdict_reasons}
            for part in parts
        ],
        "not_merged": [{"source": name, "reason": reason} for name, reason in not_merged.items()],
        "images": merged.num_images(),
        "points3D": merged.num_points3D(),
    }
    with atomic_directory(target, overwrite=overwrite) as staging:
        merged.write_binary(str(staging))
        (staging / "merge.json").write_text(json.dumps(record, indent=2))
    return target
