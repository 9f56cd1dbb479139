"""SIFT + pycolmap initialisers: ground truth recovered on clean renders, failures reported, sg-init-baseline.

The scene here is the synthetic generator's layout and COLMAP writers (sg_nerfstudio.synthetic) with
three planes of multi-scale noise texture at 320x240, instead of a generated landmark: the tiny preset's
48x36 renders are too small for SIFT, and the default preset (whose meta-images both initialisers do
register, see the README) takes about 40 s to generate and a minute to initialise.
Photos have their own sizes and focal lengths, two use SIMPLE_RADIAL distortion, and the meta-image
lives in a random Sim(3) frame, as in the generator.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from sg_nerfstudio.initialisers import METHODS, Initialiser, InitialiserSettings, ReferenceSource, set_colmap_verbosity
from sg_nerfstudio.initialisers.reference_cloud import ReferenceSourceError
from sg_nerfstudio.geometry.meta_image import load_meta_image
from sg_nerfstudio.geometry.sim3 import Sim3, rotation_angle_deg
from sg_nerfstudio.registration.metrics import pose_errors
from sg_nerfstudio.scripts.init_baseline import main as baseline_main
from sg_nerfstudio.synthetic.capture import Shot, look_at, pinhole_camera
from sg_nerfstudio.synthetic.generator import RenderedShot, build_reconstruction, sim3_record, sparse_tracks, write_images

SKY = np.array([0.75, 0.82, 0.9])


def texture(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """[size, size, 3] float texture with structure at several scales (SIFT-friendly)."""
    image = np.zeros((size, size, 3), np.float32)
    for sigma, weight in ((1.5, 0.25), (4.0, 0.35), (12.0, 0.4)):
        noise = rng.random((size, size, 3)).astype(np.float32)
        blurred = cv2.GaussianBlur(noise, (0, 0), sigma)
        blurred = (blurred - blurred.mean()) / (blurred.std() + 1e-6)
        image += weight * blurred
    for _ in range(60):
        centre = tuple(int(v) for v in rng.integers(0, size, 2))
        cv2.circle(image, centre, int(rng.integers(4, 20)), tuple(float(v) for v in rng.normal(0, 1.5, 3)), -1)
    return np.clip(0.5 + 0.18 * image, 0, 1)


class Plane:
    """A textured rectangle origin + a * u + b * v, (a, b) in [0, 1]^2."""

    def __init__(self, origin, u, v, rng):
        self.origin, self.u, self.v = (np.asarray(x, float) for x in (origin, u, v))
        self.normal = np.cross(self.u, self.v)
        self.normal /= np.linalg.norm(self.normal)
        self.texture = texture(rng)

    def intersect(self, centre: np.ndarray, rays: np.ndarray):
        """Ray parameters t [N] (inf where missed) and texture coordinates [N, 2] for rays [N, 3]."""
        denominator = rays @ self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((self.origin - centre) @ self.normal) / denominator
        points = centre + t[:, None] * rays
        relative = points - self.origin
        ab = np.stack([relative @ self.u / (self.u @ self.u), relative @ self.v / (self.v @ self.v)], axis=1)
        hit = np.isfinite(t) & (t > 1e-6) & np.all((ab >= 0) & (ab <= 1), axis=1)
        return np.where(hit, t, np.inf), ab


def render(planes: list[Plane], shot: Shot) -> RenderedShot:
    camera = shot.camera
    columns, rows = np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5)
    pixels = np.stack([columns.ravel(), rows.ravel()], axis=1)
    rays_camera = np.hstack([camera.cam_from_img(pixels), np.ones((len(pixels), 1))])  # z = 1: t is the depth
    rotation = shot.cam_from_world.rotation.matrix()
    centre = -rotation.T @ shot.cam_from_world.translation
    rays = rays_camera @ rotation
    depth = np.full(len(pixels), np.inf)
    colour = np.tile(SKY, (len(pixels), 1)).astype(np.float32)
    for plane in planes:
        t, ab = plane.intersect(centre, rays)
        closer = t < depth
        size = plane.texture.shape[0] - 1
        shape = (camera.height, camera.width)
        sampled = cv2.remap(plane.texture, np.nan_to_num(ab[:, 0] * size).astype(np.float32).reshape(shape),
                            np.nan_to_num(ab[:, 1] * size).astype(np.float32).reshape(shape), cv2.INTER_LINEAR).reshape(-1, 3)
        colour[closer], depth[closer] = sampled[closer], t[closer]
    shape = (camera.height, camera.width)
    return RenderedShot(shot, colour.reshape(*shape, 3), depth.reshape(shape), {})


def make_textured_scene(root: Path, seed: int = 0, n_reference: int = 12, n_photos: int = 5) -> Path:
    """root/reference/{images, colmap/sparse/0} and root/meta/front/{images, sparse/0, gt_transform.json};
    reference units: median distance of the reference cameras to their centroid ~ 1."""
    rng = np.random.default_rng(seed)
    unit = 4.0
    planes = [
        Plane(np.array([-3.0, 0.0, 0.0]) / unit, np.array([6.0, 0, 0]) / unit, np.array([0, 0, 4.0]) / unit, rng),  # facade
        Plane(np.array([-5.0, -9.0, 0.0]) / unit, np.array([10.0, 0, 0]) / unit, np.array([0, 9.0, 0]) / unit, rng),  # ground
        Plane(np.array([3.0, 0.0, 0.0]) / unit, np.array([0, 4.0, 0]) / unit, np.array([0, 0, 3.0]) / unit, rng),  # side wall
    ]
    target = np.array([0.0, 0.0, 1.5]) / unit
    reference_camera = pinhole_camera(1, 320, 240, 60.0)
    shots = []
    for index, angle in enumerate(np.linspace(-55, 55, n_reference)):
        radius, height = 6.5 + 0.5 * (index % 2), 1.6 + 0.8 * (index % 3)
        eye = np.array([radius * np.sin(np.radians(angle)), -radius * np.cos(np.radians(angle)), height]) / unit
        shots.append(Shot(f"ref_{index:03d}.png", reference_camera, look_at(eye, target)))
    photo_shots = []
    for index in range(n_photos):
        angle = rng.uniform(-35, 35)
        eye = np.array([5.5 * np.sin(np.radians(angle)), -5.5 * np.cos(np.radians(angle)), rng.uniform(1.4, 2.4)]) / unit
        width, height = (240, 320) if index == 2 else (320 + 32 * (index % 2), 240 + 24 * (index % 2))
        k1 = [0.0, 0.05, 0.0, -0.04, 0.0][index % 5]
        camera = pinhole_camera(index + 1, width, height, rng.uniform(50, 65), k1)
        photo_shots.append(Shot(f"photo_{index:03d}.png", camera, look_at(eye, target + rng.normal(0, 0.1, 3), roll_deg=rng.uniform(-5, 5))))

    surface = np.concatenate([p.origin + rng.random((300, 1)) * p.u + rng.random((300, 1)) * p.v for p in planes])
    reference_renders = [render(planes, shot) for shot in shots]
    photo_renders = [render(planes, shot) for shot in photo_shots]

    reference_dir = root / "reference"
    write_images(reference_renders, reference_dir / "images")
    points, observations = sparse_tracks(surface, reference_renders, 500, rng)
    (reference_dir / "colmap" / "sparse" / "0").mkdir(parents=True)
    build_reconstruction(reference_renders, points, observations, shared_camera=True).write_binary(str(reference_dir / "colmap" / "sparse" / "0"))

    meta_dir = root / "meta" / "front"
    write_images(photo_renders, meta_dir / "images")
    points, observations = sparse_tracks(surface, photo_renders, 400, rng)
    meta_model = build_reconstruction(photo_renders, points, observations, shared_camera=False)
    axis = rng.normal(size=3)
    meta_to_reference = pycolmap.Sim3d(0.35, pycolmap.Rotation3d(axis / np.linalg.norm(axis) * 1.1), rng.normal(0, 2, 3))
    meta_model.transform(meta_to_reference.inverse())
    (meta_dir / "sparse" / "0").mkdir(parents=True)
    meta_model.write_binary(str(meta_dir / "sparse" / "0"))
    (meta_dir / "gt_transform.json").write_text(json.dumps(sim3_record(meta_to_reference)))
    return root


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return make_textured_scene(tmp_path_factory.mktemp("textured"))


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("init-cache")


@pytest.fixture(scope="module")
def initialiser(scene, cache_dir) -> Initialiser:
    source = ReferenceSource(scene / "reference" / "colmap" / "sparse" / "0", scene / "reference" / "images")
    return Initialiser(source, InitialiserSettings(cache_dir=cache_dir))


def ground_truth(meta_dir: Path) -> Sim3:
    return Sim3.from_matrix(json.loads((meta_dir / "gt_transform.json").read_text())["matrix"])


@pytest.mark.parametrize("method, within", [(m, (2.0, 0.05)) for m in METHODS if m != "dense"] + [("dense", (15.0, 0.3))])
def test_initialisers_recover_the_ground_truth_on_clean_renders(method, within, initialiser, scene):
    """SIFT starts (auto takes colmap's here) land within 2° / 0.05; the dense start is a coarse one, placed by
    16-cell teacher maps among 12 reference views, for the registration to refine: within its goal of 15° / 0.3."""
    meta = load_meta_image(scene / "meta" / "front")
    result = initialiser(meta, method)
    assert result.succeeded, result.failure
    assert result.method == ("colmap" if method == "auto" else method)
    errors = pose_errors([p.cam_from_world for p in meta.photos], result.transform, ground_truth(scene / "meta" / "front"))
    assert errors.rotation_deg < within[0] and errors.translation < within[1], (errors.rotation_deg, errors.translation)
    assert len(result.agreeing_photos) >= 3
    assert initialiser(meta, method).transform == pytest.approx(result.transform, abs=1e-9)  # deterministic


def test_keypoint_anchors_are_inliers_that_reproject_under_the_truth(initialiser, scene, tmp_path):
    """`Initialiser.keypoints`: per registered photo its RANSAC inliers, which reproject under the ground truth
    to within the RANSAC threshold (as the keypoint term measures them); photos with nothing to match have none."""
    from sg_nerfstudio.registration.anchored_start.anchors import KeypointTerm

    meta = load_meta_image(scene / "meta" / "front")
    anchors = initialiser.keypoints(meta)
    assert len(anchors) >= 3 and all(len(a.points2D) >= 30 and a.points2D.shape[1] == 2 and a.points3D.shape[1] == 3 for a in anchors)
    truth = ground_truth(scene / "meta" / "front")
    grid = 32
    term = KeypointTerm(meta, anchors, Sim3.identity(), grid_size=grid, weight=1.0)
    cell_px = max(meta.photos[0].camera.width, meta.photos[0].camera.height) / grid
    assert term.median_error_cells(truth) * cell_px < 2.0  # pixels
    assert initialiser.keypoints(load_meta_image(blank_meta_image(scene, tmp_path))) == []


def test_photos_too_weak_to_register_alone_lend_their_rig_inliers_as_anchors(initialiser, scene):
    """Where no photo registers on its own (here: an absolute-pose minimum no photo reaches), `Initialiser.keypoints`
    takes each photo's inliers under the meta-image's generalized pose instead: as many photos, and they reproject
    under the ground truth as the alone-registered ones do."""
    from dataclasses import replace as replace_settings

    from sg_nerfstudio.registration.anchored_start.anchors import KeypointTerm

    meta = load_meta_image(scene / "meta" / "front")
    alone = initialiser.keypoints(meta)
    strict = Initialiser(initialiser.source, replace_settings(
        initialiser.settings, absolute_pose=replace_settings(initialiser.settings.absolute_pose, min_inliers=100_000),
    ))
    assert strict(meta, "colmap").succeeded is False  # no photo registers alone
    rig = strict.keypoints(meta)
    assert sorted(k.name for k in rig) == sorted(k.name for k in alone)
    truth = ground_truth(scene / "meta" / "front")
    term = KeypointTerm(meta, rig, Sim3.identity(), grid_size=32, weight=1.0)
    cell_px = max(meta.photos[0].camera.width, meta.photos[0].camera.height) / 32
    assert term.median_error_cells(truth) * cell_px < 2.0  # pixels


def test_features_and_reference_triangulation_come_from_the_cache(scene, cache_dir, initialiser):
    meta = load_meta_image(scene / "meta" / "front")
    initialiser(meta, "colmap")  # fills the cache if the order of tests did not
    again = Initialiser(initialiser.source, InitialiserSettings(cache_dir=cache_dir))
    again(meta, "colmap")
    assert again.extractor.computed == 0
    assert len(list((cache_dir / "reference").iterdir())) == 1


def blank_meta_image(scene: Path, target: Path, keep: int = 0) -> Path:
    """The clean meta-image with its photos (all but the first `keep`) replaced by flat grey and by noise (nothing to
    match)."""
    meta_dir = target / ("blank" if keep == 0 else f"blank-but-{keep}")
    (meta_dir / "images").mkdir(parents=True)
    (meta_dir / "sparse").symlink_to(scene / "meta" / "front" / "sparse", target_is_directory=True)
    rng = np.random.default_rng(0)
    for index, photo in enumerate(sorted((scene / "meta" / "front" / "images").iterdir())):
        if index < keep:
            shutil.copy(photo, meta_dir / "images" / photo.name)
            continue
        shape = cv2.imread(str(photo)).shape
        image = np.full(shape, 128, np.uint8) if index % 2 else (rng.random(shape) * 255).astype(np.uint8)
        cv2.imwrite(str(meta_dir / "images" / photo.name), image)
    return meta_dir


def test_colmap_start_from_two_registered_photos_and_from_one(initialiser, scene, cache_dir, tmp_path):
    """A meta-image where only two photos can register (a 3-photo meta-image with one weak photo): their poses give
    the Sim(3) (rotation from both orientations, scale and translation from both centres). One photo alone gives its
    pose and a scale from its depths, said in the result's note; with `one_photo_start` off it is a failure."""
    two = load_meta_image(blank_meta_image(scene, tmp_path, keep=2))
    result = initialiser(two, "colmap")
    assert result.succeeded, result.failure
    assert len(result.agreeing_photos) == 2
    errors = pose_errors([p.cam_from_world for p in two.photos], result.transform, ground_truth(scene / "meta" / "front"))
    assert errors.rotation_deg < 2.0 and errors.translation < 0.05, (errors.rotation_deg, errors.translation)
    single = load_meta_image(blank_meta_image(scene, tmp_path, keep=1))
    one = initialiser(single, "colmap")
    assert one.succeeded and one.agreeing_photos == [single.photos[0].name] and "scale is a first guess from its depths" in one.note
    errors = pose_errors([p.cam_from_world for p in single.photos], one.transform, ground_truth(scene / "meta" / "front"))
    assert errors.rotation_deg < 2.0 and errors.translation < 0.3, (errors.rotation_deg, errors.translation)
    first = pose_errors([single.photos[0].cam_from_world], one.transform, ground_truth(scene / "meta" / "front"))
    assert first.rotation_deg < 1.0 and first.translation < 0.05  # the registered photo's own camera is placed
    classical = Initialiser(initialiser.source, InitialiserSettings(cache_dir=cache_dir, one_photo_start=False))(single, "colmap")
    assert not classical.succeeded and "only 1 of 5 photos registered to the reference (at least 2 are needed)" in classical.failure
    generalized = initialiser(single, "generalized")  # no rig of two photos: the same start from the one that registers
    assert generalized.succeeded and generalized.method == "generalized" and np.allclose(generalized.transform.matrix, one.transform.matrix)


def test_registered_photos_from_one_spot_start_from_the_one_with_the_most_inliers(initialiser, scene, cache_dir, tmp_path):
    """Two photos register, but the meta-image's SfM puts them at one spot (the second at the first's pose, as for a
    photo and a zoomed copy of it): their centres give no scale and no Sim(3) fits both. The start is the one-photo
    start from the photo with the most inliers, and the note says why; with `one_photo_start` off, the failure."""
    meta_dir = blank_meta_image(scene, tmp_path, keep=2)
    (meta_dir / "sparse").unlink()
    model = pycolmap.Reconstruction(str(scene / "meta" / "front" / "sparse" / "0"))
    first, second = sorted(model.images.values(), key=lambda image: image.name)[:2]
    model.frames[second.frame_id].rig_from_world = model.frames[first.frame_id].rig_from_world
    (meta_dir / "sparse" / "0").mkdir(parents=True)
    model.write(str(meta_dir / "sparse" / "0"))
    meta = load_meta_image(meta_dir)
    result = initialiser(meta, "colmap")
    assert result.succeeded, result.failure
    chosen = max((p for p in result.photos if p.registered), key=lambda p: p.num_inliers).name
    assert result.agreeing_photos == [chosen] and "give no Sim(3)" in result.note and f"starting from {chosen} alone" in result.note
    classical = Initialiser(initialiser.source, InitialiserSettings(cache_dir=cache_dir, one_photo_start=False))(meta, "colmap")
    assert not classical.succeeded and "the 2 registered photos give no Sim(3)" in classical.failure


def test_similarity_from_one_photo_is_exact_with_the_true_depths():
    """The registered photo's pose in both frames fixes rotation and centre; the ratio of its depths, the scale."""
    from sg_nerfstudio.initialisers.estimate import similarity_from_one_photo

    rng = np.random.default_rng(5)
    truth = Sim3.random(rng, 70.0, 3.0, 0.6)
    rotation = Sim3.random(rng, 40.0, 0.0, 0.0).rotation
    cam_from_meta = np.concatenate([rotation, rng.normal(size=(3, 1))], axis=1)
    found = similarity_from_one_photo(cam_from_meta, truth.move_camera(cam_from_meta), 2.0, 2.0 * truth.scale)
    assert np.allclose(found, truth.matrix, atol=1e-9)
    assert similarity_from_one_photo(cam_from_meta, truth.move_camera(cam_from_meta), 0.0, 1.0) is None


@pytest.mark.parametrize("method", METHODS)
def test_too_few_matches_is_a_reported_failure(method, initialiser, scene, tmp_path):
    meta = load_meta_image(blank_meta_image(scene, tmp_path))
    result = initialiser(meta, method)
    assert not result.succeeded and result.transform is None
    assert result.failure.startswith(f"Initialisation '{method}' failed for meta-image 'blank'")
    assert result.failure.count(".") == 1 and result.failure.endswith(".")


def test_baseline_cli_writes_transforms_metrics_and_failures(scene, cache_dir, tmp_path, capsys):
    blank, single = blank_meta_image(scene, tmp_path), blank_meta_image(scene, tmp_path, keep=1)
    out = tmp_path / "baseline"
    gt = str(scene / "meta" / "front" / "gt_transform.json")
    code = baseline_main([
        "--reference-colmap", str(scene / "reference" / "colmap" / "sparse" / "0"), "--reference-images", str(scene / "reference" / "images"),
        "--meta-image", str(scene / "meta" / "front"), "--meta-image", str(blank), "--meta-image", str(single), "--output-dir", str(out),
        "--gt", gt, "--gt", gt, "--gt", gt, "--initialiser.cache-dir", str(cache_dir),
    ])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    record = json.loads((out / "front" / "init_transform.json").read_text())
    assert {"matrix", "scale", "rotation_wxyz", "translation", "initialiser"} <= set(record)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["failures"] == 1 and not metrics["meta_images"]["blank"]["succeeded"]
    assert metrics["meta_images"]["front"]["errors"]["delta_R_deg"] < 2.0
    assert not (out / "blank").exists()
    assert "failed for meta-image 'blank'" in captured.err
    assert "scale is a first guess from its depths" in metrics["meta_images"]["blank-but-1"]["note"]  # one photo registered
    assert "blank-but-1: one photo registered" in captured.out.replace("\n", " ") + captured.err.replace("\n", " ")


def test_baseline_cli_missing_reference_model_is_one_sentence_and_no_output(scene, tmp_path, capsys):
    out = tmp_path / "baseline"
    code = baseline_main([
        "--reference-colmap", str(tmp_path / "nowhere"), "--reference-images", str(scene / "reference" / "images"),
        "--meta-image", str(scene / "meta" / "front"), "--output-dir", str(out),
    ])
    err = capsys.readouterr().err
    assert code == 1
    assert "Reference COLMAP model" in err and str(tmp_path / "nowhere") in err.replace("\n", "")
    assert err.strip().count("\n") == 0, err
    assert not out.exists()


def test_a_reference_folder_whose_model_is_one_level_down_is_named(scene):
    """--reference-colmap given the dataset folder (reference/) rather than its model: the sentence names the model."""
    folder = scene / "reference"
    expected = f"Reference COLMAP model {folder} was not found; expected a folder with cameras, images and points3D (.bin or .txt) (this one has a model in {folder / 'colmap' / 'sparse' / '0'})."
    with pytest.raises(ReferenceSourceError) as raised:
        ReferenceSource(folder, folder / "images").load()
    assert str(raised.value) == expected


def test_a_truncated_reference_image_is_one_sentence(scene, tmp_path):
    images = tmp_path / "images"
    shutil.copytree(scene / "reference" / "images", images)
    cut = sorted(images.iterdir())[0]
    cut.write_bytes(cut.read_bytes()[: cut.stat().st_size // 2])
    with pytest.raises(ReferenceSourceError, match=f"Reference image {cut} could not be read as an image .*; expected a complete JPEG or PNG"):
        ReferenceSource(scene / "reference" / "colmap" / "sparse" / "0", images).load()


def test_colmap_info_log_shows_only_when_verbose(capfd):
    """COLMAP's glog INFO lines (hundreds per meta-image) stay off the terminal unless --verbose; warnings stay."""
    try:
        set_colmap_verbosity(False)
        pycolmap.logging.info("sg-probe-quiet")
        pycolmap.logging.warning("sg-probe-warning")
        set_colmap_verbosity(True)
        pycolmap.logging.info("sg-probe-verbose")
    finally:
        set_colmap_verbosity(False)
    err = capfd.readouterr().err
    assert "sg-probe-quiet" not in err and "sg-probe-warning" in err and "sg-probe-verbose" in err


def test_pose_similarity_for_few_collinear_photos():
    """Three photos along one line (their centres leave the roll about the line free) and one wrong PnP pose:
    the pose-based similarity recovers the transform and flags the wrong photo."""
    from sg_nerfstudio.geometry.sim3 import Sim3
    from sg_nerfstudio.initialisers.estimate import centres_degenerate, similarity_from_poses

    rng = np.random.default_rng(4)
    poses = []
    for index in range(4):
        rotation = Sim3.random(rng, 10.0, 0.0, 0.0).rotation
        centre = np.array([float(index), 0.01 * index**2, 0.0])
        poses.append(np.concatenate([rotation, (-rotation @ centre)[:, None]], axis=1))
    cam_from_meta = np.stack(poses)
    truth = Sim3.random(rng, 90.0, 3.0, 0.5)
    cam_from_reference = np.stack([truth.move_camera(p) for p in cam_from_meta])
    cam_from_reference[3] = Sim3.random(rng, 30.0, 0.0, 0.0).move_camera(cam_from_reference[3])  # a wrong registration
    assert centres_degenerate(np.stack([-p[:, :3].T @ p[:, 3] for p in cam_from_meta]))
    matrix, inliers = similarity_from_poses(cam_from_meta, cam_from_reference, max_error=0.05)
    assert inliers.tolist() == [True, True, True, False]
    np.testing.assert_allclose(matrix, np.asarray(truth), atol=1e-9)


def test_generalized_pose_finds_a_scale_between_its_grid_points_for_photos_far_apart():
    """Three photos 4 units apart looking at a facade 10 away (a walk along it): a rig pose at a scale 25% off
    the truth fits one photo and misses the others' points by ~60 px, so the scale's basin is narrower than the
    first grid's spacing. With the truth midway between two grid points the search still finds it (the
    points are exact but for 0.5 px noise and 20% outliers)."""
    from sg_nerfstudio.initialisers.estimate import GeneralizedSettings, Observations, generalized_similarity

    rng = np.random.default_rng(7)
    truth = Sim3.random(rng, 60.0, 2.0, 0.0) @ Sim3.from_parts(0.37, np.eye(3), np.zeros(3))  # meta -> reference
    meta_from_reference = truth.inverse()
    observations, correct = [], {}
    for index, x in enumerate((-4.0, 0.0, 4.0)):
        cam_from_reference = look_at(np.array([x, -10.0, 1.5]), np.array([0.7 * x, 0.0, 2.0])).matrix()
        camera = pinhole_camera(index + 1, 640, 480, 56.0)
        points = np.column_stack([rng.uniform(-9, 9, 300), rng.uniform(-0.5, 0.5, 300), rng.uniform(0, 6, 300)])
        in_camera = points @ cam_from_reference[:, :3].T + cam_from_reference[:, 3]
        pixels = camera.img_from_cam(in_camera) + rng.normal(0.0, 0.5, (300, 2))
        visible = (in_camera[:, 2] > 0) & (pixels[:, 0] > 0) & (pixels[:, 0] < 640) & (pixels[:, 1] > 0) & (pixels[:, 1] < 480)
        pixels, points = pixels[visible], points[visible]
        wrong = rng.random(len(points)) < 0.2
        pixels[wrong] = rng.uniform([0, 0], [640, 480], (int(wrong.sum()), 2))
        cam_from_meta = meta_from_reference.move_camera(cam_from_reference)
        observations.append(Observations(f"{index}.jpg", camera, cam_from_meta, pixels, points))
        correct[f"{index}.jpg"] = int((~wrong).sum())
    settings = GeneralizedSettings()
    spread = np.median(np.linalg.norm(np.concatenate([o.points3D for o in observations]) - np.median(np.concatenate([o.points3D for o in observations]), axis=0), axis=1))
    midway = truth.scale * 10.0 ** (0.5 / settings.scale_steps_per_decade)  # the first guess, so the truth falls between grid points
    pose = generalized_similarity(observations, meta_depth=spread / midway, settings=settings)

    assert pose is not None and all(pose.inliers_per_photo[name] >= 0.9 * count for name, count in correct.items())
    assert pose.transform.scale == pytest.approx(truth.scale, rel=0.005)
    assert rotation_angle_deg(pose.transform.rotation @ truth.rotation.T) < 0.05
