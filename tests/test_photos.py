"""Real-photo path: photo folder -> meta-images (pycolmap SfM), camera alignment, Strecha cameras, the
real-photo scene builder, and one sentence for each bad input.

The photos are rendered by the synthetic generator at a size SIFT can use (320x240, no in-the-wild look),
so the suite needs nothing outside the repository.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pycolmap
import pytest
from PIL import Image

from sg_nerfstudio.geometry.alignment import AlignmentError, align_cameras
from sg_nerfstudio.geometry.meta_image import load_meta_image
from sg_nerfstudio.geometry.sim3 import Sim3
from sg_nerfstudio.photos.coarse_reference import CoarseModelSettings, new_view_poses, smooth_field
from sg_nerfstudio.photos.collection import prepare_photos
from sg_nerfstudio.photos.scene import RealSceneError, RealSceneSettings, build_real_scene, split_photos
from sg_nerfstudio.photos.sfm import SfmSettingsError
from sg_nerfstudio.photos.strecha import CameraFileError, read_strecha_camera
from sg_nerfstudio.scripts.make_scene import main as make_scene_main
from sg_nerfstudio.scripts.meta_images import main as meta_images_main
from sg_nerfstudio.synthetic import SceneConfig, generate_scene
from sg_nerfstudio.synthetic.building import BuildingConfig


@pytest.fixture(scope="module")
def photo_scene(tmp_path_factory) -> Path:
    """A synthetic scene whose 8 front photos (320x240, plain look) overlap like a walk along a facade."""
    config = SceneConfig(
        building=BuildingConfig(n_gaussians=4000, window_cols=4), reference_size=(48, 36), n_ring=6, n_aerial=0,
        meta_images=("front:8",), photo_size=(320, 240), appearance_strength=0.0, occluder_rate=0.0, distortion=0.0,
        n_sparse_points=800,
    )
    output = tmp_path_factory.mktemp("photos") / "scene"
    generate_scene(config, output)
    return output


@pytest.fixture(scope="module")
def photos(photo_scene) -> Path:
    return photo_scene / "meta" / "front" / "images"


def noise_photo(path: Path, seed: int, size=(320, 240)) -> None:
    rng = np.random.default_rng(seed)
    Image.fromarray(rng.integers(0, 256, (size[1], size[0], 3), dtype=np.uint8)).save(path)


def test_meta_images_from_a_photo_folder(photos, tmp_path, capsys):
    folder = tmp_path / "photos"
    shutil.copytree(photos, folder)
    noise_photo(folder / "zz-noise.png", 0)  # a photo of nothing: reported, not registered
    (folder / "IMG_0001.HEIC").write_bytes(b"not read")  # formats SfM here does not take: named, not read
    (folder / ".DS_Store").write_bytes(b"hidden")
    before = sorted((p.name, p.stat().st_size) for p in folder.iterdir())
    output = tmp_path / "metas"
    assert meta_images_main([str(folder), "--output", str(output), "--threads", "1"]) == 0
    assert sorted((p.name, p.stat().st_size) for p in folder.iterdir()) == before  # the input is only read
    record = json.loads((output / "meta_images.json").read_text())
    assert record["pairing"] == "exhaustive"
    assert [m["photos"] for m in record["models"]] == [8]
    assert [u["photo"] for u in record["unregistered"]] == ["zz-noise.png"]
    meta = load_meta_image(output / "meta-00")  # the layout ns-register-meta reads
    assert len(meta.photos) == 8
    err = capsys.readouterr().err
    assert "meta-00" in err and "zz-noise.png" in err
    assert "1 file(s) in" in err and "are not JPEG or PNG and were not read: IMG_0001.HEIC (convert" in err


def test_retrieval_pairs_above_the_exhaustive_limit(photos, tmp_path):
    output = tmp_path / "metas"
    assert meta_images_main([str(photos), "--output", str(output), "--threads", "1", "--exhaustive-limit", "4", "--retrieval-neighbours", "3"]) == 0
    record = json.loads((output / "meta_images.json").read_text())
    assert record["pairing"].startswith("retrieval (3 most similar")
    assert sum(m["photos"] for m in record["models"]) >= 6


def test_prepare_photos_applies_exif_grey_and_cap(tmp_path):
    source = tmp_path / "in"
    source.mkdir()
    wide = Image.fromarray(np.tile(np.arange(400, dtype=np.uint8)[None, :, None], (200, 1, 3)))
    exif = wide.getexif()
    exif[0x0112] = 6  # orientation: rotate 90 degrees clockwise to view
    wide.save(source / "rotated.jpg", exif=exif)
    Image.fromarray(np.zeros((50, 80), np.uint8)).save(source / "grey.png")
    ramp = np.tile(np.linspace(0, 65535, 80).astype(np.uint16)[None, :], (50, 1))
    Image.fromarray(ramp).save(source / "grey16.png")  # a 16-bit grey PNG (scans, HDR merges)
    assert Image.open(source / "grey16.png").mode in ("I;16", "I")
    prepared = prepare_photos(sorted(source.iterdir()), tmp_path / "out", max_size=100)
    by_name = {p.name: p for p in prepared}
    assert by_name["rotated.jpg"].size == (50, 100)  # upright (portrait) and capped at 100
    assert by_name["grey.png"].size == (80, 50)  # small photos are not enlarged
    assert Image.open(tmp_path / "out" / "grey.png").mode == "RGB"
    grey16 = np.asarray(Image.open(tmp_path / "out" / "grey16.png"))
    assert grey16.shape == (50, 80, 3)  # its tones kept at 8 bits, not clipped to white
    np.testing.assert_array_equal(grey16[0, :, 1], np.rint(ramp[0] / 257.0).astype(np.uint8))


@pytest.mark.parametrize("case", ["missing", "a-file", "empty", "two", "truncated", "no-model", "camera-model", "max-size", "threads"])
def test_bad_photo_folders_are_one_sentence(case, tmp_path, capfd):
    folder = tmp_path / "photos"
    if case == "a-file":
        folder.write_text("not a folder")
    elif case != "missing":
        folder.mkdir()
    if case == "truncated":
        noise_photo(folder / "a.jpg", 0)
        data = (folder / "a.jpg").read_bytes()
        (folder / "a.jpg").write_bytes(data[: len(data) // 2])
        for seed in (1, 2):
            noise_photo(folder / f"noise{seed}.png", seed)
    if case == "two":
        for seed in range(2):
            noise_photo(folder / f"noise{seed}.png", seed)
    if case in ("no-model", "camera-model", "max-size", "threads"):
        for seed in range(3):
            noise_photo(folder / f"noise{seed}.png", seed)
    output = tmp_path / "metas"
    extra = {"camera-model": ["--camera-model", "OPENCV_TYPO"], "max-size": ["--max-size", "-3"]}.get(case, [])
    threads = "0" if case == "threads" else "1"
    assert meta_images_main([str(folder), "--output", str(output), "--threads", threads, *extra]) == 1
    err = capfd.readouterr().err  # file-descriptor level: COLMAP's glog writes there, not through sys.stderr
    expected = {"missing": "does not exist", "a-file": f"Photo folder {folder} is a file; expected a directory", "empty": "holds no JPEG or PNG", "two": f"{folder} holds 2 JPEG or PNG photo(s); expected at least 3", "truncated": "a.jpg could not be decoded",
                "no-model": "formed no model", "camera-model": "'OPENCV_TYPO' is not a COLMAP camera model; expected one of SIMPLE_PINHOLE",
                "max-size": "--max-size must be 0 (photos as they are) or a long side in pixels, got -3.", "threads": "--threads must be 1 or more"}[case]
    assert expected in err and "Traceback" not in err
    assert "Failed to create any sparse model" not in err and "No images with matches" not in err  # the mapper's own lines
    assert not output.exists() and not list(tmp_path.glob(".metas*"))


@pytest.mark.parametrize("layout", ["the-folder", "its-parent"])
def test_an_output_that_would_replace_the_photos_is_refused_and_they_stay(layout, tmp_path, capfd):
    """--overwrite replaces the output directory whole; where that directory is the photo folder or holds it, the
    command stops before anything is read or written."""
    folder = tmp_path / "photos"
    folder.mkdir()
    for seed in range(3):
        noise_photo(folder / f"noise{seed}.png", seed)
    (folder / "notes.txt").write_text("the user's notes")
    before = {path: path.read_bytes() for path in tmp_path.rglob("*") if path.is_file()}
    output = folder if layout == "the-folder" else tmp_path
    assert meta_images_main([str(folder), "--output", str(output), "--overwrite", "--threads", "1"]) == 1
    err = capfd.readouterr().err
    relation = "is" if layout == "the-folder" else "holds"
    assert f"Output directory {output} {relation} the input {folder}; expected a directory apart from the inputs" in err
    assert err.strip().count("\n") == 0 and "Traceback" not in err
    assert {path: path.read_bytes() for path in tmp_path.rglob("*") if path.is_file()} == before


def random_poses(rng, count: int, collinear: bool) -> np.ndarray:
    poses = []
    for index in range(count):
        rotation = Sim3.random(rng, 20.0, 0.0, 0.0).rotation
        centre = np.array([index, 0.0, 0.0]) if collinear else rng.normal(size=3)
        poses.append(np.concatenate([rotation, (-rotation @ centre)[:, None]], axis=1))
    return np.stack(poses)


@pytest.mark.parametrize("collinear", [False, True])
def test_align_cameras_recovers_a_similarity(collinear):
    rng = np.random.default_rng(3)
    source = random_poses(rng, 3, collinear)
    truth = Sim3.random(rng, 120.0, 5.0, 0.8)
    target = np.stack([truth.move_camera(p) for p in source])
    aligned = align_cameras(source, target)
    np.testing.assert_allclose(np.asarray(aligned.transform), np.asarray(truth), atol=1e-9)
    assert aligned.rotation_residual_deg.max() < 1e-4 and aligned.centre_residual.max() < 1e-9
    with pytest.raises(AlignmentError, match="distinct centres"):
        align_cameras(source[:1], target[:1])


def test_strecha_camera_file(tmp_path):
    rotation_c2w = Sim3.random(np.random.default_rng(1), 90.0, 0.0, 0.0).rotation
    centre = np.array([1.0, -2.0, 3.0])
    lines = ["2000 0 1500", "0 2000 1000", "0 0 1", "0 0 0", *[" ".join(map(str, row)) for row in rotation_c2w], "1 -2 3", "3000 2000"]
    path = tmp_path / "a.jpg.camera"
    path.write_text("\n".join(lines) + "\n")
    camera = read_strecha_camera(path)
    point = np.array([0.5, 0.2, 9.0])
    pose = camera.cam_from_world()
    np.testing.assert_allclose(pose[:, :3] @ point + pose[:, 3], rotation_c2w.T @ (point - centre), atol=1e-12)
    colmap = camera.colmap_camera(300, 200)
    np.testing.assert_allclose(colmap.params, [200, 200, 150, 100])
    path.write_text("\n".join(lines[:5]))
    with pytest.raises(CameraFileError, match="Strecha format"):
        read_strecha_camera(path)
    path.write_text("\n".join([lines[0], lines[1], lines[2], lines[3], lines[4], lines[5], lines[6], "nan -2 3", lines[8]]) + "\n")
    with pytest.raises(CameraFileError, match="holds values that are not finite"):  # passed the rotation check before
        read_strecha_camera(path)


def test_ground_truth_cameras_turned_to_the_sfm_principal_point():
    """A calibrated camera whose principal point is off the image centre (as Strecha's fountain-P11: 15 / 17 px of 3072),
    turned to the centred principal point an SfM holds: the scene point the true camera sees at the image centre is
    seen there by the turned camera with the centred intrinsics, points near it within a tenth of a pixel, the centre
    does not move, and the turn is the offset's angle; with the principal points equal nothing changes."""
    from sg_nerfstudio.geometry.sim3 import rotation_angle_deg
    from sg_nerfstudio.photos.scene import at_principal_point_of

    true_camera = pycolmap.Camera(model="PINHOLE", width=640, height=427, params=[575.0, 576.0, 316.8, 209.8])
    sfm_camera = pycolmap.Camera(model="SIMPLE_RADIAL", width=640, height=427, params=[575.0, 320.0, 213.5, 0.0])
    pose = Sim3.random(np.random.default_rng(2), 90.0, 3.0, 0.0).matrix[:3]
    turned = at_principal_point_of(pose, true_camera, sfm_camera)
    centred = pycolmap.Camera(model="PINHOLE", width=640, height=427, params=[575.0, 576.0, 320.0, 213.5])
    centre = -pose[:, :3].T @ pose[:, 3]
    np.testing.assert_allclose(-turned[:, :3].T @ turned[:, 3], centre, atol=1e-12)
    pixels = np.array([[320.0, 213.5], [330.0, 220.0], [300.0, 200.0]])
    rays = np.column_stack([true_camera.cam_from_img(pixels), np.ones(3)])
    points = (pose[:, :3].T @ (10.0 * rays).T).T + centre  # world points 10 units along the true camera's rays
    seen = centred.img_from_cam((turned[:, :3] @ points.T).T + turned[:, 3])
    np.testing.assert_allclose(seen[0], pixels[0], atol=1e-9)
    assert np.abs(seen - pixels).max() < 0.1
    offset = np.hypot(np.arctan(3.2 / 575.0), np.arctan(3.7 / 576.0))
    assert abs(np.radians(rotation_angle_deg(turned[:, :3] @ pose[:, :3].T)) - offset) < 1e-5
    np.testing.assert_allclose(at_principal_point_of(pose, centred, sfm_camera), pose, atol=1e-12)


def test_split_along_the_path():
    names = [f"{i:02d}" for i in range(11)]
    reference, metas = split_photos(names, 2, 3)
    assert reference == ["00", "02", "04", "06", "08", "10"]
    assert metas == [["01", "03", "05"], ["05", "07", "09"]]
    with pytest.raises(RealSceneError, match="at least 3 reference photos"):
        split_photos(names[:4], 2, 3)


def colmap_cameras(scene: Path, output: Path) -> Path:
    """The generator's true cameras of the front photos as a COLMAP model (the --cameras input)."""
    record = json.loads((scene / "scene.json").read_text())["meta_images"][0]["photos"]
    meta = pycolmap.Reconstruction(str(scene / "meta" / "front" / "sparse" / "0"))
    model = pycolmap.Reconstruction()
    for index, photo in enumerate(record, start=1):
        image = next(im for im in meta.images.values() if im.name == photo["name"])
        camera = pycolmap.Camera(meta.cameras[image.camera_id].todict())
        camera.camera_id = index
        model.add_camera_with_trivial_rig(camera)
        pose = np.array(photo["cam_from_world_reference"])[:3]
        model.add_image_with_trivial_frame(pycolmap.Image(name=photo["name"], camera_id=index, image_id=index),
                                           pycolmap.Rigid3d(pycolmap.Rotation3d(pose[:, :3]), pose[:, 3]))
    output.mkdir()
    model.write_binary(str(output))
    return output


def test_real_scene_builder_writes_the_bench_layout(photo_scene, photos, tmp_path, monkeypatch):
    from sg_nerfstudio.bench.layout import read_benchmark
    from sg_nerfstudio.photos import scene as scene_module

    threads = []  # every SfM of the builder on one thread: pycolmap's multi-threaded mapper gives another scene each run
    reconstruct = scene_module.reconstruct
    monkeypatch.setattr(scene_module, "reconstruct", lambda *args, **kwargs: threads.append(args[3].threads) or reconstruct(*args, **kwargs))

    cameras = colmap_cameras(photo_scene, tmp_path / "cameras")
    settings = RealSceneSettings(
        reference_every=3, meta_size=4, reference_size=320, photo_size=320, appearance_strength=0.3, occluder_rate=0.0, min_reference_points=50,
    )
    output = tmp_path / "bench" / "scene"
    manifest = build_real_scene(photos, output, settings, cameras)
    assert manifest["solution"].startswith("COLMAP model")
    (scene,) = read_benchmark(tmp_path / "bench")
    assert len(scene.metas) == 1 and len(manifest["reference"]["images"]) == 4
    for meta in manifest["meta_images"]:
        assert meta["written"], meta
        # the SfM cameras of the meta-image, moved by the ground truth, are the given cameras to SfM precision
        assert meta["gt_residual_rotation_deg_max"] < 1.0
        truth_record = json.loads((output / meta["path"] / "gt_transform.json").read_text())
        # the given cameras are the generator's with the SfM's centred principal point: no turn, the plain alignment
        assert max(truth_record["principal_point_turn_deg"]) < 1e-6
        np.testing.assert_allclose(truth_record["given_principal_point"]["matrix"], truth_record["matrix"], atol=1e-9)
        # the meta-image's own points, triangulated again with the given cameras, agree with the camera-based truth
        point_based = truth_record["point_based"]
        assert point_based["inliers"] >= 20 and point_based["delta_R_deg"] < 1.0 and point_based["delta_T"] < 0.05, point_based
        assert scene.metas[0].truth_disagreement == {"dR": point_based["delta_R_deg"], "dT": point_based["delta_T"]}
    truth = scene.metas[0].ground_truth
    assert 0 < truth.scale and np.isfinite(np.asarray(truth)).all()
    assert not (output / "work").exists()
    assert threads and set(threads) == {1}, threads


def test_real_scene_bad_inputs(photos, tmp_path, capsys):
    output = tmp_path / "scene"
    cameras = tmp_path / "cameras"
    cameras.mkdir()
    assert make_scene_main(["--from-photos", str(photos), "--cameras", str(cameras), "--output", str(output)]) == 1
    assert "has no" in capsys.readouterr().err and not output.exists()
    assert make_scene_main(["--from-photos", str(photos), "--cameras", str(tmp_path / "gone"), "--output", str(output)]) == 1
    assert f"Cameras {tmp_path / 'gone'} does not exist; expected a COLMAP model directory or a folder of" in capsys.readouterr().err
    with pytest.raises(SfmSettingsError, match="--scene.meta-camera-model 'opencv' is not a COLMAP camera model"):
        build_real_scene(photos, output, RealSceneSettings(meta_camera_model="opencv"))
    settings = RealSceneSettings(reference_size=320, photo_size=320, min_reference_points=10**6)
    with pytest.raises(RealSceneError, match="to initialise the splat"):
        build_real_scene(photos, output, settings)
    assert not output.exists() and not list(tmp_path.glob(".scene*"))


def test_a_reference_without_3d_points_is_one_sentence(tiny_scene, tmp_path):
    from sg_nerfstudio.features import TeacherConfig
    from sg_nerfstudio.splat.datamanager import DatasetInputError
    from sg_nerfstudio.splat.training import cpu_config, train

    reference = tmp_path / "reference"
    shutil.copytree(tiny_scene / "reference", reference)
    model_dir = reference / "colmap" / "sparse" / "0"
    model = pycolmap.Reconstruction(str(model_dir))
    for point_id in list(model.points3D):
        model.delete_point3D(point_id)
    model.write_binary(str(model_dir))
    config = cpu_config(reference, tmp_path / "runs", 2, TeacherConfig(name="offline", input_size=64, cache_dir=tmp_path / "cache"))
    with pytest.raises(DatasetInputError, match="has 0 3D points"):
        train(config)


@pytest.mark.parametrize("layout", ["sparse/0", "none"])
def test_a_dataset_without_the_model_colmap_looks_for_is_refused_before_anything_is_written(layout, tiny_scene, tmp_path):
    """`ns-train ... colmap --data DIR` on COLMAP's own layout (DIR/sparse/0, what sg-meta-images writes) names the flag
    that reads it, and writes no run directory (nerfstudio saves config.yml before it builds the datamanager)."""
    from sg_nerfstudio.features import TeacherConfig
    from sg_nerfstudio.splat.datamanager import DatasetInputError
    from sg_nerfstudio.splat.training import cpu_config

    dataset = tmp_path / "dataset"
    shutil.copytree(tiny_scene / "reference" / "images", dataset / "images")
    if layout != "none":
        shutil.copytree(tiny_scene / "reference" / "colmap" / "sparse" / "0", dataset / layout)
    runs = tmp_path / "runs"
    config = cpu_config(dataset, runs, 2, TeacherConfig(name="offline", input_size=64, cache_dir=tmp_path / "cache"))
    expected = {
        "sparse/0": rf"No COLMAP model in {dataset}/colmap/sparse/0; this folder has one in {dataset}/sparse/0: add `--colmap-path sparse/0` after `colmap`\.",
        "none": rf"No COLMAP model in {dataset}/colmap/sparse/0; expected cameras, images and points3D",
    }[layout]
    with pytest.raises(DatasetInputError, match=expected):
        config.save_config()
    assert not runs.exists()


def test_a_truncated_training_image_is_refused_before_anything_is_written(tiny_scene, tmp_path):
    """nerfstudio's datamanager would decode it with a traceback, after ns-train wrote the run's config.yml."""
    from sg_nerfstudio.features import TeacherConfig
    from sg_nerfstudio.splat.datamanager import DatasetInputError
    from sg_nerfstudio.splat.training import cpu_config

    reference = tmp_path / "reference"
    shutil.copytree(tiny_scene / "reference", reference)
    cut = reference / "images" / "ring_003.png"
    cut.write_bytes(cut.read_bytes()[: cut.stat().st_size // 2])
    runs = tmp_path / "runs"
    config = cpu_config(reference, runs, 2, TeacherConfig(name="offline", input_size=64, cache_dir=tmp_path / "cache"))
    with pytest.raises(DatasetInputError, match=rf"Image {cut} of the COLMAP model .* could not be read as an image .*; expected a complete JPEG or PNG"):
        config.save_config()
    assert not runs.exists()


def test_a_coarse_model_reference_renders_the_photos_model_and_holds_measured_pairs(photo_scene, photos, tmp_path):
    from sg_nerfstudio.bench.gap import measure_gap
    from sg_nerfstudio.bench.layout import read_benchmark
    from sg_nerfstudio.bench.pairs import read_pairs

    cameras = colmap_cameras(photo_scene, tmp_path / "cameras")
    settings = RealSceneSettings(
        reference_every=3, meta_size=4, reference_size=320, photo_size=160, appearance_strength=0.3, occluder_rate=0.0,
        min_reference_points=10, reference_kind="coarse-model", coarse=CoarseModelSettings(train_size=320, steps=300),
    )
    output = tmp_path / "bench" / "scene"
    manifest = build_real_scene(photos, output, settings, cameras, measure_pairs=measure_gap)
    reference = manifest["reference"]
    # the four reference photos' cameras and three lifted views between each two neighbours, all rendered from the model
    assert reference["kind"] == "coarse-model" and len(reference["images"]) == 4 + 3 * 3
    assert sorted(p.name for p in (output / "reference" / "images").iterdir()) == sorted(reference["images"])
    model = pycolmap.Reconstruction(str(output / "reference" / "colmap" / "sparse" / "0"))
    assert model.num_reg_images() == 13 and model.num_points3D() == reference["n_points3D"] >= 10
    assert reference["coarse_model"]["gaussians"] > 0 and reference["coarse_model"]["scene_depth"] > 0
    # every meta photo has its render at its size; the builder measured them as bench.gap does
    pairs = read_pairs(output / "pairs")
    (meta,) = [m for m in manifest["meta_images"] if m["written"]]
    assert sorted(p.name for p in pairs) == sorted(Path(n).stem for n in meta["photos"])
    assert manifest["gap"]["measured"] and manifest["gap"]["pairs"] == len(pairs)
    (scene,) = read_benchmark(tmp_path / "bench")
    assert scene.metas[0].name == meta["name"]
    assert not (output / "work").exists()


def test_a_filtered_photo_reference_says_it_has_no_gap_measure(photo_scene, photos, tmp_path):
    settings = RealSceneSettings(reference_every=3, meta_size=4, reference_size=160, photo_size=160, occluder_rate=0.0, min_reference_points=10)
    manifest = build_real_scene(photos, tmp_path / "scene", settings, colmap_cameras(photo_scene, tmp_path / "cameras"))
    assert manifest["reference"]["kind"] == "filtered-photos" and not manifest["gap"]["measured"]
    assert not (tmp_path / "scene" / "pairs").exists()


def test_the_displacement_field_is_smooth_seeded_and_of_its_rms():
    rng = np.random.default_rng(0)
    points = rng.uniform(-5, 5, size=(20000, 3))
    field = smooth_field(points, rms=0.1, wavelength=2.0, seed=3)
    assert field.shape == points.shape
    np.testing.assert_allclose(np.sqrt((field ** 2).mean(axis=0)), 0.1, rtol=0.25)
    np.testing.assert_array_equal(field, smooth_field(points, rms=0.1, wavelength=2.0, seed=3))
    assert not np.allclose(field, smooth_field(points, rms=0.1, wavelength=2.0, seed=4))
    # neighbours move together: a step of a hundredth of the wavelength changes the displacement by a few percent
    near = smooth_field(points + 0.02, rms=0.1, wavelength=2.0, seed=3)
    assert np.abs(near - field).max() < 0.1 * np.abs(field).max()


def test_new_views_sit_between_their_neighbours_lifted_and_look_where_they_looked():
    # two cameras 2 apart along x, looking along +z (OpenCV: y down, so world up is -y), the scene 4 ahead
    poses = np.stack([np.concatenate([np.eye(3), -np.array([[x], [0.0], [0.0]])], axis=1) for x in (-1.0, 1.0)])
    views = new_view_poses(poses, depth=np.array([4.0, 4.0]), lift=0.5, per_gap=3)
    assert views.shape == (3, 3, 4)
    for view, x in zip(views, (-0.5, 0.0, 0.5)):
        rotation, centre = view[:, :3], -view[:, :3].T @ view[:, 3]
        np.testing.assert_allclose(centre, [x, -0.5, 0.0], atol=1e-12)  # evenly spaced, 0.5 up
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
        aim = np.array([x, 0.0, 4.0]) - centre
        np.testing.assert_allclose(rotation[2], aim / np.linalg.norm(aim), atol=1e-12)  # looks at what its neighbours saw
        assert abs(rotation[0] @ [0.0, 1.0, 0.0]) < 1e-12  # no roll: its x axis stays horizontal


def test_coarse_model_settings_out_of_range_are_one_sentence(photos, tmp_path, capsys):
    output = tmp_path / "scene"
    args = ["--from-photos", str(photos), "--output", str(output), "--scene.reference-kind", "coarse-model", "--scene.coarse.train-size", "4"]
    assert make_scene_main(args) == 1
    assert "Scene setting --scene.coarse.train-size must be" in capsys.readouterr().err and not output.exists()
    with pytest.raises(RealSceneError, match="--scene.coarse.tint must be"):
        build_real_scene(photos, output, RealSceneSettings(coarse=CoarseModelSettings(tint=(1.0, -1.0, 1.0))))


def test_renders_sift_cannot_triangulate_are_one_sentence_naming_the_settings(tmp_path, monkeypatch):
    from sg_nerfstudio.initialisers.reference_cloud import ReferenceSourceError
    from sg_nerfstudio.photos import scene as scene_module

    def no_pair(source, *args, **kwargs):
        raise ReferenceSourceError(f"No pair of reference images in {source.colmap_path} has 15 verified SIFT matches.")

    monkeypatch.setattr(scene_module, "build_reference_cloud", no_pair)
    views = [("a.png", pycolmap.Camera(model="PINHOLE", width=64, height=48, params=[50.0, 50.0, 32.0, 24.0]), np.eye(4)[:3])]
    with pytest.raises(RealSceneError, match=r"^Triangulating the coarse model's renders gave no 3D points: .*--scene.coarse.steps"):
        scene_module.triangulate_posed(tmp_path, tmp_path / "work", views, 100, "the coarse model's renders", scene_module.RENDERS_HINT)
