"""Gap scenes: the reference look of the paper's setting, the scene's photo/render pairs and the gap measure."""

from __future__ import annotations

import json
from dataclasses import replace

import cv2
import numpy as np
import pytest

from sg_nerfstudio.bench.gap import GAP_TEACHER, PAPER_PAIRS, benchmark_gap, gap_sentence, in_paper_range, measure_gap, pool, summarise
from sg_nerfstudio.bench.pairs import read_pairs
from sg_nerfstudio.scripts.make_scene import main as make_scene_main
from sg_nerfstudio.synthetic import PRESETS, SceneGenerationError, generate_scene
from sg_nerfstudio.synthetic.appearance import EARTH_LOOK, ReferenceLook, flat_lighting
from sg_nerfstudio.synthetic.building import BuildingConfig, landmark_surfaces
from sg_nerfstudio.synthetic.capture import Shot, look_at, pinhole_camera
from sg_nerfstudio.synthetic.generator import SUITES, read_scene_config, reference_render
from sg_nerfstudio.synthetic.raycast import raycast_shot

SMALL_GAP = replace(
    PRESETS["gap"], building=replace(PRESETS["tiny"].building), reference_size=(48, 36), n_ring=6, n_aerial=2,
    meta_images=("front:3",), photo_size=(72, 72), n_sparse_points=300, occluder_rate=0.0,
)
"""A gap scene small enough for a test whose photos (64-79 px) are still large enough for the gap measure."""


UNIT = 1.0 / 40.0
"""Scene units per metre in these tests: the camera is about one unit from the landmark, as in a generated scene."""


def front_shot(width: int = 64, height: int = 48) -> Shot:
    """A photo of the default landmark's front facade from 40 m (in scene units of 40 m)."""
    return Shot("front.png", pinhole_camera(1, width, height, 60.0), look_at(np.array([0.0, -40.0, 6.0]) * UNIT, np.array([0.0, 0.0, 8.0]) * UNIT))


def test_the_default_look_renders_the_pixels_of_scenes_made_before_gap_scenes():
    surfaces, shot = landmark_surfaces(BuildingConfig()), front_shot()
    image, _ = reference_render(ReferenceLook(), surfaces, shot, unit=UNIT)
    old, _ = raycast_shot(surfaces, flat_lighting, 0.2, shot, np.array([0.80, 0.85, 0.90]), 1.0 / UNIT)
    np.testing.assert_array_equal(image, np.clip(old, 0.0, 1.0))


def test_earth_look_misplaces_the_texture_by_at_most_its_setting_and_the_same_in_every_view():
    uv = np.random.default_rng(0).uniform(-20, 20, (500, 2))
    moved = EARTH_LOOK.texture_coordinates(uv, surface_index=3)
    offsets = np.abs(moved - uv)
    assert offsets.max() <= EARTH_LOOK.texture_misalignment and offsets.mean() > 0.1 * EARTH_LOOK.texture_misalignment
    np.testing.assert_array_equal(moved, EARTH_LOOK.texture_coordinates(uv, surface_index=3))  # a property of the model
    assert not np.allclose(moved, EARTH_LOOK.texture_coordinates(uv, surface_index=4))
    np.testing.assert_array_equal(ReferenceLook().texture_coordinates(uv, 3), uv)


def test_earth_look_removes_the_detail_sift_needs():
    """What makes SIFT fail across the gap: the render keeps the large shapes, loses the fine gradients."""
    surfaces, shot = landmark_surfaces(BuildingConfig()), front_shot(128, 96)
    soft, _ = reference_render(ReferenceLook(), surfaces, shot, unit=UNIT)
    earth, _ = reference_render(EARTH_LOOK, surfaces, shot, unit=UNIT)

    def fine_detail(image):
        grey = cv2.cvtColor(image.astype(np.float32), cv2.COLOR_RGB2GRAY)
        return float(np.abs(cv2.Laplacian(grey, cv2.CV_32F)).mean())

    assert fine_detail(earth) < 0.5 * fine_detail(soft)
    assert abs(float(earth.mean()) - float(soft.mean())) < 0.15


def test_a_gap_scene_holds_its_photo_render_pairs_and_their_gap_measure(tmp_path):
    manifest = generate_scene(SMALL_GAP, tmp_path / "gap", measure_pairs=measure_gap)
    pairs = read_pairs(tmp_path / "gap" / "pairs")
    assert [(p.landmark, p.name) for p in pairs] == [("front", f"front_{i:03d}") for i in range(3)]
    photo = cv2.imread(str(pairs[0].photo))
    assert np.array_equal(photo, cv2.imread(str(tmp_path / "gap" / "meta" / "front" / "images" / "front_000.png")))
    gap = manifest["gap"]
    assert gap["measured"] and gap["pairs"] == 3 and gap["teacher"] == GAP_TEACHER
    assert 0.0 <= gap["sift_share"] <= 1.0 and 0.0 <= gap["identifiable"] <= 1.0
    assert json.loads((tmp_path / "gap" / "scene.json").read_text())["gap"] == gap
    assert read_scene_config(tmp_path / "gap").reference_look == EARTH_LOOK


