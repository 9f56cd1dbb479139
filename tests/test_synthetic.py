"""The synthetic scene generator: COLMAP models, ground truth, sparse points, determinism, bad inputs."""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from sg_nerfstudio.scripts.make_scene import main as make_scene_main
from sg_nerfstudio.synthetic import PRESETS, SceneGenerationError, generate_scene


def load(path: Path) -> pycolmap.Reconstruction:
    return pycolmap.Reconstruction(str(path))


def test_models_load_with_pycolmap_and_images_exist(tiny_scene):
    manifest = json.loads((tiny_scene / "scene.json").read_text())
    reference = load(tiny_scene / "reference" / "colmap" / "sparse" / "0")
    assert reference.num_images() == manifest["reference"]["n_images"] == 16
    assert reference.num_points3D() > 50
    for image in reference.images.values():
        assert (tiny_scene / "reference" / "images" / image.name).is_file()
    meta = load(tiny_scene / "meta" / "front" / "sparse" / "0")
    assert meta.num_images() == 5 and meta.num_cameras() == 5  # one camera per photo
    sizes = {(c.width, c.height) for c in meta.cameras.values()}
    assert len(sizes) > 1  # photos get their own sizes (and orientations) around the base size
    assert any(height > width for width, height in sizes)
    for image in meta.images.values():
        photo = tiny_scene / "meta" / "front" / "images" / image.name
        import cv2

        pixels = cv2.imread(str(photo))
        camera = meta.cameras[image.camera_id]
        assert pixels.shape[:2] == (camera.height, camera.width)


def test_models_load_with_nerfstudio_colmap_dataparser(tiny_scene):
    from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParserConfig

    outputs = ColmapDataParserConfig(data=tiny_scene / "reference", load_3D_points=True).setup().get_dataparser_outputs("train")
    assert len(outputs.image_filenames) > 0
    assert all(Path(f).is_file() for f in outputs.image_filenames)
    assert outputs.metadata["points3D_xyz"].shape[0] > 50
    meta_outputs = ColmapDataParserConfig(
        data=tiny_scene / "meta" / "front", colmap_path=Path("sparse/0"), eval_mode="all"
    ).setup().get_dataparser_outputs("train")
    assert len(meta_outputs.image_filenames) == 5


def test_ground_truth_transform_maps_meta_cameras_onto_rendered_cameras(tiny_scene):
    manifest = json.loads((tiny_scene / "scene.json").read_text())
    record = json.loads((tiny_scene / "meta" / "front" / "gt_transform.json").read_text())
    matrix = np.array(record["matrix"])
    scale = record["scale"]
    rotation = matrix[:3, :3] / scale
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    meta = load(tiny_scene / "meta" / "front" / "sparse" / "0")
    truth = {p["name"]: np.array(p["cam_from_world_reference"]) for p in manifest["meta_images"][0]["photos"]}
    assert len(truth) == meta.num_images()
    for image in meta.images.values():
        cam_from_meta = image.cam_from_world().matrix()
        centre_meta = -cam_from_meta[:3, :3].T @ cam_from_meta[:3, 3]
        centre_ref = scale * rotation @ centre_meta + matrix[:3, 3]
        world_from_cam_ref = rotation @ cam_from_meta[:3, :3].T
        expected = truth[image.name]
        np.testing.assert_allclose(world_from_cam_ref, expected[:3, :3].T, atol=1e-6)
        np.testing.assert_allclose(centre_ref, -expected[:3, :3].T @ expected[:3, 3], atol=1e-6)


def test_meta_frame_is_a_nontrivial_similarity(tiny_scene):
    record = json.loads((tiny_scene / "meta" / "front" / "gt_transform.json").read_text())
    assert record["scale"] != pytest.approx(1.0, abs=1e-3)
    assert not np.allclose(np.array(record["matrix"])[:3, :3], np.eye(3) * record["scale"], atol=1e-2)


@pytest.mark.parametrize("model", ["reference/colmap/sparse/0", "meta/front/sparse/0"])
def test_sparse_points_reproject_inside_images_onto_their_keypoints(tiny_scene, model):
    recon = load(tiny_scene / model)
    assert recon.num_points3D() > 20
    for point in recon.points3D.values():
        assert point.track.length() >= 2
        for element in point.track.elements:
            image = recon.images[element.image_id]
            camera = recon.cameras[image.camera_id]
            projected = image.project_point(point.xyz)
            assert projected is not None
            assert 0 <= projected[0] < camera.width and 0 <= projected[1] < camera.height
            np.testing.assert_allclose(projected, image.points2D[element.point2D_idx].xy, atol=1e-3)


