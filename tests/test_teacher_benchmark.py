"""The teacher benchmark (`sg-bench teacher`): its measures on generated pairs with a known answer, its layout and
its bad inputs."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from sg_nerfstudio.bench import teacher as bench
from sg_nerfstudio.bench.pairs import PairsError, read_pairs
from sg_nerfstudio.scripts.bench import main as bench_main

SIDE = 120
"""Pair size: crop_side 86 pixels, so one cell of the hypotheses' grid is 86 / 32 = 2.7 pixels."""


def texture(seed: int, size: int = 2 * SIDE) -> np.ndarray:
    """[size, size, 3] float32 in [0.1, 0.9]: blocks of random colour with a little fine noise (structure at every scale)."""
    generator = np.random.default_rng(seed)
    blocks = cv2.resize(generator.random((size // 12, size // 12, 3)).astype(np.float32), (size, size), interpolation=cv2.INTER_NEAREST)
    return (0.1 + 0.7 * blocks + 0.1 * generator.random((size, size, 3))).astype(np.float32)


def window(image: np.ndarray, down: int = 0, right: int = 0) -> np.ndarray:
    """The SIDE x SIDE window of `image` whose top-left corner is (SIDE / 2 + down, SIDE / 2 + right)."""
    top, left = SIDE // 2 + down, SIDE // 2 + right
    return np.ascontiguousarray(image[top:top + SIDE, left:left + SIDE])


def test_a_shifted_copy_is_found_at_its_shift_and_a_copy_is_identifiable():
    scene = texture(0)
    cell = bench.crop_side(SIDE, SIDE) / bench.GRID_CELLS
    # the render's pixel p shows the photo's pixel p + (3, -2) cells: the photo's view is the render shifted by (-3, 2)
    render = window(scene, round(3 * cell), round(-2 * cell))
    found = bench.landscapes(bench.colour_cells, window(scene), render, shift_only=True)
    centre = bench.MAX_SHIFT_CELLS
    assert np.unravel_index(int(np.argmin(found.shift)), found.shift.shape) == (centre - 3, centre + 2)
    assert not bench.identifiable(found.shift)
    copy = bench.landscapes(bench.colour_cells, window(scene), window(scene))
    measures = bench.pair_measures(copy)
    assert measures["identifiable"] and measures["rotation_identifiable"] and measures["zoom_identifiable"]
    assert measures["prominence"] > 0 and measures["basin"]["2"] > 0.5


def test_unrelated_images_are_not_identifiable():
    found = bench.landscapes(bench.colour_cells, window(texture(1)), window(texture(2)), shift_only=True)
    assert not bench.identifiable(found.shift)
    assert bench.prominence(found.shift) < 0.05


def test_basin_counts_the_starts_that_descend_to_the_truth():
    down, right = np.meshgrid(np.arange(-6, 7), np.arange(-6, 7), indexing="ij")
    bowl = (down**2 + right**2).astype(float)
    assert all(bench.basin(bowl, k) == 1.0 for k in bench.BASIN_DISTANCES)
    walled = bowl.copy()
    walled[:, 9] = 100.0  # a wall 3 cells right of the truth: starts beyond it stop against it
    walled[:, 10:] -= 50.0
    assert bench.basin(walled, 2) == 1.0 and bench.basin(walled, 4) < 1.0
    assert bench.descend(walled, (6, 12)) != (6, 6) and bench.identifiable(walled) is False
    line = np.array([4.0, 3.0, 2.0, 1.0, 0.0, 1.0, 2.0, 3.0, 4.0])
    assert bench.identifiable(line) and bench.basin(line, 4) == 1.0


def test_hypothesis_views_turn_and_zoom_about_the_centre():
    image = texture(3)  # 240 x 240: the crop's pixel q shows the image's pixel 120 + (q - side / 2), turned and zoomed
    side = bench.crop_side(*image.shape[:2])
    corner = 120 - side // 2
    np.testing.assert_allclose(bench.hypothesis_view(image, side), image[corner:corner + side, corner:corner + side], atol=1e-6)
    zoomed = bench.hypothesis_view(image, side, zoom=2.0)
    np.testing.assert_allclose(zoomed[side // 2 - 20:side // 2 + 20:2, side // 2 - 20:side // 2 + 20:2], image[110:130, 110:130], atol=1e-6)
    turned = bench.hypothesis_view(image, side, angle=90.0)  # (x, y) shows (120 + y - side / 2, 120 - x + side / 2)
    near = np.arange(side // 2 - 20, side // 2 + 20)
    shown = image[(120 + side // 2 - near)[None, :], (120 - side // 2 + near)[:, None]]
    np.testing.assert_allclose(turned[near[0]:near[-1] + 1, near[0]:near[-1] + 1], shown, atol=1e-5)


def test_control_partner_is_another_landmark_and_sift_counts_matches_in_place():
    assert bench.control_partner(0, ["a", "a", "b", "b"]) == 2
    assert bench.control_partner(3, ["a", "a", "b", "b"]) == 1
    assert bench.control_partner(0, ["a", "a"]) == 1 and bench.control_partner(0, ["a"]) is None
    photo = texture(4)
    assert bench.sift_matches(photo, photo) >= bench.SIFT_ENOUGH
    assert bench.sift_matches(photo, np.full_like(photo, 0.5)) == 0


def write_pairs(root, landmarks=("a", "b"), per_landmark=2, size=SIDE):
    for index, landmark in enumerate(landmarks):
        for number in range(per_landmark):
            scene = texture(10 * index + number, 2 * size)
            for kind, image in (("photos", window(scene)), ("renders", 0.6 * window(scene) + 0.2)):
                (root / landmark / kind).mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(root / landmark / kind / f"frame_{number}.png"), cv2.cvtColor((image * 255).astype(np.uint8), cv2.COLOR_RGB2BGR))
    return root


def test_sg_bench_teacher_writes_its_report(tmp_path):
    pairs = write_pairs(tmp_path / "pairs")
    assert bench_main(["teacher", str(pairs), "--output", str(tmp_path / "out"), "--teachers", "colour", "--threads", "1"]) == 0
    report = json.loads((tmp_path / "out" / "teacher-benchmark.json").read_text())
    overall = report["summary"]["teachers"]["colour"]["all"]
    assert overall["pairs"] == 4 and overall["identifiable"] == 100.0 and overall["control_pairs"] == 2
    assert set(report["summary"]["sift"]) == {"all", "a", "b"}
    assert (tmp_path / "out" / "landscapes.png").stat().st_size > 0
    assert "| colour (4) | 100.0 |" in (tmp_path / "out" / "teacher-benchmark.md").read_text()


@pytest.mark.parametrize("damage,message", [
    (lambda root: (root / "b" / "renders" / "frame_1.png").unlink(), r"Photo .*frame_1.png has no render; expected"),
    (lambda root: cv2.imwrite(str(root / "a" / "renders" / "frame_0.png"), np.zeros((90, 90, 3), np.uint8)), r"is 90x90 but its photo is 120x120"),
    (lambda root: (root / "a" / "photos" / "frame_1.png").write_bytes(b"not an image"), r"could not be read as an image"),
    (lambda root: [p.unlink() for p in (root / "b" / "renders").iterdir()] and (root / "b" / "renders").rmdir(), r"has no sibling renders/ folder"),
])
def test_a_bad_pairs_folder_is_one_sentence_and_no_output(tmp_path, capsys, damage, message):
    pairs = write_pairs(tmp_path / "pairs")
    damage(pairs)
    assert bench_main(["teacher", str(pairs), "--output", str(tmp_path / "out"), "--teachers", "colour", "--threads", "1"]) == 1
    error = capsys.readouterr().err
    assert __import__("re").search(message, error) and "Traceback" not in error
    assert not (tmp_path / "out").exists()


def test_pairs_layout_errors_name_the_folder(tmp_path):
    with pytest.raises(PairsError, match="does not exist"):
        read_pairs(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(PairsError, match="holds no photos/ folder"):
        read_pairs(tmp_path / "empty")
    single = write_pairs(tmp_path / "one", landmarks=("x",)) / "x"
    assert [(p.landmark, p.name) for p in read_pairs(single)] == [("x", "frame_0"), ("x", "frame_1")]
    pairs = write_pairs(tmp_path / "pairs")
    assert bench_main(["teacher", str(pairs), "--output", str(pairs / "out"), "--teachers", "colour"]) == 1


def test_dinov2_without_local_weights_names_the_benchmarks_flag(tmp_path, monkeypatch, capsys):
    from sg_nerfstudio.features import dinov2

    monkeypatch.setattr(dinov2, "weight_search_paths", lambda explicit: [tmp_path / "torch" / dinov2.TORCH_HUB_FILENAME])
    pairs = write_pairs(tmp_path / "pairs")
    assert bench_main(["teacher", str(pairs), "--output", str(tmp_path / "out"), "--teachers", "dinov2"]) == 1
    assert "pass --dinov2-weights FILE or leave dinov2 out of --teachers" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