def test_the_gap_measure_finds_a_copy_and_rejects_an_unrelated_render(tmp_path):
    rng = np.random.default_rng(0)
    texture = cv2.resize(rng.uniform(0, 255, (24, 24, 3)).astype(np.float32), (128, 128), interpolation=cv2.INTER_CUBIC)
    texture = np.clip(texture + rng.normal(0, 20, texture.shape), 0, 255).astype(np.uint8)
    other = np.ascontiguousarray(np.clip(cv2.resize(rng.uniform(0, 255, (6, 6, 3)).astype(np.float32), (128, 128)), 0, 255).astype(np.uint8))
    for folder, render in (("same", texture), ("other", other)):
        for kind, image in (("photos", texture), ("renders", render)):
            (tmp_path / folder / kind).mkdir(parents=True)
            cv2.imwrite(str(tmp_path / folder / kind / "a.png"), image)
    same, unrelated = measure_gap(tmp_path / "same"), measure_gap(tmp_path / "other")
    assert same["identifiable"] == 1.0 and same["sift_share"] == 1.0
    assert unrelated["sift_share"] == 0.0
    assert not in_paper_range(same) and "NOT in the paper's range" in gap_sentence(same)


def test_photos_too_small_for_the_measure_are_said_to_be_so(tmp_path):
    for kind in ("photos", "renders"):
        (tmp_path / kind).mkdir()
        cv2.imwrite(str(tmp_path / kind / "a.png"), np.zeros((36, 48, 3), np.uint8))
    measures = measure_gap(tmp_path)
    assert not measures["measured"] and "not measured: photos smaller than 64 pixels" in gap_sentence(measures)


def test_paper_pairs_range_is_the_issue_s():
    assert in_paper_range({"sift_share": 0.15, "identifiable": PAPER_PAIRS["identifiable"] + 0.05})
    assert not in_paper_range({"sift_share": 0.16, "identifiable": 0.5})
    assert not in_paper_range({"sift_share": 0.0, "identifiable": PAPER_PAIRS["identifiable"] + 0.051})


def test_gap_teacher_is_the_cpu_method_s_teacher():
    from sg_nerfstudio.splat.method import sg_feature_splat_cpu

    assert sg_feature_splat_cpu.config.pipeline.datamanager.teacher.name == GAP_TEACHER


def test_the_gap_suite_is_the_benchmark_s_landmarks_in_the_gap_look():
    assert list(SUITES["gap-benchmark"]) == list(SUITES["benchmark"])
    for name, config in SUITES["gap-benchmark"].items():
        assert config.reference_look == EARTH_LOOK and replace(config, reference_look=ReferenceLook(), photo_distance=(0.65, 1.25)) == SUITES["benchmark"][name]


@pytest.mark.parametrize("flags, message", [
    (["--photo-distance", "1.2", "0.5"], "photo_distance must list their lower bound first"),
    (["--detail-scale", "0"], "--detail-scale must be"),
    (["--texture-misalignment", "-1"], "--texture-misalignment must be"),
])
def test_bad_gap_settings_fail_with_one_sentence_and_leave_nothing(tmp_path, capsys, flags, message):
    assert make_scene_main(["--preset", "gap", "--output", str(tmp_path / "out"), *flags]) != 0
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
    with pytest.raises(SceneGenerationError):
        generate_scene(replace(SMALL_GAP, photo_distance=(0.0, 1.0)), tmp_path / "x")
    assert not (tmp_path / "x").exists()


def test_a_suite_s_gap_pools_its_scenes_photos():
    def scene(*found):
        return summarise([{"pair": f"front/p{i}", "sift_matches": matches, "identifiable": hit} for i, (matches, hit) in enumerate(found)])

    pooled = pool({"a": scene((20, True), (0, True)), "b": scene((1, False), (2, True)), "tiny": {"measured": False, "why": "small"}})
    assert pooled["pairs"] == 4 and pooled["sift_share"] == 0.25 and pooled["identifiable"] == 0.75 and pooled["sift_median"] == 1.5
    assert [p["pair"] for p in pooled["per_pair"]] == ["a/front/p0", "a/front/p1", "b/front/p0", "b/front/p1"]
    assert pool({"tiny": {"measured": False, "why": "small"}})["measured"] is False


def test_a_benchmark_s_gap_pools_the_scenes_the_builder_measured(tmp_path):
    from types import SimpleNamespace

    def scene(name, gap):
        directory = tmp_path / name
        directory.mkdir()
        if gap is not None:
            (directory / "scene.json").write_text(json.dumps({"gap": gap}))
        return SimpleNamespace(name=name, directory=directory)

    measured = summarise([{"pair": "m/p0", "sift_matches": 20, "identifiable": True}, {"pair": "m/p1", "sift_matches": 0, "identifiable": False}])
    scenes = [scene("gap", measured), scene("filtered", {"measured": False, "why": "no renders"}), scene("old", None)]
    pooled = benchmark_gap(scenes)
    assert pooled["pairs"] == 2 and pooled["sift_share"] == 0.5 and pooled["identifiable"] == 0.5
    assert [p["pair"] for p in pooled["per_pair"]] == ["gap/m/p0", "gap/m/p1"]
    assert benchmark_gap(scenes[1:])["measured"] is False
