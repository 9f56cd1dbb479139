"""Tracks triangulated again with other cameras (geometry/triangulation.py) and its two users: the point-based ground
truth of the real-photo scenes (`photos.scene.point_truth`) and the registration's aligned model
(`registration.merge.aligned_reconstruction` with `retriangulate`). Small exact models built here: no files, no SfM."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from sg_nerfstudio.geometry.sim3 import Sim3
from sg_nerfstudio.geometry.triangulation import triangulate_track
from sg_nerfstudio.registration.merge import aligned_reconstruction

def _model_with_tracks(cam_from_meta: list, points: np.ndarray, camera: pycolmap.Camera) -> pycolmap.Reconstruction:
    """A COLMAP model of photos `cam_from_meta` [3, 4] that all see `points` [N, 3] (meta frame), one track each."""
    model = pycolmap.Reconstruction()
    model.add_camera_with_trivial_rig(camera)
    for image_id, pose in enumerate(cam_from_meta, start=1):
        pixels = camera.img_from_cam(points @ pose[:, :3].T + pose[:, 3])
        image = pycolmap.Image(name=f"{image_id}.jpg", camera_id=camera.camera_id, image_id=image_id,
                               points2D=pycolmap.Point2DList([pycolmap.Point2D(xy) for xy in pixels]))
        model.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(pose[:, :3]), pose[:, 3]))
    for index, point in enumerate(points):
        track = pycolmap.Track()
        for image_id in range(1, len(cam_from_meta) + 1):
            track.add_element(image_id, index)
        model.add_point3D(point, track)
    return model


def _three_photos(rng: np.random.Generator, count: int = 60) -> tuple[list[np.ndarray], np.ndarray]:
    """Three photos 0.4 apart along x, turned 0.05 rad from each other, and `count` points 4-7 in front of them."""
    poses = [np.hstack([Rotation.from_rotvec([0.0, 0.05 * k, 0.0]).as_matrix(), [[-0.4 * k], [0.0], [0.0]]]) for k in (-1, 0, 1)]
    return poses, rng.uniform([-1.5, -1.0, 4.0], [1.5, 1.0, 7.0], (count, 3))


def test_point_truth_recovers_the_similarity_and_measures_the_camera_truths_distance():
    """Three photos of 60 points, the solution their cameras moved by a known Sim(3): the tracks triangulated with the
    solution's cameras give that Sim(3) back, and its distance from a camera truth turned by 0.5° is 0.5° (no distance
    from the right one). A model with too few tracks gives no point-based truth and says why."""
    from sg_nerfstudio.photos.scene import SolvedPhoto, point_truth

    truth = Sim3.from_parts(2.5, Rotation.from_rotvec([0.2, -0.4, 0.3]).as_matrix(), [1.0, -2.0, 0.5])
    camera = pycolmap.Camera(model="SIMPLE_PINHOLE", width=640, height=480, params=[500.0, 320.0, 240.0], camera_id=1)
    poses, points = _three_photos(np.random.default_rng(4))
    model = _model_with_tracks(poses, points, camera)
    solution = {f"{i}.jpg": SolvedPhoto(f"{i}.jpg", camera, truth.move_camera(pose)) for i, pose in enumerate(poses, start=1)}
    record = point_truth(model, solution, truth)
    np.testing.assert_allclose(record["matrix"], np.asarray(truth), atol=1e-6)
    assert record["inliers"] == record["points"] == 60
    assert record["delta_R_deg"] < 1e-4 and record["delta_T"] < 1e-5
    turned = Sim3.from_parts(1.0, Rotation.from_rotvec([0.0, 0.0, np.radians(0.5)]).as_matrix(), np.zeros(3)) @ truth
    assert point_truth(model, solution, turned)["delta_R_deg"] == pytest.approx(0.5, abs=1e-3)
    assert "why" in point_truth(_model_with_tracks(poses, points[:10], camera), solution, truth)


def _reprojection_errors(model: pycolmap.Reconstruction) -> np.ndarray:
    errors = []
    for point in model.points3D.values():
        for element in point.track.elements:
            image = model.images[element.image_id]
            seen = model.cameras[image.camera_id].img_from_cam((image.cam_from_world() * point.xyz)[None])[0]
            errors.append(np.linalg.norm(seen - image.points2D[element.point2D_idx].xy))
    return np.array(errors)


def test_triangulate_track_finds_the_point_and_drops_the_observation_that_disagrees():
    camera = pycolmap.Camera(model="SIMPLE_PINHOLE", width=640, height=480, params=[500.0, 320.0, 240.0], camera_id=1)
    poses, points = _three_photos(np.random.default_rng(1), 1)
    pixels = np.stack([camera.img_from_cam((pose[:, :3] @ points[0] + pose[:, 3])[None])[0] for pose in poses])
    found = triangulate_track(pixels, poses, [camera] * 3)
    np.testing.assert_allclose(found.xyz, points[0], atol=1e-8)
    assert found.inliers.all()
    pixels[2] += [0.0, 30.0]  # across the epipolar lines (the photos are side by side): no depth explains it
    found = triangulate_track(pixels, poses, [camera] * 3)
    np.testing.assert_allclose(found.xyz, points[0], atol=1e-6)
    assert found.inliers.tolist() == [True, True, False]
    assert triangulate_track(pixels[1:], poses[1:], [camera] * 2) is None  # two observations that disagree
    assert triangulate_track(pixels[:2], poses[:2], [camera] * 2, min_angle_deg=20.0) is None  # rays meet at a few degrees


def test_aligned_model_with_the_fitted_cameras_carries_its_points_to_them():
    """A meta-image whose SfM focal length is 6% long (its points and poses consistent with that) registered with the
    focal length and poses the photos really have: moved rigidly, its points reproject pixels off under those cameras;
    triangulated again, they are the true points and reproject exactly. An observation 30 px off leaves its track."""
    rng = np.random.default_rng(5)
    world_from_meta = Sim3.from_parts(2.0, Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix(), [1.0, 2.0, -1.0])
    true_camera = pycolmap.Camera(model="SIMPLE_RADIAL", width=640, height=480, params=[500.0, 320.0, 240.0, 0.0], camera_id=1)
    poses, points = _three_photos(rng)
    model = _model_with_tracks(poses, points, true_camera)  # the photos' keypoints, from the true cameras
    long_focal = 1.06
    sfm = pycolmap.Reconstruction(model)  # the SfM's version: focal 6% long, depths 6% longer along each optical axis
    sfm.cameras[1].params = [500.0 * long_focal, 320.0, 240.0, 0.0]
    for point_id in sfm.point3D_ids():
        point = sfm.points3D[point_id]
        point.xyz = point.xyz * np.array([1.0, 1.0, long_focal])  # the middle photo's axis is z: its pixels are unchanged
    true_world = {f"{i}.jpg": world_from_meta.move_camera(pose) for i, pose in enumerate(poses, start=1)}

    rigid = aligned_reconstruction(sfm, world_from_meta, {1: 1.0 / long_focal}, true_world)
    assert np.median(_reprojection_errors(rigid)) > 1.0
    carried = aligned_reconstruction(sfm, world_from_meta, {1: 1.0 / long_focal}, true_world, retriangulate=True)
    assert carried.num_points3D() == len(points) and _reprojection_errors(carried).max() < 1e-6
    for point_id, point in carried.points3D.items():
        np.testing.assert_allclose(point.xyz, world_from_meta.apply(model.points3D[point_id].xyz[None])[0], atol=1e-6)
    for name, pose in true_world.items():
        np.testing.assert_allclose(carried.find_image_with_name(name).cam_from_world().matrix(), pose, atol=1e-9)

    first = next(iter(sfm.point3D_ids()))
    element = sfm.points3D[first].track.elements[0]
    sfm.images[element.image_id].points2D[element.point2D_idx].xy += [0.0, 30.0]
    carried = aligned_reconstruction(sfm, world_from_meta, {1: 1.0 / long_focal}, true_world, retriangulate=True)
    assert carried.points3D[first].track.length() == 2 and carried.num_points3D() == len(points)
