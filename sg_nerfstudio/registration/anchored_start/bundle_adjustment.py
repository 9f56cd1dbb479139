"""The camera fit as one bundle adjustment: the meta-image's own SfM observations and the keypoint anchors, in pycolmap.

`camera_fit.fit_cameras` with `solver: adjustment` (fast-cpu). The meta-image's model is moved into the reference world
by the pre-aligned Sim(3); each photo's anchors join it as observations of *constant* 3-D points (the reference's);
COLMAP's bundle adjuster then refines every photo's pose, each camera's focal length and k1 and the model's own points
together, under a Cauchy loss of FIT_KERNEL_FRACTION of the long side. The anchors fix the frame; the model's own tracks
hold the photos to one another as its SfM did, with every correlation between focal length, distortion, depth and
orientation that independent priors (the prior fit) would each charge on their own.

The result is a `CameraFit` like the prior fit's: the Sim(3) that maps the meta-image's cameras onto the adjusted ones
(`geometry.alignment.align_cameras`) and, relative to it, each photo's pose, focal scale and k1. Every photo moves, with
anchors or not. Left to the prior fit (`camera_fit.fit_cameras` decides): camera models with more terms than k1 (COLMAP's
adjuster frees all of a camera's extra parameters or none), multi-camera rigs, and anchors that leave the scale free.
Frames: the meta-image frame, the reference world of the anchors' points, the dataparser frame (`world_to_dataparser`).
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import pycolmap

from sg_nerfstudio.geometry.alignment import AlignmentError, align_cameras, camera_centres
from sg_nerfstudio.geometry.meta_image import MetaImage, radial_k1_index
from sg_nerfstudio.geometry.sim3 import Sim3, rotation_angle_deg
from sg_nerfstudio.initialisers.estimate import PhotoKeypoints

Array = np.ndarray

ADJUSTABLE_MODELS = {"SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL"}
"""Camera models whose extra parameters are at most k1: what the prior fit frees, so the adjustment frees the same."""
ANCHOR_OBSERVATIONS = 2
"""Each anchor enters as this many observations of its constant point: COLMAP's adjuster takes only points with a track
of two or more (more copies changed nothing measurable)."""


def adjustable(meta: MetaImage) -> bool:
    """Whether every camera of the meta-image is of ADJUSTABLE_MODELS and every photo is its own rig (one sensor a rig, as
    COLMAP's mapper writes for photos). `adjust_with_anchors` sets each photo's frame pose to the photo's camera pose,
    which for a multi-camera rig would be the pose of its reference sensor only; such models take the prior fit."""
    model = meta.reconstruction
    return all(camera.model.name in ADJUSTABLE_MODELS for camera in model.cameras.values()) and all(rig.num_sensors() == 1 for rig in model.rigs.values())


def adjust_with_anchors(
    meta: MetaImage, keypoints: list[PhotoKeypoints], world_to_dataparser: Sim3, start: Sim3, focal: bool, distortion: bool, loss_fraction: float,
) -> Optional[tuple[Sim3, dict[str, Array], dict[int, float], dict[int, float]]]:
    """The adjustment from `start` (numpy Sim3, meta -> dataparser): (the Sim(3) meta -> dataparser that maps the
    meta-image's cameras onto the adjusted ones, {photo name: [3, 4] adjusted cam_from_meta under it}, {COLMAP camera id:
    adjusted / given focal length} with `focal`, {camera id: adjusted k1} with `distortion`), or None when the adjuster
    failed or left something not finite. Cauchy loss of `loss_fraction` of each photo's long side (the median over
    the photos, in pixels: COLMAP's loss has one scale)."""
    world_from_meta = world_to_dataparser.inverse() @ start
    model = pycolmap.Reconstruction(meta.reconstruction)
    for photo in meta.photos:  # the photos' poses (a MetaImage's, e.g. moved by an earlier fit), not the model file's
        image = model.find_image_with_name(photo.name)
        pose = photo.cam_from_world
        model.frames[image.frame_id].rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(pose[:, :3]), pose[:, 3])
    scale, rotation, translation = world_from_meta.scale, world_from_meta.linear / world_from_meta.scale, world_from_meta.translation
    model.transform(pycolmap.Sim3d(float(scale), pycolmap.Rotation3d(rotation), translation))
    for camera_id, factor in meta.camera_focal_scales().items():  # an earlier fit's focal scales (none before the first)
        camera = model.cameras[camera_id]
        params = np.array(camera.params)
        params[list(camera.focal_length_idxs())] *= factor
        camera.params = params
    given_focal = {camera_id: camera.mean_focal_length() for camera_id, camera in model.cameras.items()}
    config = with_anchor_observations(model, keypoints)
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length, options.refine_principal_point, options.refine_extra_params = focal, False, distortion
    options.print_summary = False
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    sides = [max(photo.camera.width, photo.camera.height) for photo in meta.photos]
    options.ceres.loss_function_scale = float(loss_fraction * np.median(sides))
    options.ceres.solver_options.num_threads = 1  # deterministic
    summary = pycolmap.create_default_ceres_bundle_adjuster(options, config, model).solve()
    if summary.termination_type == pycolmap.BundleAdjustmentTerminationType.FAILURE:
        return None
    names = [photo.name for photo in meta.photos]
    adjusted_world = np.stack([model.find_image_with_name(name).cam_from_world().matrix() for name in names])
    if not np.isfinite(adjusted_world).all():
        return None
    try:
        meta_to_world = align_cameras(np.stack([photo.cam_from_world for photo in meta.photos]), adjusted_world).transform
    except AlignmentError:
        return None
    back = meta_to_world.inverse()
    poses = {name: back.move_camera(pose) for name, pose in zip(names, adjusted_world)}
    focal_change = {c: model.cameras[c].mean_focal_length() / given_focal[c] for c in model.cameras} if focal else {}
    radial_k1 = {}
    if distortion:
        for camera_id, camera in model.cameras.items():
            index = radial_k1_index(camera)
            if index is not None:
                radial_k1[int(camera_id)] = float(camera.params[index])
    if not all(np.isfinite(v) for v in [*focal_change.values(), *radial_k1.values()]):
        return None
    return world_to_dataparser @ meta_to_world, poses, focal_change, radial_k1