def test_distorted_photos_are_described_by_their_models(tiny_scene):
    manifest = json.loads((tiny_scene / "scene.json").read_text())
    models = {p["camera_model"] for p in manifest["meta_images"][0]["photos"]}
    assert models <= {"PINHOLE", "SIMPLE_RADIAL"}
    occluded = [p["occluded_fraction"] for p in manifest["meta_images"][0]["photos"]]
    assert any(f > 0.05 for f in occluded)


def test_occluders_are_textured_like_real_ones():
    """Inside an occluder the image has edges (clothing, foliage, panels), not a flat colour."""
    import cv2

    from sg_nerfstudio.synthetic.appearance import draw_occluders

    flat = np.full((240, 320, 3), 0.5)
    image, coverage = draw_occluders(flat, 0.4, np.random.default_rng(0))
    assert 0.3 <= coverage <= 0.8
    covered = np.any(np.abs(image - flat) > 1e-9, axis=2).astype(np.uint8)
    interior = cv2.erode(covered, np.ones((7, 7), np.uint8)) > 0  # away from the shapes' outlines
    grey = image.mean(axis=2).astype(np.float32)
    gradient = np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1))
    textured = gradient[interior] > 0.05
    assert interior.sum() > 0.2 * interior.size and textured.mean() > 0.3


@pytest.mark.parametrize("unique_detail, repeats", [(0.0, True), (1.0, False)])
def test_without_unique_detail_a_facade_repeats_window_to_window(unique_detail, repeats):
    """`unique_detail` 0 (no decals, no weathering) makes a soft facade periodic with its window columns: the case of
    a registration one window away. At the default no window looks like its neighbour."""
    from sg_nerfstudio.synthetic.building import BuildingConfig, landmark_surfaces

    config = BuildingConfig(unique_detail=unique_detail)
    rear = next(s for s in landmark_surfaces(config) if s.name == "body_rear")
    column = config.width / max(config.window_cols - 2, 2)  # the rear facade's window pitch (`landmark_surfaces`)
    u, v = np.meshgrid(np.linspace(0.5, config.width - column - 0.5, 120), np.linspace(0.5, config.height - 0.5, 40))
    uv = np.stack([u.ravel(), v.ravel()], axis=1)
    difference = np.abs(rear.pattern(uv, 0.3) - rear.pattern(uv + [column, 0.0], 0.3)).mean()
    assert (difference < 1e-9) == repeats
    assert repeats or difference > 0.05


def digest(directory: Path) -> str:
    h = hashlib.sha256()
    for path in sorted(p for p in directory.rglob("*") if p.is_file() and p.name != "scene.json"):
        h.update(path.relative_to(directory).as_posix().encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def test_same_seed_gives_identical_files(tmp_path, tiny_scene):
    config = replace(PRESETS["tiny"], occluder_rate=0.6)
    generate_scene(config, tmp_path / "again")
    assert digest(tmp_path / "again") == digest(tiny_scene)
    generate_scene(replace(config, seed=1), tmp_path / "other")
    assert digest(tmp_path / "other") != digest(tiny_scene)


def test_bad_settings_fail_with_one_sentence_and_leave_nothing(tmp_path, capsys):
    with pytest.raises(SceneGenerationError, match="at least 3 photos"):
        generate_scene(replace(PRESETS["tiny"], meta_images=("front:2",)), tmp_path / "x")
    with pytest.raises(SceneGenerationError, match="SIDE:N_PHOTOS"):
        generate_scene(replace(PRESETS["tiny"], meta_images=("top:5",)), tmp_path / "x")
    with pytest.raises(SceneGenerationError, match="one meta-image"):
        generate_scene(replace(PRESETS["tiny"], meta_images=("front:5", "front:6")), tmp_path / "x")
    with pytest.raises(SceneGenerationError, match="--unique-detail must be a finite number of 0 or more, got nan"):
        generate_scene(replace(PRESETS["tiny"], building=replace(PRESETS["tiny"].building, unique_detail=float("nan"))), tmp_path / "x")
    assert list(tmp_path.iterdir()) == []

    existing = tmp_path / "existing"
    existing.mkdir()
    (existing / "keep.txt").write_text("user data")
    assert make_scene_main(["--preset", "tiny", "--output", str(existing)]) == 1
    assert "already exists" in capsys.readouterr().err
    assert (existing / "keep.txt").read_text() == "user data"
    assert make_scene_main(["--preset", "nonexistent", "--output", str(tmp_path / "y")]) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["existing"]


def test_scene_config_round_trips_through_scene_json(tiny_scene):
    from sg_nerfstudio.synthetic.generator import read_scene_config

    assert read_scene_config(tiny_scene) == replace(PRESETS["tiny"], occluder_rate=0.6)


@pytest.mark.parametrize("roof", ["pitched", "dome", "flat"])
def test_rays_hit_every_surface_where_its_samples_lie(roof):
    """A ray from outside the landmark through a surface sample meets that surface at the sample, with the
    sample's (u, v) and normal: the ray caster and the sampled point clouds describe the same landmark."""
    from sg_nerfstudio.synthetic.building import BuildingConfig, landmark_surfaces

    rng = np.random.default_rng(0)
    centre = np.array([70.0, -90.0, 60.0])  # metres, outside everything
    for surface in landmark_surfaces(BuildingConfig(roof=roof, towers=1)):
        samples = surface.sample(200, rng)
        t, uv, normals = surface.intersect(centre, samples.points - centre)
        reached = np.isfinite(t)  # rays through the far side of a dome meet its near side first
        assert reached.mean() > 0.45, surface.name
        hits_sample = reached & (np.abs(t - 1.0) < 1e-6)
        assert hits_sample.mean() > 0.45, surface.name
        np.testing.assert_allclose(uv[hits_sample], samples.uv[hits_sample], atol=1e-6)
        np.testing.assert_allclose(normals[hits_sample], samples.normals[hits_sample], atol=1e-6)
        assert np.all(t[reached] <= 1.0 + 1e-6), surface.name


def test_ray_cast_follows_the_distorted_camera():
    """A marked point of a wall appears where the SIMPLE_RADIAL model projects it (rays come from the camera
    model, not from resampling a pinhole render), and depth is the camera-z distance in scene units."""
    from sg_nerfstudio.synthetic.building import planar_patch
    from sg_nerfstudio.synthetic.capture import Shot, pinhole_camera
    from sg_nerfstudio.synthetic.raycast import raycast_shot

    mark = np.array([4.0, 10.0, -2.5])  # metres; the wall is the plane y = 10, uv = (x + 50, z + 50)

    def disc(uv, softness):
        inside = np.hypot(uv[:, 0] - (mark[0] + 50), uv[:, 1] - (mark[2] + 50)) < 0.6
        return np.repeat(np.where(inside, 0.0, 1.0)[:, None], 3, axis=1)

    wall = planar_patch("wall", [-50.0, 10.0, -50.0], [1.0, 0, 0], [0, 0, 1.0], (100.0, 100.0), disc)
    camera = pinhole_camera(1, 40, 30, 70.0, k1=0.3)
    looking_along_y = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])), np.zeros(3))
    metres_per_unit = 2.0
    image, depth = raycast_shot([wall], lambda albedo, normals: albedo, 0.04, Shot("w", camera, looking_along_y), np.zeros(3), metres_per_unit)
    np.testing.assert_allclose(depth, 10.0 / metres_per_unit, rtol=1e-9)

    darkness = 1.0 - image[..., 0]
    rows, cols = np.mgrid[0:30, 0:40] + 0.5  # COLMAP pixel centres
    centroid = np.array([(darkness * cols).sum(), (darkness * rows).sum()]) / darkness.sum()
    mark_camera = np.array([[mark[0], -mark[2], mark[1]]])
    expected = camera.img_from_cam(mark_camera)[0]
    pinhole = pinhole_camera(1, 40, 30, 70.0).img_from_cam(mark_camera)[0]
    assert np.linalg.norm(expected - pinhole) > 0.5  # the distortion moves the mark measurably
    np.testing.assert_allclose(centroid, expected, atol=0.15)