def with_anchor_observations(model: pycolmap.Reconstruction, keypoints: list[PhotoKeypoints]) -> pycolmap.BundleAdjustmentConfig:
    """Rebuild `model`'s observations as its own tracks plus, per photo with anchors, each anchor as ANCHOR_OBSERVATIONS
    observations of a new point at the anchor's reference-world position; the config holds every registered photo and
    those points constant."""
    images = {image_id: model.images[image_id] for image_id in model.reg_image_ids()}
    own = [
        (point.xyz.copy(), [(element.image_id, np.array(images[element.image_id].points2D[element.point2D_idx].xy)) for element in point.track.elements])
        for point in model.points3D.values()
    ]
    model.delete_all_points2D_and_points3D()
    observed: dict[int, list[Array]] = {image_id: [] for image_id in images}

    def observe(image_id: int, xy: Array) -> tuple[int, int]:
        observed[image_id].append(np.asarray(xy, dtype=np.float64))
        return image_id, len(observed[image_id]) - 1

    tracks = [(xyz, [observe(image_id, xy) for image_id, xy in elements], False) for xyz, elements in own]
    by_name = {image.name: image_id for image_id, image in images.items()}
    for photo in keypoints:
        image_id = by_name.get(photo.name)
        if image_id is None:
            continue
        for xy, xyz in zip(np.asarray(photo.points2D, dtype=np.float64), np.asarray(photo.points3D, dtype=np.float64)):
            tracks.append((xyz, [observe(image_id, xy) for _ in range(ANCHOR_OBSERVATIONS)], True))
    config = pycolmap.BundleAdjustmentConfig()
    for image_id, points in observed.items():
        images[image_id].points2D = pycolmap.Point2DList([pycolmap.Point2D(xy) for xy in points])
        config.add_image(image_id)
    for xyz, elements, constant in tracks:
        track = pycolmap.Track()
        for image_id, index in elements:
            track.add_element(image_id, index)
        point_id = model.add_point3D(np.asarray(xyz, dtype=np.float64), track)
        if constant:
            config.add_constant_point(point_id)
    return config


def pose_changes(meta: MetaImage, poses: dict[str, Array]) -> tuple[Array, Array, Array]:
    """[P] rotation (degrees) and centre shift (meta units) of each photo's adjusted pose (`poses`, cam_from_meta) from
    its given one, and [P] its median sparse-point depth (meta units; the median over the others where it has none)."""
    angles, shifts, depths = [], [], []
    for photo in meta.photos:
        pose = poses[photo.name]
        angles.append(rotation_angle_deg(pose[:, :3] @ photo.cam_from_world[:, :3].T))
        shifts.append(float(np.linalg.norm(camera_centres(pose[None])[0] - photo.centre)))
        depths.append(photo.median_depth)
    depths = np.array(depths)
    depths[~np.isfinite(depths)] = np.nanmedian(depths) if np.isfinite(depths).any() else 1.0
    return np.array(angles), np.array(shifts), depths
