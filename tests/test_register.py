"""ns-register-meta: Sim(3) maths, frozen model, convergence from a perturbed start, outputs, bad inputs."""

from __future__ import annotations

import copy
import hashlib
import json
import shutil
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
import torch
import yaml

from sg_nerfstudio.features import TeacherConfig, build_teacher
from sg_nerfstudio.geometry.frames import viewmat
from sg_nerfstudio.geometry.meta_image import load_meta_image
from sg_nerfstudio.geometry.sim3 import Sim3, decompose, perturbed
from sg_nerfstudio.registration.anchored_start.camera_fit import adjusted_cameras, fit_cameras
from sg_nerfstudio.registration.depth_agreement import PointPixels, log_depth_ratios, summarise
from sg_nerfstudio.registration.metrics import pose_errors
from sg_nerfstudio.registration import hypotheses, optimize, schedules, stages, verdict
from sg_nerfstudio.registration.anchored_start import scale_search
from sg_nerfstudio.registration.objectives import (
    ObjectiveSettingsError, PhotoLosses, build_objective, prepare_photos, refine_settings, teacher_on_render_target,
)
from sg_nerfstudio.registration.optimize import register
from sg_nerfstudio.registration.reference import load_reference
from sg_nerfstudio.registration.robust import RobustAggregator, RobustSettingsError, TrimmingRule, check_robust_settings
from sg_nerfstudio.registration.settings import RegistrationSettings, SettingsRangeError, check_ranges
from sg_nerfstudio.scripts.register_meta import main as register_main

FAST = RegistrationSettings().changed(optimiser={"steps": 150, "lr": 0.004, "lr_final": 0.0002, "photos_per_step": 0}, objective={"render_scale": 2.0}, seed=0)


@pytest.fixture(scope="module")
def reference_config(trained) -> Path:
    _, _, config = trained
    return config.get_base_dir() / "config.yml"


@pytest.fixture(scope="module")
def reference(reference_config):
    return load_reference(reference_config)


@pytest.fixture(scope="module")
def meta(tiny_scene):
    return load_meta_image(tiny_scene / "meta" / "front")


@pytest.fixture(scope="module")
def ground_truth(tiny_scene) -> Sim3:
    return Sim3.read_json(tiny_scene / "meta" / "front" / "gt_transform.json", "Ground truth")


def perturbed_start(meta, ground_truth, seed, rotation_deg, translation, scale_fraction) -> Sim3:
    """ground truth followed by a perturbation about the cameras' centroid in the reference frame."""
    return perturbed(ground_truth, meta.centres, np.random.default_rng(seed), rotation_deg, translation, scale_fraction)


def test_sim3_helpers():
    rng = np.random.default_rng(0)
    transform = Sim3.random(rng, 5.0, 0.1, 0.1)
    scale, rotation, translation = transform.scale, transform.rotation, transform.translation
    assert scale == pytest.approx(1.1) or scale == pytest.approx(0.9)
    assert np.degrees(np.arccos((np.trace(rotation) - 1) / 2)) == pytest.approx(5.0)
    assert np.linalg.norm(translation) == pytest.approx(0.1)
    np.testing.assert_allclose((transform.inverse() @ transform).matrix, np.eye(4), atol=1e-12)
    centre = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    np.testing.assert_allclose(Sim3.update(torch.zeros(7, dtype=torch.float64), centre).matrix.numpy(), np.eye(4), atol=1e-15)
    delta = torch.tensor([0.1, -0.2, 0.05, 0.3, 0.0, -0.1, 0.2], dtype=torch.float64)
    moved = Sim3.update(delta, centre).matrix.numpy() @ np.append(centre.numpy(), 1)
    np.testing.assert_allclose(moved[:3], centre.numpy() + delta[3:6].numpy(), atol=1e-12)  # the centre only translates
    with pytest.raises(ValueError, match="positive"):
        decompose(np.diag([-1.0, 1.0, 1.0, 1.0]))


def test_camera_viewmat_matches_pycolmap_similarity(meta):
    transform = Sim3.random(np.random.default_rng(1), 20.0, 0.5, 0.3)
    moved = pycolmap.Reconstruction(meta.reconstruction)
    moved.transform(pycolmap.Sim3d(transform.scale, pycolmap.Rotation3d(transform.rotation), transform.translation))
    on_torch = transform.to_torch()
    for photo in meta.photos:
        ours = viewmat(on_torch.move_camera(torch.from_numpy(photo.cam_from_world))).float()
        expected = moved.find_image_with_name(photo.name).cam_from_world().matrix()
        np.testing.assert_allclose(ours[:3].numpy(), expected, atol=1e-5)
        np.testing.assert_allclose(transform.move_camera(photo.cam_from_world), expected, atol=1e-9)  # numpy, same function


def test_pose_errors(meta, ground_truth):
    poses = meta.poses
    assert pose_errors(poses, ground_truth, ground_truth).rotation_deg == pytest.approx(0.0, abs=1e-4)
    rotated = perturbed_start(meta, ground_truth, 0, 7.0, 0.0, 0.0)
    errors = pose_errors(poses, rotated, ground_truth)
    assert errors.rotation_deg == pytest.approx(7.0, abs=1e-6)
    assert not errors.accurate() and not errors.outlier()


def checkpoint_digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def rendered_targets(reference, meta, photos, transform, settings):
    """Replace each photo's target by what the objective sees of the model itself rendered at `transform`."""
    objective = build_objective(reference, settings)
    meta_to_dataparser = (reference.world_to_dataparser @ transform).to_torch()
    for photo in photos:
        camera = viewmat(meta_to_dataparser.move_camera(photo.cam_from_meta)).float()
        with torch.no_grad():
            rendered, _ = objective.render(reference, camera[None], photo.K[None], photo.width, photo.height, 0.01, "auto")
            photo.target = objective.to_target_grid(rendered, photo.target)[0]
    return photos


def test_teacher_on_render_target_sees_the_photo_as_the_render_is_seen():
    """A photo that is exactly a render enlarged 3x gets the target the render itself is described with
    (the blur of rendering below the teacher's input size is matched, not held against the pose)."""
    teacher = build_teacher(TeacherConfig(name="offline", input_size=64, device="cpu"))
    rng = np.random.default_rng(0)
    render = rng.integers(0, 256, size=(20, 30, 3)).astype(np.float32) / 255.0
    photo = torch.from_numpy((np.repeat(np.repeat(render, 3, axis=0), 3, axis=1) * 255.0).round().astype(np.uint8))
    grid = teacher.grid_shape(60, 90)
    target = teacher_on_render_target(photo, (30, 20), teacher)
    from_render = teacher.describe(torch.from_numpy(render), grid)
    torch.testing.assert_close(target, from_render, rtol=0, atol=1e-5)
    assert (teacher.extract(photo.float() / 255.0) - from_render).abs().max() > 1e-2


@pytest.mark.parametrize("objective,render_teacher", [("features", None), ("teacher-on-render", None), ("teacher-on-render", "dense-sift")])
def test_registration_converges_where_the_optimum_is_known_and_leaves_the_model_untouched(objective, render_teacher, reference, meta, ground_truth):
    """Targets rendered by the model itself at the ground truth: the optimum is exactly the ground truth,
    so this checks frames, gradients, the update and the loop independently of how good the model is."""
    before_digest = checkpoint_digest(reference.checkpoint_path)
    before_state = {k: v.clone() for k, v in reference.model.state_dict().items()}
    settings = FAST.changed(objective={"kind": objective, "render_teacher": render_teacher})
    photos = rendered_targets(reference, meta, prepare_photos(reference, meta, settings), ground_truth, settings)
    start = perturbed_start(meta, ground_truth, 0, 4.0, 0.06, 0.06)
    result = register(reference, meta, start, settings, photos=photos)
    poses = meta.poses
    initial, final = pose_errors(poses, start, ground_truth), pose_errors(poses, result.transform, ground_truth)
    assert final.rotation_deg < 0.25 * initial.rotation_deg, (initial, final)
    assert final.translation < 0.25 * initial.translation, (initial, final)
    assert result.final_trimmed_loss < 0.6 * float(np.median(result.initial_losses))
    assert all(not p.requires_grad for p in reference.model.parameters())
    for key, value in reference.model.state_dict().items():
        assert torch.equal(value, before_state[key]), key
    assert checkpoint_digest(reference.checkpoint_path) == before_digest


def test_render_teacher_replaces_the_reference_teacher_only_where_renders_are_described(reference):
    """--render-teacher: the photos and renders are described by the named descriptor (at its own default input
    size unless one is given); the features objective, which compares the distilled field, refuses it."""
    assert reference.teacher.name == "offline"
    sift = build_objective(reference, FAST.changed(objective={"kind": "teacher-on-render", "render_teacher": "dense-sift"}))
    assert sift.teacher.settings()["teacher"] == "dense_sift" and sift.teacher.input_size == 256
    sized = build_objective(reference, FAST.changed(objective={"kind": "photometric", "render_teacher": "dense-sift", "teacher_input_size": 128}))
    assert sized.teacher.grid_size == 16
    own = build_objective(reference, FAST.changed(objective={"kind": "teacher-on-render", "render_teacher": "offline"}))
    assert own.teacher.input_size == reference.teacher.input_size and own.teacher.settings()["teacher"] == "offline_hog"
    with pytest.raises(ObjectiveSettingsError, match=r"--objective.render-teacher dense-sift describes rendered images .* the features objective compares"):
        build_objective(reference, FAST.changed(objective={"kind": "features", "render_teacher": "dense-sift"}))


def test_batched_rendering_gives_the_per_photo_losses(reference, meta, ground_truth, monkeypatch):
    """Photos rendered together (one packed projection) or one per call give the same losses and coverage."""
    from sg_nerfstudio.registration import objectives

    settings = FAST.changed(objective={"kind": "teacher-on-render"})
    photos = prepare_photos(reference, meta, settings)
    transform = (reference.world_to_dataparser @ ground_truth).to_torch()
    indices = list(range(len(photos)))[::-1]
    objective = PhotoLosses(reference, photos, build_objective(reference, settings), settings, 0.01)
    assert len(objective.same_size_groups(indices)) < len(indices)  # several photos share a render call
    together, coverage_together = objective(transform, indices)
    monkeypatch.setattr(objectives, "RENDER_BATCH_ELEMENTS", 1)
    assert len(objective.same_size_groups(indices)) == len(indices)
    alone, coverage_alone = objective(transform, indices)
    torch.testing.assert_close(torch.stack(together), torch.stack(alone), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(coverage_together, coverage_alone, rtol=1e-5, atol=1e-6)


def test_culling_to_the_visible_gaussians_gives_the_same_losses_and_recull_follows_the_pose(reference, meta, ground_truth):
    """The culled model renders what the whole model renders, at the cull pose and within the re-cull bounds;
    a pose beyond them is culled again (level of detail off: this checks the cull alone)."""
    settings = FAST.changed(objective={"kind": "teacher-on-render"}, level_of_detail={"voxel_pixels": 0.0})
    objective = build_objective(reference, settings)
    photos = prepare_photos(reference, meta, settings, objective)
    culled = PhotoLosses(reference, photos, objective, settings, 0.01)
    whole = PhotoLosses(reference, photos, objective, settings, 0.01, cull=False)
    indices = list(range(len(photos)))
    start = perturbed_start(meta, ground_truth, 11, 2.0, 0.02, 0.02)
    nearby = perturbed(start, meta.centres, np.random.default_rng(12), 1.0, 0.0, 0.0)  # 1 degree from the cull pose
    for transform, culls in ((start, 1), (nearby, 1)):
        with torch.no_grad():
            ours, ours_coverage = culled((reference.world_to_dataparser @ transform).to_torch(), indices)
            full, full_coverage = whole((reference.world_to_dataparser @ transform).to_torch(), indices)
        torch.testing.assert_close(torch.stack(ours), torch.stack(full), rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(ours_coverage, full_coverage, rtol=1e-5, atol=1e-6)
        assert culled.visible.culls == culls
    assert culled.visible.subset.count < reference.count  # the photos of one side do not see the whole model
    far = perturbed(start, meta.centres, np.random.default_rng(13), 20.0, 0.0, 0.0)
    with torch.no_grad():
        culled((reference.world_to_dataparser @ far).to_torch(), indices)
    assert culled.visible.culls == 2  # 20 degrees from the last cull: culled again


def test_same_seed_same_transform(reference, meta, ground_truth):
    start = perturbed_start(meta, ground_truth, 5, 3.0, 0.05, 0.05)
    settings = FAST.changed(optimiser={"steps": 15, "photos_per_step": 2})
    first = register(reference, meta, start, settings).transform
    second = register(reference, meta, start, settings).transform
    np.testing.assert_allclose(first, second, atol=1e-6, rtol=0)


def test_lts_ignores_the_worst_photos(reference, meta, ground_truth):
    result = register(reference, meta, ground_truth, FAST.changed(optimiser={"steps": 10}))
    kept = [row["kept"] for row in result.history]
    assert 0 < sum(kept) < len(kept)
    worst = int(np.argmax(result.initial_losses))
    assert result.ignored_fraction[worst] == pytest.approx(1.0)


def test_retrim_schedule_renders_only_the_counted_photos_between_re_decisions():
    schedule = schedules.RetrimSchedule(5, RegistrationSettings().changed(robust={"retrim_every": 3}), warmup_steps=2)
    counted = np.array([True, False, True, False, True])
    batches = []
    for _ in range(8):
        batch = schedule.next()
        schedule.counted(batch, counted[batch] if len(batch) == 5 else np.ones(len(batch), bool))
        batches.append((batch, schedule.left_out(batch)))
    every, kept = ([0, 1, 2, 3, 4], []), ([0, 2, 4], [1, 3])
    # warm-up (2 steps), then a re-decision every third step, the counted photos alone in between
    assert batches == [every, every, every, kept, kept, every, kept, kept]
    paper = schedules.RetrimSchedule(5, RegistrationSettings(), warmup_steps=0)
    assert all(paper.next() == [0, 1, 2, 3, 4] for _ in range(4))
    with pytest.raises(SettingsRangeError, match=r"robust\.retrim_every \(--robust\.retrim-every\) must be a whole number of 1 or more, got 0"):
        check_ranges(RegistrationSettings().changed(robust={"retrim_every": 0}))


def test_retrimming_less_often_renders_less_and_ends_where_the_paper_rule_does(reference, meta, ground_truth):
    start = perturbed_start(meta, ground_truth, 5, 3.0, 0.05, 0.05)
    paper = register(reference, meta, start, FAST.changed(optimiser={"steps": 60}))
    lazy = register(reference, meta, start, FAST.changed(optimiser={"steps": 60}, robust={"retrim_every": 4}))
    photos = len(paper.photo_names)
    assert len(paper.history) == 60 * photos and len(lazy.history) < 60 * photos
    # every photo the paper's rule always ignored is ignored in every step of the lazy one too, rendered or not
    np.testing.assert_array_equal(lazy.ignored_fraction[paper.ignored_fraction == 1.0], 1.0)
    initial, ends = pose_errors(meta.poses, start, ground_truth), pose_errors(meta.poses, lazy.transform, paper.transform)
    # measured from 3° / 0.055: under a tenth of that on the earlier CI machine, 0.42° / 0.0058 on an AMD EPYC (another draw
    # of the tiny reference, presumably from the CPU's arithmetic)
    assert ends.rotation_deg < 0.2 * initial.rotation_deg and ends.translation < 0.2 * initial.translation, (initial, ends)


def test_trimming_rules_drop_only_what_they_should():
    median_rule, outlier_rule = TrimmingRule("lts"), TrimmingRule("outlier-lts")
    alike = np.array([0.100, 0.105, 0.110])  # away from the answer: every photo near the same floor
    assert (alike <= median_rule.threshold(alike)).sum() == 2  # the paper's rule drops one of three anyway
    assert (alike <= outlier_rule.threshold(alike)).all()
    one_far = np.array([0.060, 0.062, 0.120])
    assert (one_far <= outlier_rule.threshold(one_far)).tolist() == [True, True, False]
    # Two photos that agree closely (MAD ~ 0) do not make a third 25% above them an outlier (scale floor).
    close = np.array([0.100, 0.1001, 0.125])
    assert (close <= outlier_rule.threshold(close)).all() and not (np.array([0.1, 0.1001, 0.14]) <= outlier_rule.threshold(np.array([0.1, 0.1001, 0.14]))).all()
    assert outlier_rule.trimmed_mean(one_far) == pytest.approx(0.061) and TrimmingRule("none").trimmed_mean(one_far) == pytest.approx(one_far.mean())


def test_robust_rule_trims_only_after_its_warm_up():
    losses = [torch.tensor(v, dtype=torch.float64, requires_grad=True) for v in (0.10, 0.11, 0.30)]
    aggregator = RobustAggregator(TrimmingRule("lts"), np.array([0.10, 0.11, 0.30]), warmup_steps=2)
    for _ in range(2):  # warm-up: the plain mean, every photo counts
        objective, kept, _ = aggregator(losses, np.arange(3))
        assert kept.all() and float(objective.detach()) == pytest.approx(0.17)
    objective, kept, _ = aggregator(losses, np.arange(3))
    assert kept.tolist() == [True, True, False] and float(objective.detach()) == pytest.approx(0.105)


@pytest.mark.parametrize("setting, value, flag", [("trim_after", 1.0, "--robust.trim-after"), ("lts_percentile", 0.0, "--robust.lts-percentile"), ("outlier_z", -1.0, "--robust.outlier-z")])
def test_robust_settings_out_of_range_are_one_sentence(setting, value, flag):
    with pytest.raises(RobustSettingsError, match=flag):
        check_robust_settings(RegistrationSettings().changed(robust={setting: value}))
    check_robust_settings(RegistrationSettings().changed(robust={"trim_after": 0.5}))


def test_outlier_lts_ignores_a_wrong_photo_and_keeps_the_others(reference, meta, ground_truth):
    settings = FAST.changed(optimiser={"steps": 10}, robust={"rule": "outlier-lts"})
    photos = prepare_photos(reference, meta, settings)
    wrong = copy.copy(photos[1])
    # A map no pose explains: the photo's descriptor inverted. (The photo upside down was used before; on the
    # tiny scene's 16-cell grid its loss came within 3 robust scales of the others with some trainings.)
    wrong.target = photos[1].target.max() - photos[1].target
    photos[1] = wrong
    result = register(reference, meta, ground_truth, settings, photos=photos)
    assert result.ignored_fraction[1] == pytest.approx(1.0)
    assert np.delete(result.ignored_fraction, 1).max() == 0.0
    median = register(reference, meta, ground_truth, settings.changed(robust={"rule": "lts"}), photos=photos)
    assert np.delete(median.ignored_fraction, 1).max() > 0.0  # the median rule also drops photos that agree


def run_cli(args: list[str], capsys) -> tuple[int, str]:
    capsys.readouterr()
    code = register_main(args)
    return code, capsys.readouterr().err


def test_cli_writes_every_output(reference_config, tiny_scene, tmp_path, capsys, ground_truth):
    start = perturbed_start(load_meta_image(tiny_scene / "meta" / "front"), ground_truth, 7, 3.0, 0.05, 0.05)
    init = tmp_path / "init.json"
    init.write_text(json.dumps({"matrix": np.asarray(start).tolist()}))
    out = tmp_path / "out"
    code, err = run_cli([
        "--load-config", str(reference_config), "--meta-image", str(tiny_scene / "meta" / "front"), "--output-dir", str(out),
        "--init", str(init), "--gt", str(tiny_scene / "meta" / "front" / "gt_transform.json"),
        "--optimiser.steps", "12", "--optimiser.photos-per-step", "2", "--optimiser.lr", "0.004", "--last-stage.steps", "3", "--robust.retrim-every", "1",  # two rows a step
    ], capsys)
    assert code == 0, err
    result = out / "front"
    record = json.loads((result / "transform.json").read_text())
    assert {"matrix", "scale", "rotation_wxyz", "translation", "initial", "final_trimmed_loss", "steps", "wall_time_s", "settings", "verdict"} <= set(record)
    assert record["verdict"] in {"registered", "uncertain", "failed"} and record["verdict_reasons"] and "sharpness" in record["verdict_evidence"]
    assert record["steps"] == 12 + 3 and record["settings"]["optimiser"]["photos_per_step"] == 2 and record["settings"]["robust"]["retrim_every"] == 1
    rendered = record["rendered_model"]  # the tiny reference is far within the render budget: merged at 1 px
    assert rendered["voxel_pixels"] == 1.0 and 0 < rendered["rendered"] <= rendered["gaussians"] and rendered["culls"] >= 1
    np.testing.assert_allclose(record["initial"]["matrix"], start, atol=1e-9)
    aligned = pycolmap.Reconstruction(str(result / "aligned"))
    meta = load_meta_image(tiny_scene / "meta" / "front")
    matrix = np.array(record["matrix"])
    for photo in meta.photos:
        centre = aligned.find_image_with_name(photo.name).projection_center()
        np.testing.assert_allclose(centre, (matrix @ np.append(photo.centre, 1))[:3], atol=1e-6)
    rows = (result / "losses.csv").read_text().strip().splitlines()
    assert rows[0] == "step,image,loss,kept,weight,stage" and len(rows) == 1 + (12 + 3) * 2
    assert [row.rsplit(",", 1)[1].split("-")[0] for row in rows[1:]] == ["main"] * 24 + ["refine"] * 6
    for name in ("loss_curve.png", "ignored_histogram.png"):
        assert cv2.imread(str(result / "report" / name)) is not None
    assert len(list((result / "report" / "comparisons").glob("*_before_after.png"))) >= 2
    metrics = json.loads((result / "metrics.json").read_text())
    assert set(metrics) == {"before", "after"} and "delta_R_deg" in metrics["after"]
    assert not any(p.name.startswith(".") for p in out.iterdir())  # no staging directory left


def test_cli_without_config_picks_the_preset_for_the_device_and_labels_its_comparisons(reference_config, tiny_scene, tmp_path, capsys):
    out = tmp_path / "out"
    code = register_main([
        "--load-config", str(reference_config), "--meta-image", str(tiny_scene / "meta" / "front"), "--output-dir", str(out),
        "--init", str(tiny_scene / "meta" / "front" / "gt_transform.json"), "--optimiser.steps", "2", "--level-of-detail.render-budget", "1",
    ])
    printed = capsys.readouterr().out
    assert code == 0
    # A budget no merge can meet: the voxel doubles to its limit (4x --level-of-detail), and the console says so.
    rendered = json.loads((out / "front" / "transform.json").read_text())["rendered_model"]
    assert rendered["voxel_pixels"] == 4.0 and f"rendered {rendered['rendered']:,} of the reference's {rendered['gaussians']:,} Gaussians" in printed
    expected = "paper" if torch.cuda.is_available() else "fast-cpu"  # the tiny reference uses the offline teacher
    assert f"Registration preset: {expected}" in printed
    settings = json.loads((out / "front" / "transform.json").read_text())["settings"]
    assert settings["objective"]["kind"] == ("features" if expected == "paper" else "teacher-on-render") and settings["optimiser"]["steps"] == 2
    from sg_nerfstudio.registration.outputs import COMPARISON_LONG_SIDE, TITLE_HEIGHT

    photo = load_meta_image(tiny_scene / "meta" / "front").photos[0]
    scale = COMPARISON_LONG_SIDE / max(photo.camera.width, photo.camera.height)
    comparison = cv2.imread(str(next((out / "front" / "report" / "comparisons").glob("*_before_after.png"))))
    assert comparison.shape[0] == TITLE_HEIGHT + round(scale * photo.camera.height)
    title = comparison[:TITLE_HEIGHT]
    assert 0 < (title < 128).all(axis=2).mean() < 0.3  # dark text on the white strip above each panel


def test_summary_table_is_readable_at_80_columns():
    from types import SimpleNamespace

    from rich.console import Console

    from sg_nerfstudio.registration.metrics import PoseErrors
    from sg_nerfstudio.registration.session import MetaOutcome, summary_table

    meta = SimpleNamespace(name="front-facade", photos=[None] * 16)
    result = SimpleNamespace(final_trimmed_loss=0.0123, wall_time_s=215.3, verdict=SimpleNamespace(label="uncertain"))
    errors = {"before": PoseErrors(15.0, 0.1, [], []), "after": PoseErrors(0.31, 0.0041, [], [])}
    console = Console(width=80, record=True)
    console.print(summary_table([MetaOutcome(meta, result, errors), MetaOutcome(meta)]))
    text = console.export_text()
    assert max(len(line) for line in text.splitlines()) <= 80 and "…" not in text
    for cell in ("meta-image", "photos", "ΔR (°)", "ΔT", "accurate", "outlier", "verdict", "15.00→0.31", "0.100→0.004", "no→yes", "yes→no", "uncertain", "215", "init failed"):
        assert cell in text, cell


def test_comparison_files_of_photos_in_sub_folders_do_not_overwrite_each_other(tmp_path):
    from sg_nerfstudio.registration.outputs import comparison_path

    names = ["cam1/0001.jpg", "cam2/0001.jpg", "0001.jpg", "cam1/deeper/0001.png"]
    paths = [comparison_path(tmp_path, name) for name in names]
    assert len(set(paths)) == len(names) and all(path.parent == tmp_path for path in paths)
    assert paths[0].name == "cam1__0001_before_after.png" and paths[2].name == "0001_before_after.png"


def test_the_other_models_of_a_colmap_project_are_named(tiny_scene, tmp_path):
    """A COLMAP project whose mapper wrote several models (sparse/0, sparse/1): sparse/0 is registered and the others
    are named for the note ns-register-meta prints."""
    from sg_nerfstudio.geometry.meta_image import sibling_models

    meta_dir = shutil.copytree(tiny_scene / "meta" / "front", tmp_path / "project")
    assert sibling_models(meta_dir / "sparse" / "0") == []
    shutil.copytree(meta_dir / "sparse" / "0", meta_dir / "sparse" / "1")
    (meta_dir / "sparse" / "2").mkdir()  # no model in it
    meta = load_meta_image(meta_dir)
    assert meta.model_path == meta_dir / "sparse" / "0"
    assert sibling_models(meta.model_path) == [meta_dir / "sparse" / "1"]


def test_a_meta_image_in_nerfstudio_s_layout_is_read(tiny_scene, tmp_path):
    """`ns-process-data` writes images/ and colmap/sparse/0: a nerfstudio user's own reconstruction as it is."""
    meta_dir = shutil.copytree(tiny_scene / "meta" / "front", tmp_path / "processed")
    (meta_dir / "colmap").mkdir()
    shutil.move(meta_dir / "sparse", meta_dir / "colmap" / "sparse")
    meta = load_meta_image(meta_dir)
    assert meta.model_path == meta_dir / "colmap" / "sparse" / "0"
    assert [p.name for p in meta.photos] == [p.name for p in load_meta_image(tiny_scene / "meta" / "front").photos]


def copy_meta(tiny_scene: Path, tmp_path: Path) -> Path:
    target = tmp_path / "front"
    shutil.copytree(tiny_scene / "meta" / "front", target)
    return target


@pytest.mark.parametrize("case", [
    "not_feature_splat", "config_is_the_run_directory", "missing_model", "corrupt_model", "missing_photo", "too_few_photos", "wrong_size", "truncated_jpeg",
    "meta_is_a_file", "output_holds_the_meta_image", "output_cannot_be_created", "nan_camera", "nan_point", "output_is_a_file", "nan_lr_flag", "threads_zero", "cuda_without_cuda", "negative_steps_preset", "negative_scale", "nan_init", "sees_nothing", "render_teacher_on_features",
])
def test_bad_inputs_fail_with_one_sentence_and_no_output(case, reference_config, tiny_scene, tmp_path, capsys, monkeypatch):
    meta_dir = copy_meta(tiny_scene, tmp_path)
    config = reference_config
    init = "identity"
    extra: list[str] = []
    gt = meta_dir / "gt_transform.json"
    expected = {
        "not_feature_splat": "expected an sg-feature-splat model",
        "config_is_the_run_directory": f"{reference_config.parent} is a directory; expected the config.yml of a trained sg-feature-splat (this one has {reference_config})",
        "missing_model": "No COLMAP model",
        "corrupt_model": "could not be read",
        "missing_photo": "missing from",
        "too_few_photos": "at least 3 are needed",
        "wrong_size": "pixels but its COLMAP camera says",
        "truncated_jpeg": "front_001.jpg could not be read as an image (image file is truncated",
        "meta_is_a_file": "front is a file; expected a directory holding images/",
        "output_cannot_be_created": "Output directory /proc/sg-nerfstudio-test/out cannot be created in /proc",
        "output_holds_the_meta_image": f"Output directory {meta_dir} is the input {meta_dir}; expected a directory apart from the inputs",
        "nan_camera": "has camera parameters [nan,",
        "nan_point": "observes 3D points that are not finite",
        "output_is_a_file": "out is a file; expected a directory there",
        "nan_lr_flag": "Registration setting optimiser.lr (--optimiser.lr) must be a finite number above 0, got nan.",
        "threads_zero": "--threads must be 1 or more",
        "cuda_without_cuda": "--device cuda was given, but torch sees no CUDA device on this machine; expected --device cpu or auto.",
        "negative_steps_preset": "steps must be a whole number of 0 or more, got -3.",
        "negative_scale": "scale must be positive",
        "nan_init": "finite 4x4",
        "sees_nothing": "renders nothing",
        "render_teacher_on_features": "--objective.render-teacher dense-sift describes rendered images",
    }[case]
    if case == "not_feature_splat":
        from nerfstudio.configs.method_configs import method_configs

        other = copy.deepcopy(method_configs["splatfacto"])
        config = tmp_path / "config.yml"
        config.write_text(yaml.dump(other))
    elif case == "config_is_the_run_directory":
        config = reference_config.parent
    elif case == "missing_model":
        shutil.rmtree(meta_dir / "sparse")
    elif case == "corrupt_model":
        (meta_dir / "sparse" / "0" / "images.bin").write_bytes(b"\x01garbage")
    elif case == "missing_photo":
        (meta_dir / "images" / "front_002.png").unlink()
    elif case == "too_few_photos":
        model = pycolmap.Reconstruction(str(meta_dir / "sparse" / "0"))
        for frame_id in list(model.reg_frame_ids())[:3]:
            model.deregister_frame(frame_id)
        model.write_binary(str(meta_dir / "sparse" / "0"))
    elif case == "wrong_size":
        photo = meta_dir / "images" / "front_001.png"
        cv2.imwrite(str(photo), cv2.resize(cv2.imread(str(photo)), (20, 20)))
    elif case in ("nan_camera", "nan_point"):
        model = pycolmap.Reconstruction(str(meta_dir / "sparse" / "0"))
        if case == "nan_camera":
            camera = next(iter(model.cameras.values()))
            camera.params = [np.nan, *camera.params[1:]]
        else:
            point = next(iter(model.points3D.values()))
            point.xyz = [np.nan, 0.0, 0.0]
        model.write_binary(str(meta_dir / "sparse" / "0"))
    elif case == "nan_lr_flag":
        extra = ["--optimiser.lr", "nan"]
    elif case == "threads_zero":
        extra = ["--threads", "0"]
    elif case == "cuda_without_cuda":  # a machine without CUDA, whatever this one has
        monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
        extra = ["--device", "cuda"]
    elif case == "negative_steps_preset":
        preset = tmp_path / "preset.yaml"
        preset.write_text("steps: -3\n")
        extra = ["--config", str(preset)]
    elif case == "output_is_a_file":
        (tmp_path / "out").write_text("the user's file")
    elif case == "meta_is_a_file":
        shutil.rmtree(meta_dir)
        meta_dir.write_text("not a meta-image")
    elif case == "truncated_jpeg":  # OpenCV decodes the first half, fills the rest with grey and only warns
        model = pycolmap.Reconstruction(str(meta_dir / "sparse" / "0"))
        next(image for image in model.images.values() if image.name == "front_001.png").name = "front_001.jpg"
        model.write_binary(str(meta_dir / "sparse" / "0"))
        photo = meta_dir / "images" / "front_001.png"
        jpeg = cv2.imencode(".jpg", cv2.imread(str(photo)))[1].tobytes()
        (meta_dir / "images" / "front_001.jpg").write_bytes(jpeg[: len(jpeg) // 2])
        photo.unlink()
    elif case in ("negative_scale", "nan_init"):
        matrix = np.eye(4)
        matrix[0, 0] = -1.0 if case == "negative_scale" else np.nan
        init = str(tmp_path / "init.json")
        Path(init).write_text(json.dumps({"matrix": matrix.tolist()}))
    elif case == "sees_nothing":
        far = np.eye(4)
        far[:3, 3] = [1e4, 1e4, 1e4]
        init = str(tmp_path / "init.json")
        Path(init).write_text(json.dumps({"matrix": (far @ np.array(json.loads(gt.read_text())["matrix"])).tolist()}))
    elif case == "render_teacher_on_features":
        extra = ["--objective.kind", "features", "--objective.render-teacher", "dense-sift"]
    out = tmp_path / "out"
    if case == "output_holds_the_meta_image":  # results go to <output-dir>/front: the meta-image itself
        out, extra = meta_dir.parent, ["--overwrite"]
    elif case == "output_cannot_be_created":  # Linux's /proc takes no new entry, even from root
        out = Path("/proc/sg-nerfstudio-test/out")
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    code, err = run_cli([
        "--load-config", str(config), "--meta-image", str(meta_dir), "--output-dir", str(out), "--init", init,
        "--optimiser.steps", "3", "--optimiser.photos-per-step", "2", *extra,
    ], capsys)
    assert code == 1
    assert expected in err, err
    assert err.strip().count("\n") == 0, err
    if case == "output_is_a_file":
        assert out.read_text() == "the user's file"
    elif case != "output_holds_the_meta_image":
        assert not out.exists()
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before  # inputs untouched


def test_a_photo_with_an_exif_orientation_is_read_on_its_stored_pixel_grid(tiny_scene, tmp_path):
    """COLMAP's camera and keypoints describe a photo's stored pixels (pycolmap reads them so); an EXIF orientation tag,
    as on portrait phone photos, must not turn the image the registration compares with its renders."""
    from PIL import Image

    meta_dir = copy_meta(tiny_scene, tmp_path)
    model = pycolmap.Reconstruction(str(meta_dir / "sparse" / "0"))
    next(image for image in model.images.values() if image.name == "front_001.png").name = "front_001.jpg"
    model.write_binary(str(meta_dir / "sparse" / "0"))
    exif = Image.Exif()
    exif[0x0112] = 6  # orientation: turn 90 degrees clockwise to view
    Image.open(meta_dir / "images" / "front_001.png").convert("RGB").save(meta_dir / "images" / "front_001.jpg", exif=exif.tobytes(), quality=95)
    (meta_dir / "images" / "front_001.png").unlink()
    stored = np.asarray(Image.open(meta_dir / "images" / "front_001.jpg").convert("RGB"))  # PIL does not apply the tag
    assert pycolmap.Bitmap.read(str(meta_dir / "images" / "front_001.jpg"), True).width == stored.shape[1]

    photo = next(p for p in load_meta_image(meta_dir).photos if p.name == "front_001.jpg")
    assert stored.shape[:2] == (photo.camera.height, photo.camera.width) and stored.shape[0] != stored.shape[1]
    loaded = photo.load_undistorted()
    assert loaded.shape == stored.shape
    assert np.abs(loaded.astype(float) - stored).mean() < 2.0  # undistorted by its small k1 (0.5 here), not turned


def moved_meta_image(source: Path, target: Path, similarity: Sim3) -> Path:
    """A copy of a meta-image expressed in another frame (x_new = similarity x_old), with its ground truth."""
    shutil.copytree(source, target)
    sparse = target / "sparse" / "0" if (target / "sparse" / "0").is_dir() else target / "sparse"
    reconstruction = pycolmap.Reconstruction(str(sparse))
    reconstruction.transform(pycolmap.Sim3d(similarity.scale, pycolmap.Rotation3d(similarity.rotation), similarity.translation))
    reconstruction.write_binary(str(sparse))
    truth = np.array(json.loads((source / "gt_transform.json").read_text())["matrix"]) @ similarity.inverse().matrix
    (target / "gt_transform.json").write_text(json.dumps({"matrix": truth.tolist()}))
    return target


def test_several_meta_images_merge_into_one_model_in_the_reference_frame(reference_config, tiny_scene, tmp_path, capsys):
    """Two meta-images (the second in another frame) registered in one call land in merged/ with every
    camera where its own registration put it, which is within the registration tolerance of the truth."""
    first = tiny_scene / "meta" / "front"
    second = moved_meta_image(first, tmp_path / "front_moved", Sim3.random(np.random.default_rng(3), 40.0, 2.0, 0.5))
    out = tmp_path / "out"
    metas = [first, second]
    # 5 small steps from the truth stay near it (on this 36-52 px, 60%-occluded scene the objective's own minimum is
    # degrees away: fast-cpu from the truth ends 6.6° off), hence no refine stage either
    args = ["--load-config", str(reference_config), "--output-dir", str(out), "--optimiser.steps", "5", "--optimiser.lr", "0.001", "--last-stage.steps", "0", "--merge-reference"]
    for meta_dir in metas:
        args += ["--meta-image", str(meta_dir), "--init", str(meta_dir / "gt_transform.json"), "--gt", str(meta_dir / "gt_transform.json")]
    code, err = run_cli(args, capsys)
    assert code == 0, err
    merged = pycolmap.Reconstruction(str(out / "merged"))
    record = json.loads((out / "merged" / "merge.json").read_text())
    assert [part["source"] for part in record["merged"]] == ["reference", "front", "front_moved"] and record["not_merged"] == []
    reference_images = pycolmap.Reconstruction(str(tiny_scene / "reference" / "colmap" / "sparse" / "0")).num_reg_images()
    assert merged.num_images() == reference_images + 2 * len(load_meta_image(first).photos)
    assert merged.num_points3D() == sum(part["points3D"] for part in record["merged"])
    for meta_dir in metas:
        meta = load_meta_image(meta_dir)
        result = np.array(json.loads((out / meta.name / "transform.json").read_text())["matrix"])
        truth = np.array(json.loads((meta_dir / "gt_transform.json").read_text())["matrix"])
        for photo in meta.photos:
            image = merged.find_image_with_name(f"{meta.name}/{photo.name}")
            np.testing.assert_allclose(image.projection_center(), (result @ np.append(photo.centre, 1))[:3], atol=1e-6)
        errors = pose_errors(meta.poses, Sim3.from_matrix(result), Sim3.from_matrix(truth))
        assert errors.rotation_deg < 1.0 and errors.translation < 0.05, errors
    assert {track.image_id for point in merged.points3D.values() for track in point.track.elements} <= set(merged.reg_image_ids())


def test_verdict_rule_follows_its_evidence():
    from sg_nerfstudio.registration.verdict import Evidence, decide

    sound = dict(sharpness=2 * verdict.REGISTERED_SHARPNESS, flattest_rise=0.05, agreeing_photos=8, photos=10, median_coverage=0.8,
                 objective_drop=0.3, probe_rotation_deg=1.8, probe_translation=0.02)
    assert decide(Evidence(**sound)).label == "registered"
    assert decide(Evidence(**sound | {"agreeing_photos": 2})).label == "failed"
    assert decide(Evidence(**sound | {"sharpness": 0.5 * verdict.FAILED_SHARPNESS})).label == "failed"
    shallow = 0.5 * (verdict.FAILED_SHARPNESS + verdict.REGISTERED_SHARPNESS)
    assert decide(Evidence(**sound | {"sharpness": shallow})).label == "uncertain"
    descending = decide(Evidence(**sound | {"flattest_rise": 2 * verdict.DESCENT_TOLERANCE}))
    assert descending.label == "uncertain" and "not converged" in descending.reasons[0]
    held = {"sharpness": shallow, "keypoint_photos": 2, "keypoint_error_cells": 0.5 * verdict.ANCHORS_HOLD_CELLS,
            "keypoint_scale_motion_px": 2.0, "keypoint_error_px": 0.5}
    anchored = decide(Evidence(**sound | held))
    assert anchored.label == "registered" and "anchors of 2 photos hold" in anchored.reasons[1]
    # most of enough of the meta-image's own points on the reference's surface hold a shallow minimum as anchors do
    depths = {"sharpness": shallow, "depth_agreeing": 0.9, "depth_points": 2 * verdict.DEPTH_HOLDS_POINTS}
    held_by_depths = decide(Evidence(**sound | depths))
    assert held_by_depths.label == "registered" and "90% of 100 sparse points lie within 10%" in held_by_depths.reasons[1]
    too_few = decide(Evidence(**sound | depths | {"depth_agreeing": 0.9 * verdict.DEPTH_HOLDS_SHARE}))
    assert too_few.label == "uncertain" and "54% of 100 sparse points" in too_few.reasons[0]
    assert decide(Evidence(**sound | depths | {"depth_points": verdict.DEPTH_HOLDS_POINTS - 1})).label == "uncertain"
    assert decide(Evidence(**sound | depths | {"flattest_rise": 2 * verdict.DESCENT_TOLERANCE})).label == "uncertain"
    assert decide(Evidence(**sound | depths | {"agreeing_photos": 4})).label == "uncertain"
    # anchors that a 2% scale change barely moves (one photo's, or photos from one spot) do not fix the scale
    assert decide(Evidence(**sound | held | {"keypoint_scale_motion_px": 0.01})).label == "uncertain"
    assert decide(Evidence(**sound | held | {"keypoint_scale_motion_px": 0.05, "keypoint_error_px": 0.0})).label == "uncertain"
    refused = decide(Evidence(**sound | {"camera_fit_refused": "a photo turned 3.9° (beyond 2°)"}))
    assert refused.label == "uncertain" and refused.reasons[0].startswith("the camera fit was refused (a photo turned 3.9°")
    off = decide(Evidence(**sound | held | {"keypoint_error_cells": 2 * verdict.ANCHORS_HOLD_CELLS}))
    assert off.label == "uncertain" and any("anchors reproject 0.500 cells off" in reason for reason in off.reasons)
    # anchors that do not hold also overrule a sharp minimum: verified matches disagree with the result
    sharp_but_off = decide(Evidence(**sound | {"keypoint_photos": 2, "keypoint_error_cells": 2 * verdict.ANCHORS_HOLD_CELLS}))
    assert sharp_but_off.label == "uncertain" and "anchors reproject" in sharp_but_off.reasons[0]
    # a photo at a maximum of its own loss contradicts the result; one that reads flat (occluded) does not
    rises, covered = [0.1] * 8 + [0.0, 0.0], [0.8] * 10
    assert decide(Evidence(**sound | {"per_photo_rise": rises, "per_photo_coverage": covered})).label == "registered"
    falling = rises[:-1] + [-2 * verdict.PHOTO_RISE]
    contradicted = decide(Evidence(**sound | {"per_photo_rise": falling, "per_photo_coverage": covered}))
    assert contradicted.label == "uncertain" and contradicted.reasons[0].startswith("1 photo(s) contradict the result")
    # a photo the model barely covers says little about the pose, falling or not
    barely = covered[:-1] + [0.5 * verdict.PHOTO_COVERAGE]
    assert decide(Evidence(**sound | {"per_photo_rise": falling, "per_photo_coverage": barely})).label == "registered"
    assert decide(Evidence(**sound | held | {"flattest_rise": 2 * verdict.DESCENT_TOLERANCE})).label == "uncertain"
    assert decide(Evidence(**sound | held | {"sharpness": 0.5 * verdict.FAILED_SHARPNESS})).label == "failed"
    scale_seen = {"scale_rise": 2 * verdict.REGISTERED_SHARPNESS, "scale_probe": 0.04}
    assert decide(Evidence(**sound | scale_seen)).label == "registered"
    assert decide(Evidence(**sound | scale_seen | {"scale_rise": 0.5 * verdict.REGISTERED_SHARPNESS})).label == "registered"
    flat_scale = decide(Evidence(**sound | scale_seen | {"scale_rise": 0.5 * verdict.FAILED_SHARPNESS}))
    assert flat_scale.label == "uncertain" and flat_scale.reasons[0].startswith("scale not fixed")
    # another minimum as deep as the result (one window along a repetitive facade) makes it uncertain; a deeper one too
    assert decide(Evidence(**sound | {"other_minimum_rise": 10 * verdict.OTHER_MINIMUM_MARGIN, "other_minimum_cells": 8.0})).label == "registered"
    twin = decide(Evidence(**sound | {"other_minimum_rise": 0.5 * verdict.OTHER_MINIMUM_MARGIN, "other_minimum_cells": 8.0}))
    assert twin.label == "uncertain" and twin.reasons[0].startswith("another minimum 8 cells away is only 2.5% higher")
    deeper = decide(Evidence(**sound | {"other_minimum_rise": -0.1, "other_minimum_cells": 8.0}))
    assert deeper.label == "uncertain" and "10.0% lower" in deeper.reasons[0]
    # an orbit about where the photos look that lowers the objective: not at the minimum along the weakest direction
    assert decide(Evidence(**sound | {"orbit_rise": 0.5 * verdict.DESCENT_TOLERANCE})).label == "registered"
    orbiting = decide(Evidence(**sound | {"orbit_rise": 2 * verdict.DESCENT_TOLERANCE}))
    assert orbiting.label == "uncertain" and orbiting.reasons[0] == (
        "not converged about the photographed scene: turning the result 2.5° about where the photos look lowers the objective 1.0%"
    )


def test_orbit_probes_turn_about_where_the_photos_look(meta):
    """The six orbit probes turn the result by ORBIT_DEG and leave the point the photos look at where it is;
    `orbit_rise` is the lowest of their robust objectives relative to the result's."""
    from sg_nerfstudio.geometry.sim3 import rotation_angle_deg

    transform = Sim3.from_matrix(np.diag([2.0, 2.0, 2.0, 1.0]))
    centre = torch.from_numpy(meta.look_at_under(transform))
    looked_at = meta.look_at_under(Sim3.from_matrix(np.eye(4)))  # meta coordinates
    deltas = verdict.orbit_probes(np.radians(verdict.ORBIT_DEG))
    assert len(deltas) == 6
    for delta in deltas:
        moved = (Sim3.update(delta, centre) @ transform.to_torch()).numpy()
        assert rotation_angle_deg(np.asarray(moved.rotation) @ np.asarray(transform.rotation).T) == pytest.approx(verdict.ORBIT_DEG)
        np.testing.assert_allclose(moved.apply(looked_at), centre.numpy(), atol=1e-9)

    lowest = np.asarray((Sim3.update(deltas[1], centre) @ transform.to_torch()).numpy().rotation)

    class TurnLosses:  # every photo's loss grows with the turn away from the second probe's rotation
        photos = [None, None]

        def __call__(self, sim3, indices):
            value = 1.0 + 0.01 * rotation_angle_deg(np.asarray(sim3.numpy().rotation) @ lowest.T)
            return [torch.tensor(value, dtype=torch.float64)] * len(indices), torch.ones(len(indices))

    rule = TrimmingRule.of(RegistrationSettings())
    assert verdict.orbit_rise(TurnLosses(), meta, transform, np.array([1.05, 1.05]), rule) == pytest.approx(1.0 / 1.05 - 1.0, abs=1e-9)


def test_the_look_for_another_minimum_finds_a_repetition_and_nothing_where_there_is_none(meta):
    """On a known objective of the translation alone: wells every `period` along the photos' mean image x axis (a
    facade of identical windows) give another minimum `period` away, at the depth given; one well gives none."""
    from sg_nerfstudio.registration import other_minimum

    result = Sim3.identity()
    x_axis = other_minimum.image_axes(meta, result)[0]
    probe, period = 0.01, 0.075  # the repetition: 7.5 translation probes

    def wells(depth_of_others: float, periodic: bool):
        def objective(transform: Sim3) -> float:
            offset = np.asarray(transform.translation)
            along, across = float(offset @ x_axis), float(np.linalg.norm(offset - (offset @ x_axis) * x_axis))
            well = round(along / period) if periodic else 0
            floor = 1.0 if well == 0 else 1.0 + depth_of_others
            return floor + 50.0 * ((along - well * period) ** 2 + across**2) ** 0.5

        def refine(start: Sim3) -> Sim3:  # the optimiser: to the bottom of the well it starts in
            along = float(np.asarray(start.translation) @ x_axis)
            well = round(along / period) if periodic else 0
            return Sim3.from_parts(1.0, np.eye(3), well * period * x_axis)

        return objective, refine

    def look(depth: float, periodic: bool = True):
        objective, refine = wells(depth, periodic)
        return other_minimum.look_for_other_minimum(objective, refine, meta, result, objective(result), np.radians(1.8), probe, sharpness=0.1)

    for depth in (0.003, 0.1):
        found = look(depth)
        assert found is not None and found.rise == pytest.approx(depth) and found.distance_cells == pytest.approx(period / probe)
    assert look(other_minimum.DESCENT_GATE + 0.1) is None  # a dip too high to be a minimum as deep: no descent
    assert look(0.0, periodic=False) is None


def test_depth_ratios_follow_the_scale_of_points_on_a_known_surface():
    """A flat depth map at 4 units: points at camera depth 2 agree under scale 2, read -log(1.25) under scale 2.5;
    points behind the camera, outside the render or where it is not covered are left out."""
    K = np.array([[10.0, 0.0, 8.0], [0.0, 10.0, 6.0], [0.0, 0.0, 1.0]])
    points = np.array([[0.0, 0.0, 2.0], [0.4, -0.2, 2.0], [0.0, 0.0, -2.0], [5.0, 0.0, 2.0], [-0.6, 0.5, 2.0]])
    pixels = PointPixels.of(points, K, 16, 12)
    assert pixels.columns.tolist() == [8, 10, 5] and pixels.rows.tolist() == [6, 5, 8]  # floor(K x / z)
    depth, alpha = torch.full((12, 16), 4.0), torch.ones(12, 16)
    alpha[8, 5] = 0.2  # the last point's pixel is barely covered
    np.testing.assert_allclose(log_depth_ratios(depth, alpha, pixels, torch.tensor(np.log(2.0))).numpy(), [0.0, 0.0], atol=1e-12)
    ratios = log_depth_ratios(depth, alpha, pixels, torch.tensor(np.log(2.5)))
    np.testing.assert_allclose(ratios.numpy(), [-np.log(1.25)] * 2, atol=1e-12)
    summary = summarise([ratios, ratios[:0]])
    assert summary.points == 2 and summary.log_ratio == pytest.approx(-np.log(1.25)) and summary.agreeing == 0.0


def test_depth_agreement_of_the_meta_image_follows_a_wrong_scale(reference, meta, ground_truth):
    """The meta-image's own sparse points against the reference's rendered depth: scaling the truth about its
    cameras (they stay, the points move) by 1.25 or 0.8 shifts the median log ratio by about -log of the factor.
    (Its value at the truth is -0.20 on this 300-step reference, whose floaters sit in front of the surface; within
    ±0.03 on the 1500-step references of docs/measurements.md "Depth agreement".)"""
    settings = FAST.changed(objective={"kind": "teacher-on-render"})
    objective = build_objective(reference, settings)
    truth = reference.world_to_dataparser @ ground_truth
    near_plane = optimize.effective_near_plane(meta, truth, settings.objective.near_plane)
    losses = PhotoLosses(reference, prepare_photos(reference, meta, settings, objective), objective, settings, near_plane)
    indices = list(range(len(meta.photos)))

    def agreement(factor: float):
        transform = hypotheses.scaled_about_centroid(truth, meta, factor)
        return summarise(losses.evaluate(transform.to_torch(), indices, with_depth=True)[2])

    at_truth, larger, smaller = agreement(1.0), agreement(1.25), agreement(0.8)
    assert min(at_truth.points, larger.points, smaller.points) > 1000
    assert larger.log_ratio - at_truth.log_ratio == pytest.approx(-np.log(1.25), abs=0.08)
    assert smaller.log_ratio - at_truth.log_ratio == pytest.approx(-np.log(0.8), abs=0.08)
    assert larger.agreeing < at_truth.agreeing


def facing_the_other_side(ground_truth: Sim3) -> Sim3:
    """The ground truth turned 180° about the vertical axis through the reference origin: the photos of one
    facade looking at the opposite one."""
    return Sim3.from_parts(1.0, np.diag([-1.0, -1.0, 1.0]), np.zeros(3)) @ ground_truth


def test_a_start_facing_the_wrong_side_is_flagged_and_one_at_the_truth_is_not(reference, meta, ground_truth, monkeypatch):
    """Also: without anchors the verdict looks for another minimum (registration/other_minimum.py) and probes orbits
    about where the photos look, and the truth of the tiny scene (windows with unique detail) has no other minimum as
    deep and no orbit that descends."""
    from sg_nerfstudio.registration import other_minimum

    looks, look = [], other_minimum.look_for_other_minimum
    monkeypatch.setattr(other_minimum, "look_for_other_minimum", lambda *args, **kwargs: looks.append(look(*args, **kwargs)) or looks[-1])
    settings = FAST.changed(optimiser={"steps": 20}, objective={"kind": "teacher-on-render"})
    wrong = register(reference, meta, facing_the_other_side(ground_truth), settings)
    looks.clear()
    right = register(reference, meta, ground_truth, settings)
    assert len(looks) == 1 and (looks[0] is None or looks[0].rise >= other_minimum.MARGIN)
    assert pose_errors(meta.poses, wrong.transform, ground_truth).outlier()
    assert wrong.verdict.label != "registered", wrong.verdict
    assert right.verdict.label == "registered", right.verdict
    assert right.verdict.evidence.depth_points > 0 and np.isfinite(right.verdict.evidence.depth_log_ratio)
    assert right.verdict.evidence.orbit_rise >= verdict.DESCENT_TOLERANCE  # probed without anchors, at its minimum


def test_coarse_stages_and_hypotheses_reach_the_known_optimum(reference, meta, ground_truth, monkeypatch):
    """Targets rendered by the model at the truth (for every stage), a start 12° / 0.1 / 10% away: a coarse stage,
    27 hypotheses (the start and 8 rotations, each at 3 scales) of which 3 are optimised, then the main stage end
    at the truth; history and step count follow the stages."""
    original = optimize.prepare_photos
    rendered = lambda ref, m, s, objective=None: rendered_targets(ref, m, original(ref, m, s, objective), ground_truth, s)
    for module in (optimize, stages):  # the main stage's photos and the coarse stage's
        monkeypatch.setattr(module, "prepare_photos", rendered)
    settings = FAST.changed(optimiser={"steps": 60, "lr": 0.01, "lr_final": 0.0005}, objective={"kind": "teacher-on-render", "render_scale": 4.0}, coarse_to_fine={"factors": (2,), "steps": 40}, hypotheses={"count": 8, "scales": (0.8, 1.25)})
    start = perturbed_start(meta, ground_truth, 30, 12.0, 0.1, 0.1)
    steps = []
    result = register(reference, meta, start, settings, on_step=lambda step, _: steps.append(step))
    errors = pose_errors(meta.poses, result.transform, ground_truth)
    assert errors.rotation_deg < 1.0 and errors.translation < 0.05, errors
    assert len(steps) == optimize.total_steps(settings) == 60 + 3 * 40  # every optimised hypothesis runs the coarse stage
    assert result.steps == 100 and len(result.hypotheses) == 3 and sum(h["agrees_with_winner"] for h in result.hypotheses) >= 1
    assert all(h["scale"] in (1.0, 0.8, 1.25) for h in result.hypotheses)
    assert [row["stage"] for row in result.history[:: len(meta.photos)]] == ["coarse-64"] * 40 + ["main"] * 60


def test_a_dense_start_beside_a_far_one_ends_at_the_truth_unless_anchors_hold(reference, meta, ground_truth, monkeypatch):
    """Targets rendered by the model at the truth, a given start 30° / 0.4 / 20% away and another start 2° away (as the
    dense initialiser would give): both run the main stage, the other one's end wins and is accurate, the step count
    includes both, and the records say which start won. With keypoint anchors the other start is not run."""
    original = optimize.prepare_photos
    monkeypatch.setattr(optimize, "prepare_photos", lambda ref, m, s, objective=None: rendered_targets(ref, m, original(ref, m, s, objective), ground_truth, s))
    settings = FAST.changed(optimiser={"steps": 40, "lr": 0.01, "lr_final": 0.0005}, objective={"kind": "teacher-on-render", "render_scale": 4.0})
    far, near = perturbed_start(meta, ground_truth, 31, 30.0, 0.4, 0.2), perturbed_start(meta, ground_truth, 32, 2.0, 0.02, 0.02)
    steps = []
    result = register(reference, meta, far, settings, on_step=lambda step, _: steps.append(step), other_starts=[("dense", near)])
    errors = pose_errors(meta.poses, result.transform, ground_truth)
    assert errors.rotation_deg < 1.0 and errors.translation < 0.05, errors
    assert len(steps) == optimize.total_steps(settings, other_starts=1) == 2 * 40 and result.steps == 40
    assert [(h["start"], h["won"]) for h in result.hypotheses] == [("given", False), ("dense", True)]
    anchored = settings.changed(optimiser={"update_centre": "look-at"}, anchors={"weight": 1.0})
    keypoints = projected_keypoints(reference, meta, ground_truth, 40, 0.0, seed=3)
    held = register(reference, meta, near, anchored, keypoints=keypoints, other_starts=[("dense", far)])
    assert held.hypotheses == [] and optimize.total_steps(anchored, anchored=True, other_starts=1) == held.steps == 40


def test_fail_on_and_merged_leave_out_a_failed_verdict(reference_config, tiny_scene, tmp_path, capsys, monkeypatch):
    """Two meta-images, the second judged failed (the rule is forced here; its evidence is tested above): the
    table and transform.json carry the verdicts, merged/ holds only the first and says why, --fail-on failed
    exits with status 2 and --fail-on uncertain too."""
    from sg_nerfstudio.registration.verdict import Verdict, decide

    first = tiny_scene / "meta" / "front"
    second = moved_meta_image(first, tmp_path / "front_moved", Sim3.random(np.random.default_rng(4), 30.0, 1.0, 0.3))
    calls = []
    monkeypatch.setattr(optimize, "decide", lambda evidence: calls.append(1) or (decide(evidence) if len(calls) % 2 else Verdict("failed", ["forced by the test"], evidence)))
    for fail_on, out in (("failed", tmp_path / "out"), ("uncertain", tmp_path / "out2")):
        args = ["--load-config", str(reference_config), "--output-dir", str(out), "--optimiser.steps", "3", "--fail-on", fail_on]
        for meta_dir in (first, second):
            args += ["--meta-image", str(meta_dir), "--init", str(meta_dir / "gt_transform.json")]
        capsys.readouterr()
        code = register_main(args)
        printed, err = capsys.readouterr()
        assert code == 2 and "front_moved" in err and f"--fail-on {fail_on}" in err, err
        assert json.loads((out / "front_moved" / "transform.json").read_text())["verdict"] == "failed"
        assert json.loads((out / "front" / "transform.json").read_text())["verdict"] in {"registered", "uncertain", "failed"}
        record = json.loads((out / "merged" / "merge.json").read_text())
        assert [part["source"] for part in record["merged"]] == ["front"]
        front = json.loads((out / "front" / "transform.json").read_text())
        assert record["merged"][0]["verdict"] == front["verdict"] and record["merged"][0]["verdict_reasons"] == front["verdict_reasons"]
        assert record["not_merged"] == [{"source": "front_moved", "reason": "verdict failed: forced by the test"}]
        assert "failed" in printed


def projected_keypoints(reference, meta, truth: Sim3, count: int, outlier_fraction: float, seed: int):
    """Keypoint anchors made from the truth: reference points (Gaussian centres, world frame) seen by each photo,
    projected through the photo's real pycolmap camera (its distortion included) under `truth`; a fraction of
    each photo's keypoints moved to random pixels (the mismatches RANSAC lets through)."""
    from sg_nerfstudio.initialisers.estimate import PhotoKeypoints

    rng = np.random.default_rng(seed)
    world = reference.world_to_dataparser.inverse().apply(reference.means.detach().double().cpu().numpy())
    anchors = []
    for photo in meta.photos:
        cam_from_world = truth.move_camera(photo.cam_from_world)  # the photo's camera in the reference world
        in_camera = world @ cam_from_world[:, :3].T + cam_from_world[:, 3]
        front = in_camera[:, 2] > 0.1
        pixels = np.zeros((len(world), 2))
        pixels[front] = photo.camera.img_from_cam(in_camera[front])
        inside = front & (pixels[:, 0] > 0) & (pixels[:, 1] > 0) & (pixels[:, 0] < photo.camera.width) & (pixels[:, 1] < photo.camera.height)
        chosen = rng.choice(np.flatnonzero(inside), min(count, int(inside.sum())), replace=False)
        points2D = pixels[chosen].copy()
        wrong = rng.random(len(chosen)) < outlier_fraction
        points2D[wrong] = rng.uniform([0, 0], [photo.camera.width, photo.camera.height], size=(int(wrong.sum()), 2))
        anchors.append(PhotoKeypoints(photo.name, points2D, world[chosen]))
    return anchors


def test_keypoint_term_vanishes_at_the_truth_and_grows_away_from_it(reference, meta, ground_truth):
    """Exact keypoints (through the photos' own distortion) reproject to 0 cells at the truth; a 1° rotation or a
    2% scale moves them by about what the camera geometry says; a photo without keypoints adds nothing."""
    from sg_nerfstudio.registration.anchored_start.anchors import KeypointTerm

    anchors = projected_keypoints(reference, meta, ground_truth, 60, 0.0, seed=0)
    term = KeypointTerm(meta, anchors, reference.world_to_dataparser, grid_size=32, weight=1.0)
    truth_ns = reference.world_to_dataparser @ ground_truth
    assert term.median_error_cells(truth_ns) < 1e-4  # pycolmap undistorts iteratively
    rotated = reference.world_to_dataparser @ perturbed_start(meta, ground_truth, 1, 1.0, 0.0, 0.0)
    focal_cells = np.median([p.pinhole_intrinsics()[0, 0] / (max(p.camera.width, p.camera.height) / 32) for p in meta.photos])
    moved = term.median_error_cells(rotated)
    assert 0.2 * np.radians(1.0) * focal_cells < moved < 3.0 * np.radians(1.0) * focal_cells, (moved, focal_cells)
    assert float(term(truth_ns.to_torch())) < 1e-6 < float(term(rotated.to_torch()))
    only_first = KeypointTerm(meta, anchors[:1], reference.world_to_dataparser, grid_size=32, weight=1.0)
    assert only_first.photos == 1 and only_first.median_error_cells(truth_ns) < 1e-4


def test_keypoint_anchors_hold_the_answer_where_the_dense_minimum_is_off(reference, meta, ground_truth, monkeypatch):
    """The real-photo failure in miniature: the photos' targets are the model rendered 1.5° away from the truth
    (a dense objective whose minimum is not the answer), the keypoints (20% of them wrong matches) are exact.
    From a 5° start the dense objective alone ends near its own minimum, more than 1° from the truth; with the
    anchors the registration ends within 0.6° of the truth (measured 0.45° on an AMD EPYC, under 0.4° before), and the verdict does not look for another minimum of
    the dense objective (the anchors fix the pose; registration/other_minimum.py)."""
    from sg_nerfstudio.registration import other_minimum

    looks = []
    monkeypatch.setattr(other_minimum, "look_for_other_minimum", lambda *args, **kwargs: looks.append(args))
    settings = FAST.changed(optimiser={"steps": 60, "lr": 0.01, "lr_final": 0.0005, "update_centre": "look-at"}, objective={"kind": "teacher-on-render"}, anchors={"weight": 3.0})
    biased = perturbed_start(meta, ground_truth, 5, 1.5, 0.03, 0.02)
    photos = rendered_targets(reference, meta, prepare_photos(reference, meta, settings), biased, settings)
    start = perturbed_start(meta, ground_truth, 3, 5.0, 0.1, 0.1)
    anchors = projected_keypoints(reference, meta, ground_truth, 40, 0.2, seed=1)
    poses = meta.poses
    dense_only = register(reference, meta, start, settings.changed(anchors={"weight": 0.0}), photos=photos, keypoints=anchors)
    assert pose_errors(poses, dense_only.transform, ground_truth).rotation_deg > 1.0
    looked = len(looks)
    anchored = register(reference, meta, start, settings, photos=photos, keypoints=anchors)
    assert pose_errors(poses, anchored.transform, ground_truth).rotation_deg < 0.6
    assert len(looks) == looked


def test_cli_keypoint_anchors_off_when_the_reference_gives_no_sift_cloud(reference_config, tiny_scene, tmp_path, capsys):
    """--keypoint-weight on the tiny scene (48x36 reference renders: nothing SIFT can match): one line says the
    anchors are off and why, the dense registration runs and its result carries no keypoint evidence.
    (Anchors that exist are tested with the initialisers' textured scene and the optimiser above.)"""
    meta_dir = tiny_scene / "meta" / "front"
    out = tmp_path / "out"
    capsys.readouterr()
    code = register_main([
        "--load-config", str(reference_config), "--meta-image", str(meta_dir), "--output-dir", str(out),
        "--init", str(meta_dir / "gt_transform.json"), "--optimiser.steps", "3", "--anchors.weight", "1",
        "--init-cache-dir", str(tmp_path / "sift"),
    ])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    assert "front: keypoint anchors are off (the dense objective alone): No pair of reference images" in " ".join(printed.out.split())
    evidence = json.loads((out / "front" / "transform.json").read_text())["verdict_evidence"]
    assert evidence["keypoint_photos"] is None and evidence["keypoint_error_cells"] is None


def test_keypoint_prealignment_brings_a_30_degree_start_home(reference, meta, ground_truth, tmp_path):
    """On the tiny scene, from 30° / 0.5 / 30% away: the keypoint term alone (20% wrong matches, no render) moves
    the start to within 0.05° of the truth, and a registration with anchors and that pre-alignment ends within
    0.5° where the dense objective alone, from the same start, does not reach 5°. The pre-aligned registration runs
    the short `prealigned_*` schedule, the dense one without anchors the full `steps`; with `prealigned_steps` 0 it is
    the keypoint fit alone, and its outputs are written (a loss curve without steps)."""
    from sg_nerfstudio.registration.anchored_start.anchors import Anchoring
    from sg_nerfstudio.registration.outputs import write_outputs

    anchors = projected_keypoints(reference, meta, ground_truth, 40, 0.2, seed=2)
    start = perturbed_start(meta, ground_truth, 4, 30.0, 0.5, 0.3)
    anchoring = Anchoring(meta, anchors, Sim3.identity(), 1.0)  # in the world frame: no dataparser transform needed
    prealigned = anchoring.prealign(start, meta.look_at_under(start), grid_size=32, steps=1000)
    assert pose_errors(meta.poses, prealigned, ground_truth).rotation_deg < 0.05
    settings = FAST.changed(optimiser={"steps": 30, "lr": 0.01, "lr_final": 0.0005, "update_centre": "look-at"}, objective={"kind": "teacher-on-render"}, anchors={"weight": 3.0, "prealign_steps": 1000, "main_steps": 10, "main_lr": 0.002})
    anchored = register(reference, meta, start, settings, keypoints=anchors)
    assert pose_errors(meta.poses, anchored.transform, ground_truth).rotation_deg < 0.5
    assert anchored.steps == optimize.total_steps(settings, anchored=True) == 10
    dense_only = register(reference, meta, start, settings.changed(anchors={"weight": 0.0}), keypoints=anchors)
    assert pose_errors(meta.poses, dense_only.transform, ground_truth).rotation_deg > 5.0
    assert dense_only.steps == optimize.total_steps(settings) == 30
    keypoints_only = register(reference, meta, start, settings.changed(anchors={"main_steps": 0}), keypoints=anchors)
    assert keypoints_only.steps == 0 and pose_errors(meta.poses, keypoints_only.transform, ground_truth).rotation_deg < 0.05
    written = write_outputs(tmp_path / "keypoints-only", reference, meta, keypoints_only)
    assert (written / "report" / "loss_curve.png").stat().st_size > 0 and (written / "transform.json").exists()


def test_anchors_that_hold_make_a_shallow_minimum_registered_unless_the_photos_disagree(reference, meta, ground_truth, monkeypatch):
    """The verdict with keypoint anchors: exact anchors hold the registration at the truth, where the dense objective
    rises little one cell away (uncertain by sharpness alone): registered. Anchors made 8° away (consistent with each
    other, as a wrong but verified match set would be) hold it there just as well, but the photos' dense losses do not
    agree with that pose: not registered, even with a shallow minimum forgiven.

    The tiny reference's rise at the truth depends on its draw: under 5% (REGISTERED_SHARPNESS) on the pinned code
    paths, 6.2% with torch's non-vector kernels (2026-12-06). Where it is not shallow by the rule, the rule is read with
    its threshold above the rise, so the case tested is the same on every draw."""
    settings = FAST.changed(optimiser={"steps": 30, "lr": 0.01, "lr_final": 0.0005, "update_centre": "look-at"}, objective={"kind": "teacher-on-render"}, anchors={"weight": 10.0, "prealign_steps": 1000, "main_steps": 20, "main_lr": 0.003})
    right = register(reference, meta, ground_truth, settings, keypoints=projected_keypoints(reference, meta, ground_truth, 40, 0.0, seed=3))
    evidence = right.verdict.evidence
    if evidence.sharpness >= verdict.REGISTERED_SHARPNESS:
        monkeypatch.setattr(verdict, "REGISTERED_SHARPNESS", 1.5 * evidence.sharpness)
    decided = verdict.decide(evidence)
    assert evidence.sharpness < verdict.REGISTERED_SHARPNESS and evidence.anchors_hold
    assert not any(reason.startswith("shallow minimum") for reason in decided.reasons), decided
    # registered, unless the tiny reference's dense objective descends a cell away from the truth (the pinned paths'
    # draw: a probe 2.0% lower, `uncertain` for that alone)
    descends = evidence.flattest_rise < verdict.DESCENT_TOLERANCE
    assert decided.label == "registered" or (descends and len(decided.reasons) == 1), decided
    elsewhere = perturbed_start(meta, ground_truth, 11, 8.0, 0.08, 0.0)
    wrong = register(reference, meta, ground_truth, settings, keypoints=projected_keypoints(reference, meta, elsewhere, 40, 0.0, seed=3))
    assert pose_errors(meta.poses, wrong.transform, ground_truth).rotation_deg > 7.0 and wrong.verdict.evidence.anchors_hold
    assert wrong.verdict.label != "registered", wrong.verdict


def with_wrong_focal_lengths(meta, factor: float):
    """The meta-image as if its SfM had found every focal length `factor` times the true one (poses unchanged)."""
    reconstruction = pycolmap.Reconstruction(meta.reconstruction)
    for camera in reconstruction.cameras.values():
        params = np.array(camera.params)
        params[list(camera.focal_length_idxs())] *= factor
        camera.params = params
    photos = [replace(photo, camera=copy.deepcopy(reconstruction.cameras[photo.camera.camera_id])) for photo in meta.photos]
    return replace(meta, photos=photos, reconstruction=reconstruction)


def test_focal_refinement_recovers_a_wrong_sfm_focal_length(reference, meta, ground_truth, tmp_path):
    """Keypoints seen through the true cameras, a meta-image whose SfM focal lengths are 5% long: the Sim(3) alone
    cannot absorb it (the pre-aligned cameras end off the truth), the joint fit of `refine_focal` finds scales
    within 1% of 1/1.05 (the rest is the SfM's own uncertainty, held at the keypoints' noise: 0.5 px on these 48-px
    photos) and puts the cameras back; a registration with it renders and records that scale (transform.json, the
    aligned model's cameras)."""
    from sg_nerfstudio.registration.anchored_start.anchors import Anchoring
    from sg_nerfstudio.registration.outputs import write_outputs

    anchors = projected_keypoints(reference, meta, ground_truth, 60, 0.0, seed=3)
    wrong = with_wrong_focal_lengths(meta, 1.05)
    anchoring = Anchoring(wrong, anchors, Sim3.identity(), 1.0)  # in the world frame: no dataparser transform needed
    prealigned = anchoring.prealign(ground_truth, wrong.look_at_under(ground_truth), grid_size=32, steps=1000)
    fit = fit_cameras(anchoring, prealigned, wrong.look_at_under(prealigned), grid_size=32, iterations=1000, focal=True, pose_prior_scale=None)
    fitted, scales = fit.transform, fit.focal_scales
    assert fit.poses == {} and sorted(scales) == sorted(photo.name for photo in meta.photos)
    assert np.allclose(list(scales.values()), 1 / 1.05, atol=0.01)
    before, after = (pose_errors(meta.poses, transform, ground_truth).translation for transform in (prealigned, fitted))
    assert after < before / 3
    far_off = Anchoring(with_wrong_focal_lengths(meta, 1.5), anchors, Sim3.identity(), 1.0)  # beyond MAX_FOCAL_CHANGE
    dropped = fit_cameras(far_off, prealigned, wrong.look_at_under(prealigned), grid_size=32, iterations=1000, focal=True, pose_prior_scale=None)
    assert dropped.transform is prealigned and dropped.focal_scales == {}
    assert fit.refused == "" and dropped.refused.startswith("a focal length x") and dropped.refused.endswith("(beyond 20%)")
    assert float(dropped.refused.split("x")[1].split()[0]) < 1 / 1.2  # the fitted scale, toward the true 1 / 1.5

    settings = FAST.changed(optimiser={"steps": 3}, objective={"kind": "teacher-on-render"}, anchors={"weight": 1.0, "prealign_steps": 1000, "main_steps": 2}, camera_fit={"focal": True})
    result = register(reference, wrong, ground_truth, settings, keypoints=anchors)
    assert result.focal_scales.keys() == scales.keys() and np.allclose(list(result.focal_scales.values()), 1 / 1.05, atol=0.01)
    target = write_outputs(tmp_path / "out", reference, wrong, result)
    recorded = {photo["name"]: photo["focal_scale"] for photo in json.loads((target / "transform.json").read_text())["photos"]}
    assert recorded == pytest.approx(result.focal_scales)
    aligned = pycolmap.Reconstruction(str(target / "aligned"))
    for image in aligned.images.values():
        source = next(photo for photo in wrong.photos if photo.name == image.name)
        assert aligned.cameras[image.camera_id].mean_focal_length() == pytest.approx(source.camera.mean_focal_length() * result.focal_scales[image.name])
    assert register(reference, wrong, ground_truth, settings.changed(camera_fit={"focal": False}), keypoints=anchors).focal_scales == {}
    # a refused fit is verdict evidence: the meta-image's own cameras disagree with the anchors
    doubted = register(reference, with_wrong_focal_lengths(meta, 1.5), ground_truth, settings, keypoints=anchors)
    assert doubted.focal_scales == {} and doubted.verdict.evidence.camera_fit_refused.startswith("a focal length")
    assert doubted.verdict.label != "registered"
    # `failed` lists only why it failed (too few photos agree); an uncertain one names the refusal
    assert doubted.verdict.label == "failed" or any(reason.startswith("the camera fit was refused") for reason in doubted.verdict.reasons)


def test_distortion_refinement_recovers_a_wrong_sfm_radial_coefficient(reference, meta, ground_truth, tmp_path):
    """Keypoints seen through the true cameras, a meta-image whose SfM put k1 0.1 too high on its SIMPLE_RADIAL cameras:
    the joint fit of `refine_distortion` compares those keypoints in the distorted photo and moves every k1 most of the
    way back, under 0.095 from the truth and 0.07 on average (48-px photos: 0.1 of k1 moves a corner by about a pixel,
    and the keypoints weigh as 0.5 px of noise against the SfM's own uncertainty), and the Sim(3) no further from the truth; a
    registration with it (dataparser frame, where the same fit stops sooner on these tiny photos) moves every k1 closer
    to the truth and records it per photo (transform.json) and in the aligned model's cameras."""
    from sg_nerfstudio.geometry.meta_image import radial_k1_index
    from sg_nerfstudio.registration.anchored_start.anchors import Anchoring
    from sg_nerfstudio.registration.outputs import write_outputs

    truth_k1 = {int(p.camera.camera_id): float(p.camera.params[radial_k1_index(p.camera)]) for p in meta.photos if radial_k1_index(p.camera) is not None}
    assert len(truth_k1) == len(meta.photos)  # the tiny meta-image's cameras are all SIMPLE_RADIAL
    wrong = meta.with_radial_distortion({camera_id: k1 + 0.1 for camera_id, k1 in truth_k1.items()})
    anchors = projected_keypoints(reference, meta, ground_truth, 60, 0.0, seed=3)
    anchoring = Anchoring(wrong, anchors, Sim3.identity(), 1.0)
    prealigned = anchoring.prealign(ground_truth, wrong.look_at_under(ground_truth), grid_size=32, steps=1000)
    fit = fit_cameras(anchoring, prealigned, wrong.look_at_under(prealigned), grid_size=32, iterations=1000, focal=False,
                                pose_prior_scale=None, distortion=True)
    assert sorted(fit.radial_k1) == sorted(truth_k1)
    errors = [abs(fit.radial_k1[c] - truth_k1[c]) for c in truth_k1]
    # measured: 0.004-0.063, mean 0.036 (earlier CI machine); up to 0.087 on an AMD EPYC (another draw of the tiny reference)
    assert max(errors) < 0.095 and np.mean(errors) < 0.07, (errors, fit.radial_k1, truth_k1)
    before, after = (pose_errors(meta.poses, transform, ground_truth) for transform in (prealigned, fit.transform))
    assert after.rotation_deg <= before.rotation_deg + 1e-3 and after.translation <= before.translation + 1e-4

    settings = FAST.changed(optimiser={"steps": 3}, objective={"kind": "teacher-on-render"}, anchors={"weight": 1.0, "prealign_steps": 1000, "main_steps": 2}, camera_fit={"distortion": True})
    result = register(reference, wrong, ground_truth, settings, keypoints=anchors)
    assert sorted(result.radial_k1) == sorted(truth_k1), result.radial_k1
    assert all(abs(result.radial_k1[c] - truth_k1[c]) < 0.095 for c in truth_k1), (result.radial_k1, truth_k1)  # closer than 0.1 (0.087 on an AMD EPYC)
    target = write_outputs(tmp_path / "out", reference, wrong, result)
    recorded = {photo["name"]: photo["radial_k1"] for photo in json.loads((target / "transform.json").read_text())["photos"]}
    assert recorded == {p.name: result.radial_k1.get(int(p.camera.camera_id)) for p in wrong.photos}
    aligned = pycolmap.Reconstruction(str(target / "aligned"))
    for camera_id, k1 in result.radial_k1.items():
        assert aligned.cameras[camera_id].params[radial_k1_index(aligned.cameras[camera_id])] == pytest.approx(k1)
    assert register(reference, wrong, ground_truth, settings.changed(camera_fit={"distortion": False}), keypoints=anchors).radial_k1 == {}


def with_one_photo_turned(meta, degrees: float):
    """The meta-image as if its SfM had turned its first photo by `degrees` about that camera's centre (an internal
    error no Sim(3) can undo); its other photos and the points unchanged."""
    from scipy.spatial.transform import Rotation

    photo = meta.photos[0]
    turn = Rotation.from_rotvec(np.radians(degrees) * np.array([0.0, 1.0, 0.0])).as_matrix()
    rotation = photo.cam_from_world[:, :3] @ turn
    pose = np.concatenate([rotation, (-rotation @ photo.centre)[:, None]], axis=1)
    return meta.with_poses({photo.name: pose})


def test_pose_refinement_takes_one_wrongly_turned_photo_out_of_the_sim3(reference, meta, ground_truth, tmp_path):
    """Keypoints seen through the true cameras, a meta-image whose SfM turned one photo by 1°. Its ground truth by the
    benchmarks' rule (`align_cameras` of its cameras onto the true ones) spreads that over the group; the rigid keypoint
    fit lets the turned photo pull the whole group instead. `refine_photo_poses`, with a prior ten times the SfM's own
    uncertainty (about 0.15° on these 52-px photos: the test turned the photo further than its SfM allows), puts every
    camera within a tenth of a degree of the truth and the Sim(3) nearer the ground truth; a registration with it
    records each photo's correction in transform.json."""
    from sg_nerfstudio.geometry.alignment import align_cameras, camera_residuals
    from sg_nerfstudio.registration.anchored_start.anchors import Anchoring
    from sg_nerfstudio.registration.outputs import write_outputs

    anchors = projected_keypoints(reference, meta, ground_truth, 60, 0.1, seed=4)
    wrong = with_one_photo_turned(meta, 1.0)
    truth = ground_truth @ align_cameras(np.stack(wrong.poses), np.stack(meta.poses)).transform
    anchoring = Anchoring(wrong, anchors, Sim3.identity(), 1.0)  # in the world frame: no dataparser transform needed
    rigid = anchoring.prealign(ground_truth, wrong.look_at_under(ground_truth), grid_size=32, steps=1000)
    fit = fit_cameras(anchoring, rigid, wrong.look_at_under(rigid), grid_size=32, iterations=1000, focal=False, pose_prior_scale=10.0)
    assert sorted(fit.poses) == sorted(photo.name for photo in meta.photos) and fit.focal_scales == {}
    moved = wrong.with_poses(fit.poses)
    shift = align_cameras(np.stack(wrong.poses), np.stack(moved.poses)).transform
    true_cameras = np.stack([ground_truth.move_camera(pose) for pose in meta.poses])  # reference world
    rigid_off, _ = camera_residuals(rigid, np.stack(wrong.poses), true_cameras)
    moved_off, _ = camera_residuals(fit.transform, np.stack(moved.poses), true_cameras)
    assert rigid_off[0] > 0.5 and moved_off.max() < 0.1
    before = pose_errors(wrong.poses, rigid, truth).rotation_deg
    after = pose_errors(wrong.poses, fit.transform @ shift, truth).rotation_deg
    assert after < before / 2

    settings = FAST.changed(optimiser={"steps": 3}, objective={"kind": "teacher-on-render"}, anchors={"weight": 1.0, "prealign_steps": 1000, "main_steps": 2, "main_lr": 1e-5}, camera_fit={"photo_poses": True, "pose_prior_scale": 10.0})  # two dense steps too small to move the result
    result = register(reference, wrong, ground_truth, settings, keypoints=anchors)
    corrections = result.pose_corrections
    assert sorted(corrections) == sorted(fit.poses) and corrections[meta.photos[0].name]["rotation_deg"] > 0.5
    assert pose_errors(wrong.poses, result.transform, truth).rotation_deg < before
    target = write_outputs(tmp_path / "out", reference, wrong, result)
    recorded = {photo["name"]: photo["pose_correction"] for photo in json.loads((target / "transform.json").read_text())["photos"]}
    assert recorded == corrections
    assert register(reference, wrong, ground_truth, settings.changed(camera_fit={"photo_poses": False}), keypoints=anchors).pose_corrections == {}


def test_levenberg_marquardt_reaches_the_robust_minimum_that_lbfgs_approaches():
    """The camera fit's solver on a 2-D similarity fit with a fifth of the correspondences wrong (Cauchy kernel, the
    keypoint term's form) and one quadratic prior: it stops converged within 30 iterations where a Newton step has less
    than 1e-8 left to go, at the same point from starts 1e-9 apart, lower than the truth (the outliers move the optimum a little)
    and than 200 L-BFGS iterations reach."""
    from sg_nerfstudio.registration.anchored_start.least_squares import RobustResiduals, levenberg_marquardt

    rng = np.random.default_rng(0)
    points = torch.from_numpy(rng.uniform(-1, 1, (200, 2)))
    angle, shift, log_scale = 0.3, torch.tensor([0.2, -0.1], dtype=torch.float64), 0.1
    rotation = torch.tensor([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]], dtype=torch.float64)
    observed = np.exp(log_scale) * points @ rotation.T + shift + torch.from_numpy(rng.normal(0, 0.002, (200, 2)))
    wrong = torch.from_numpy(rng.random(200) < 0.2)
    observed[wrong] = torch.from_numpy(rng.uniform(-2, 2, (int(wrong.sum()), 2)))

    def residuals(x):
        c, s = torch.cos(x[0]), torch.sin(x[0])
        turn = torch.stack([torch.stack([c, -s]), torch.stack([s, c])])
        moved = torch.exp(x[3]) * points @ turn.T + x[1:3]
        return RobustResiduals((moved - observed) / 0.01, torch.full((200,), 0.005, dtype=torch.float64), (x[3:] / 0.5))

    def cost(x):
        return residuals(x).cost()

    solution = levenberg_marquardt(residuals, torch.zeros(4, dtype=torch.float64), 100)
    again = levenberg_marquardt(residuals, torch.full((4,), 1e-9, dtype=torch.float64), 100)
    assert solution.converged and solution.iterations <= 30, solution
    gradient = torch.func.grad(cost)(solution.x)
    newton_step = torch.linalg.solve(torch.func.hessian(cost)(solution.x), -gradient)  # what is left to go
    assert float(newton_step.abs().max()) < 1e-8, newton_step
    assert torch.allclose(solution.x, again.x, atol=1e-9, rtol=0)
    assert abs(float(solution.x[0]) - angle) < 0.01 and torch.allclose(solution.x[1:3], shift, atol=0.01)
    truth = torch.tensor([angle, *shift.tolist(), log_scale], dtype=torch.float64)
    lbfgs_x = torch.zeros(4, dtype=torch.float64, requires_grad=True)
    lbfgs = torch.optim.LBFGS([lbfgs_x], max_iter=200, line_search_fn="strong_wolfe", tolerance_grad=1e-14, tolerance_change=1e-16)

    def closure():
        lbfgs.zero_grad()
        value = cost(lbfgs_x)
        value.backward()
        return value

    lbfgs.step(closure)
    assert float(cost(solution.x)) < float(cost(truth)) and float(cost(solution.x)) <= float(cost(lbfgs_x.detach())) + 1e-12



def at_resolution(meta, anchors, factor: int):
    """The meta-image and its keypoint anchors as if every photo were `factor` times larger: cameras rescaled (focal
    lengths and principal points), every observation of the SfM model and every keypoint scaled by `factor`."""
    from sg_nerfstudio.initialisers.estimate import PhotoKeypoints

    reconstruction = pycolmap.Reconstruction(meta.reconstruction)
    for camera in reconstruction.cameras.values():
        camera.rescale(camera.width * factor, camera.height * factor)
    for image in reconstruction.images.values():
        for point in image.points2D:
            point.xy = point.xy * factor
    photos = [replace(photo, camera=copy.deepcopy(reconstruction.cameras[photo.camera.camera_id])) for photo in meta.photos]
    scaled = [PhotoKeypoints(k.name, np.asarray(k.points2D) * factor, k.points3D) for k in anchors]
    return replace(meta, photos=photos, reconstruction=reconstruction), scaled


def test_the_camera_fit_does_not_depend_on_the_photos_resolution(reference, meta, ground_truth):
    """The camera fit weighs keypoints in teacher cells (a fraction of the photo) and holds focal lengths, k1 and poses by
    the SfM's own uncertainty at the keypoints' noise (`camera_fit.intrinsics_priors`, `rotation_priors`). The SfM's
    covariance assumes 1 px of noise, so at twice the resolution it is twice as sure of everything; the keypoints' noise
    in pixels doubles with it, and the fit of a meta-image with wrong focal lengths and k1 ends at the same Sim(3), focal
    scales, k1 and poses whether its photos and keypoints are 48 or 96 px (2e-9 apart; with the focal and k1 priors held
    at 1 px, as before 57db2fd, the focal scales were 0.0014 and k1 0.014 apart)."""
    from sg_nerfstudio.geometry.meta_image import radial_k1_index
    from sg_nerfstudio.registration.anchored_start.anchors import Anchoring

    anchors = projected_keypoints(reference, meta, ground_truth, 60, 0.05, seed=4)
    truth_k1 = {int(p.camera.camera_id): float(p.camera.params[radial_k1_index(p.camera)]) for p in meta.photos}
    wrong = with_wrong_focal_lengths(meta, 1.05).with_radial_distortion({c: k1 + 0.05 for c, k1 in truth_k1.items()})
    fits = []
    for factor in (1, 2):
        scaled, keypoints = at_resolution(wrong, anchors, factor)
        anchoring = Anchoring(scaled, keypoints, Sim3.identity(), 1.0)
        prealigned = anchoring.prealign(ground_truth, scaled.look_at_under(ground_truth), grid_size=32, steps=1000)
        fits.append(fit_cameras(anchoring, prealigned, scaled.look_at_under(prealigned), 32, 100, focal=True, pose_prior_scale=1.0, distortion=True))
    small, large = fits
    assert small.focal_scales and small.radial_k1 and small.poses, "the fit was dropped"
    assert max(abs(small.focal_scales[n] - 1.0) for n in small.focal_scales) > 0.01  # it did move them
    assert all(abs(small.focal_scales[n] - large.focal_scales[n]) < 1e-6 for n in small.focal_scales), (small.focal_scales, large.focal_scales)
    assert all(abs(small.radial_k1[c] - large.radial_k1[c]) < 1e-6 for c in small.radial_k1), (small.radial_k1, large.radial_k1)
    assert np.allclose(small.transform.matrix, large.transform.matrix, atol=1e-6, rtol=0)
    assert all(np.allclose(small.poses[n], large.poses[n], atol=1e-6, rtol=0) for n in small.poses)

def test_a_focal_change_widens_the_centre_shift_a_photo_may_take():
    """A photo whose SfM focal length was some percent wrong stood as many percent too near or far from a facade: the
    plausibility limit lets the camera fit move it by its depth times the focal change on top of MAX_POSE_CHANGE_DEG;
    the same shift without a focal change, or a turn beyond the limit, is refused."""
    from sg_nerfstudio.registration.anchored_start.camera_fit import MAX_POSE_CHANGE_DEG, implausibility
    from sg_nerfstudio.registration.anchored_start.anchors import FreeCameras

    depth, sigma = 10.0, np.radians(0.5)
    pose_sigma = torch.tensor([[sigma] * 3 + [depth * sigma] * 3], dtype=torch.float64)
    shift = depth * 0.06  # 6% of the depth: beyond 2° (3.5%), within 2° plus a 6% focal change
    corrections = torch.tensor([[0.0, 0.0, 0.0, 0.0, 0.0, shift]], dtype=torch.float64)
    camera_of = torch.tensor([0])

    def cameras(focal_scale, corrections):
        return FreeCameras(torch.tensor([np.log(focal_scale)], dtype=torch.float64), torch.tensor([0.05], dtype=torch.float64), corrections, pose_sigma)

    assert implausibility(cameras(0.94, corrections), camera_of) == ""
    assert implausibility(cameras(1.0, corrections), camera_of).startswith("a photo moved beyond its depth times 2°")
    assert implausibility(FreeCameras(pose_corrections=corrections, pose_sigma=pose_sigma), camera_of)
    turned = corrections.clone()
    turned[0, 1] = np.radians(MAX_POSE_CHANGE_DEG) * 1.1
    assert implausibility(cameras(0.94, turned), camera_of) == "a photo turned 2.2° (beyond 2°)"


def test_camera_fit_ends_where_the_priors_last_digits_do_not_matter(reference, meta, ground_truth):
    """The joint fit of the Sim(3), focal lengths and poses converges within 20 iterations: priors 1e-9 apart (pycolmap's
    covariance differs in its last digits from call to call) give the same transform and cameras to 1e-7, and a Newton
    step from the result has less than 1e-6 left to go (the L-BFGS it replaced: 3.2 after 20 iterations; unconverged
    after 1000 on a real 3-photo meta-image, whose fit then moved by 0.2% of a focal length and across the
    plausibility limit from run to run)."""
    from sg_nerfstudio.registration.anchored_start.anchors import Anchoring

    from sg_nerfstudio.registration.anchored_start.camera_fit import fit_jointly, freedom, intrinsics_priors, rotation_priors
    from sg_nerfstudio.registration.anchored_start.anchors import FIT_KERNEL_FRACTION, FreeCameras

    anchors = projected_keypoints(reference, meta, ground_truth, 60, 0.1, seed=7)
    wrong = with_one_photo_turned(meta, 1.0)
    anchoring = Anchoring(wrong, anchors, Sim3.identity(), 1.0)
    rigid = anchoring.prealign(ground_truth, wrong.look_at_under(ground_truth), grid_size=32, steps=300)
    fits = [fit_cameras(anchoring, rigid, wrong.look_at_under(rigid), 32, 20, focal=True, pose_prior_scale=scale) for scale in (10.0, 10.0 * (1 + 1e-9))]
    assert fits[0].poses and fits[0].focal_scales, "the fit was dropped"

    # stationary: a Newton step on every fitted parameter has less than 1e-6 left to go
    term = anchoring.term(32, 1.0, FIT_KERNEL_FRACTION * 32)
    focal_priors = intrinsics_priors(anchoring, FIT_KERNEL_FRACTION)[0]
    focal, pose_sigma = freedom(focal_priors, term.camera_ids), term.pose_sigma(rotation_priors(anchoring, 10.0), focal_priors)
    centre = torch.from_numpy(wrong.look_at_under(rigid))
    fitted, free = fit_jointly(term, rigid, centre.numpy(), 20, focal, pose_sigma)
    start = torch.cat([torch.zeros(7, dtype=torch.float64), free.log_focal, (free.pose_corrections / pose_sigma).reshape(-1)])

    def cost(x):
        return term(Sim3.update(x[:7], centre) @ fitted.to_torch(), FreeCameras(x[7:7 + len(focal[0])], focal[0], x[7 + len(focal[0]):].reshape(-1, 6) * pose_sigma, pose_sigma))

    newton_step = torch.linalg.solve(torch.func.hessian(cost)(start), -torch.func.grad(cost)(start))
    assert float(newton_step.abs().max()) < 1e-6, newton_step  # 3e-10 or 1.04e-7 from run to run (LM's last step)
    assert np.allclose(fits[0].transform.matrix, fits[1].transform.matrix, atol=1e-7, rtol=0)
    assert all(abs(fits[0].focal_scales[name] - fits[1].focal_scales[name]) < 1e-7 for name in fits[0].focal_scales)
    assert all(np.allclose(fits[0].poses[name], fits[1].poses[name], atol=1e-7, rtol=0) for name in fits[0].poses)


def test_the_camera_adjustment_moves_every_photo_with_its_own_tracks(reference, meta, ground_truth):
    """`camera_fit: adjustment` (registration/anchored_adjustment.py): a meta-image whose SfM put every focal length 5%
    long and turned one photo by 1°, with anchors for every photo but the turned one. The bundle adjustment of its own
    (exact) tracks with the anchors brings every focal scale within 0.1% of 1/1.05 and every camera within 0.01° of the
    truth, the turned photo's too: its own tracks carry it, where the prior fit cannot move a photo without anchors. A
    focal length 50% long is beyond MAX_FOCAL_CHANGE (the start is kept); one photo's anchors, which leave the scale free,
    and a camera model with more distortion terms than k1 are left to the prior fit. A registration with it records a
    correction for every photo."""
    from sg_nerfstudio.geometry.alignment import camera_residuals
    from sg_nerfstudio.registration.anchored_start.bundle_adjustment import adjustable
    from sg_nerfstudio.registration.anchored_start.anchors import Anchoring

    turned = meta.photos[0].name
    anchors = [k for k in projected_keypoints(reference, meta, ground_truth, 60, 0.1, seed=4) if k.name != turned]
    wrong = with_wrong_focal_lengths(with_one_photo_turned(meta, 1.0), 1.05)
    anchoring = Anchoring(wrong, anchors, Sim3.identity(), 1.0)  # in the world frame: no dataparser transform needed
    rigid = anchoring.prealign(ground_truth, wrong.look_at_under(ground_truth), grid_size=32, steps=1000)
    fit = fit_cameras(anchoring, rigid, wrong.look_at_under(rigid), 32, 100, focal=True, pose_prior_scale=1.0, distortion=True, adjustment=True)
    assert sorted(fit.poses) == sorted(fit.focal_scales) == sorted(photo.name for photo in meta.photos)
    assert np.allclose(list(fit.focal_scales.values()), 1 / 1.05, atol=0.001), fit.focal_scales
    true_cameras = np.stack([ground_truth.move_camera(pose) for pose in meta.poses])  # reference world
    moved_off, _ = camera_residuals(fit.transform, np.stack(wrong.with_poses(fit.poses).poses), true_cameras)
    rigid_off, _ = camera_residuals(rigid, np.stack(wrong.poses), true_cameras)
    assert rigid_off[0] > 0.5 and moved_off.max() < 0.01, (rigid_off, moved_off)
    priors = fit_cameras(anchoring, rigid, wrong.look_at_under(rigid), 32, 100, focal=True, pose_prior_scale=1.0, distortion=True)
    assert turned not in priors.poses

    one_photo = Anchoring(wrong, anchors[:1], Sim3.identity(), 1.0)  # its anchors leave the scale free: the prior fit
    assert not one_photo.fix_scale(rigid, 32)
    assert sorted(fit_cameras(one_photo, rigid, wrong.look_at_under(rigid), 32, 100, focal=True, pose_prior_scale=1.0, adjustment=True).poses) == [anchors[0].name]
    far_off = Anchoring(with_wrong_focal_lengths(meta, 1.5), anchors, Sim3.identity(), 1.0)
    kept = adjusted_cameras(far_off, rigid, focal=True, distortion=False)
    assert kept.transform is rigid and kept.poses == {} and kept.focal_scales == {}
    radial = pycolmap.Reconstruction(meta.reconstruction)
    camera = next(iter(radial.cameras.values()))
    radial.cameras[camera.camera_id] = pycolmap.Camera(model="RADIAL", width=camera.width, height=camera.height, params=[*camera.params, 0.0], camera_id=camera.camera_id)
    assert adjustable(meta) and not adjustable(replace(meta, reconstruction=radial))
    rig = pycolmap.Reconstruction(meta.reconstruction)  # two photos' cameras in one rig: the prior fit
    first, second = sorted(rig.cameras)[:2]
    next(r for r in rig.rigs.values() if r.ref_sensor_id.id == first).add_sensor(pycolmap.sensor_t(pycolmap.SensorType.CAMERA, second), pycolmap.Rigid3d())
    assert not adjustable(replace(meta, reconstruction=rig))

    settings = FAST.changed(optimiser={"steps": 3}, objective={"kind": "teacher-on-render"}, anchors={"weight": 1.0, "prealign_steps": 1000, "main_steps": 2, "main_lr": 1e-5}, camera_fit={"focal": True, "photo_poses": True, "solver": "adjustment"})
    result = register(reference, wrong, ground_truth, settings, keypoints=anchors)
    assert sorted(result.pose_corrections) == sorted(photo.name for photo in meta.photos)
    assert result.pose_corrections[turned]["rotation_deg"] > 0.5


def test_stages_after_the_pose_fit_keep_its_optimum(reference, meta, ground_truth):
    """After the camera fit moved the photos under the narrow kernel (FIT_KERNEL_FRACTION), the stages weigh the keypoints
    with that kernel too: minimised over the Sim(3) alone from where the fit left it, their term stays there, where the
    wider KERNEL_CELLS lets a sixth of the keypoints that sit a pixel off (what RANSAC lets through) pull it away (on a real
    3-photo meta-image, Sceaux 100_7101-100_7104, that moved the result from 0.10° to 0.28° from the truth)."""
    from sg_nerfstudio.registration.anchored_start.anchors import Anchoring, minimise_keypoint_term

    anchors = projected_keypoints(reference, meta, ground_truth, 60, 0.0, seed=5)
    rng = np.random.default_rng(6)
    for photo_anchors in anchors:  # near misses: one pixel off in a common direction per photo
        off = rng.random(len(photo_anchors.points2D)) < 1 / 6
        photo_anchors.points2D[off] += rng.normal(size=2) / np.sqrt(2)
    wrong = with_one_photo_turned(meta, 1.0)
    anchoring = Anchoring(wrong, anchors, Sim3.identity(), 1.0)
    rigid = anchoring.prealign(ground_truth, wrong.look_at_under(ground_truth), grid_size=32, steps=1000)
    fit = fit_cameras(anchoring, rigid, wrong.look_at_under(rigid), grid_size=32, iterations=1000, focal=False, pose_prior_scale=10.0)
    moved = wrong.with_poses(fit.poses)
    drift = {}
    for narrow in (True, False):
        term = anchoring.for_meta(moved, narrow=narrow).term(32, 1.0)
        stayed = minimise_keypoint_term(term, fit.transform, moved.look_at_under(fit.transform), 1000)
        drift[narrow] = pose_errors(moved.poses, stayed, fit.transform).rotation_deg
    assert drift[True] < 0.001 and drift[False] > 0.005, drift  # measured: 1e-6° and 0.04° (earlier CI machine), 1e-6° and 0.011° (AMD EPYC)


def test_sfm_uncertainty_follows_how_well_the_sfm_determined_it(meta):
    """pycolmap's bundle-adjustment covariance of the meta-image's model: a finite relative focal sigma and k1 sigma for
    every camera and a finite relative-rotation sigma (degrees) for every photo, all larger once most of the model's
    points are gone, and the model itself untouched."""
    from sg_nerfstudio.geometry.meta_image import intrinsics_uncertainty, relative_focal_uncertainty, relative_rotation_uncertainty

    before = {camera_id: np.array(camera.params) for camera_id, camera in meta.reconstruction.cameras.items()}
    poses = {image.name: image.cam_from_world().matrix() for image in meta.reconstruction.images.values()}
    focal, rotation = relative_focal_uncertainty(meta.reconstruction), relative_rotation_uncertainty(meta.reconstruction)
    assert sorted(focal) == sorted(meta.reconstruction.cameras) and all(0 < sigma < 1 for sigma in focal.values())
    assert sorted(rotation) == sorted(photo.name for photo in meta.photos) and all(0 < sigma < 5 for sigma in rotation.values())
    assert all(np.array_equal(camera.params, before[camera_id]) for camera_id, camera in meta.reconstruction.cameras.items())
    assert all(np.array_equal(image.cam_from_world().matrix(), poses[image.name]) for image in meta.reconstruction.images.values())
    sparse = pycolmap.Reconstruction(meta.reconstruction)
    for point_id in sorted(sparse.point3D_ids())[::4] + sorted(sparse.point3D_ids())[1::4] + sorted(sparse.point3D_ids())[2::4]:
        sparse.delete_point3D(point_id)
    fewer_focal, fewer_rotation = relative_focal_uncertainty(sparse), relative_rotation_uncertainty(sparse)
    assert all(fewer_focal[camera_id] > focal[camera_id] for camera_id in focal)
    assert all(fewer_rotation[name] > rotation[name] for name in rotation)
    k1, fewer_k1 = intrinsics_uncertainty(meta.reconstruction)[1], intrinsics_uncertainty(sparse)[1]
    assert sorted(k1) == sorted(meta.reconstruction.cameras) and all(0 < sigma < 1 for sigma in k1.values())  # all SIMPLE_RADIAL
    assert all(fewer_k1[camera_id] > k1[camera_id] for camera_id in k1)


def test_refine_stage_continues_from_the_main_result_with_its_own_teacher(reference, meta, ground_truth):
    """`refine_steps` with a `refine_teacher`: after the main stage (its history unchanged) a stage with that teacher
    runs from the main stage's result and lowers the refine teacher's objective there; the step count includes it;
    `refine_anchored: false` leaves it out where keypoint anchors held the pose; with another main objective the refine
    stage still describes renders with its teacher."""
    base = FAST.changed(optimiser={"steps": 30, "lr": 0.01, "lr_final": 0.0005}, objective={"kind": "teacher-on-render"})
    settings = base.changed(last_stage={"steps": 15, "teacher": "dense-sift", "lr": 0.003})
    start = perturbed_start(meta, ground_truth, 1, 3.0, 0.05, 0.05)
    main_only = register(reference, meta, start, base)
    refined = register(reference, meta, start, settings)
    assert refined.steps == optimize.total_steps(settings) == 45
    stage_names = [row["stage"] for row in refined.history]
    assert stage_names == ["main"] * (30 * len(meta.photos)) + ["refine-dense-sift"] * (15 * len(meta.photos))
    assert [row["loss"] for row in refined.history[: 30 * len(meta.photos)]] == [row["loss"] for row in main_only.history]

    sift = refine_settings(settings)
    objective = build_objective(reference, sift)
    judge = PhotoLosses(reference, prepare_photos(reference, meta, sift, objective), objective, sift, refined.near_plane)
    rule = TrimmingRule.of(settings)
    at = lambda world: rule.trimmed_mean(stages.objective_at(judge, reference.world_to_dataparser @ world))
    assert at(refined.transform) < at(main_only.transform)

    anchors = projected_keypoints(reference, meta, ground_truth, 40, 0.0, seed=2)
    anchored = settings.changed(optimiser={"update_centre": "look-at"}, anchors={"weight": 1.0}, last_stage={"with_anchors": False})
    assert optimize.total_steps(anchored, anchored=True) == 30 and optimize.total_steps(anchored) == 45
    assert {row["stage"] for row in register(reference, meta, start, anchored, keypoints=anchors).history} == {"main"}
    for objective in ("features", "photometric"):  # the refine teacher describes renders, whatever the main objective
        own = refine_settings(settings.changed(objective={"kind": objective, "teacher_input_size": 64}))
        assert (own.objective.kind, own.objective.render_teacher, own.objective.teacher_input_size) == ("teacher-on-render", "dense-sift", None)


def test_a_reference_trained_with_relative_paths_loads_from_any_directory(trained, tiny_scene, tmp_path, monkeypatch):
    """nerfstudio stores `--data` and `--output-dir` as given; a run trained in W with relative ones names its dataset
    relative to W. Read from elsewhere, the dataset is found through the run directory's own relative location."""
    from sg_nerfstudio.initialisers.pipeline import reference_source_from_config
    from sg_nerfstudio.splat.trained import load_pipeline, open_trained_run

    _, _, config = trained
    workdir, elsewhere = tmp_path / "work", tmp_path / "elsewhere"
    shutil.copytree(tiny_scene / "reference", workdir / "scenes" / "tiny")
    elsewhere.mkdir()
    moved = copy.deepcopy(config)
    moved.output_dir = Path("outputs")
    moved.pipeline.datamanager.data = Path("scenes/tiny")
    moved.pipeline.datamanager.teacher = replace(moved.pipeline.datamanager.teacher, cache_dir=Path("cache"))
    (workdir / "cache").mkdir()
    monkeypatch.chdir(workdir)
    moved.save_config()  # as ns-train in workdir: outputs/<experiment>/<method>/<timestamp>/config.yml
    run_dir = workdir / moved.get_base_dir()
    shutil.copytree(config.get_base_dir() / "nerfstudio_models", run_dir / "nerfstudio_models")
    shutil.copy(config.get_base_dir() / "dataparser_transforms.json", run_dir)
    monkeypatch.chdir(elsewhere)
    run = open_trained_run(run_dir / "config.yml")
    assert Path(run.config.pipeline.datamanager.data) == workdir / "scenes" / "tiny"
    assert Path(run.config.pipeline.datamanager.teacher.cache_dir) == workdir / "cache"
    _, checkpoint, _ = load_pipeline(run, "cpu", "inference")  # nerfstudio's eval_setup would look under the current directory
    assert checkpoint.parent == run_dir / "nerfstudio_models" and not list(elsewhere.iterdir())
    assert reference_source_from_config(run_dir / "config.yml").colmap_path == workdir / "scenes" / "tiny" / "colmap" / "sparse" / "0"
    shutil.rmtree(workdir / "scenes")  # a dataset found nowhere is still one sentence naming it
    with pytest.raises(Exception, match=r"The reference dataset scenes/tiny named in .* was not found"):
        open_trained_run(run_dir / "config.yml")


def test_a_checkpoint_with_gaussians_that_are_not_finite_is_one_sentence(trained, tmp_path):
    """A diverged training: the CPU rasterizer would silently drop such Gaussians."""
    from sg_nerfstudio.splat.trained import ReferenceModelError, load_pipeline, open_trained_run

    _, _, config = trained
    run_dir = tmp_path / "run"
    shutil.copytree(config.get_base_dir(), run_dir)
    (checkpoint,) = (run_dir / "nerfstudio_models").glob("*.ckpt")
    state = torch.load(checkpoint, weights_only=False)
    scales = next(key for key in state["pipeline"] if key.endswith("gauss_params.scales"))
    state["pipeline"][scales][:3] = float("inf")
    torch.save(state, checkpoint)
    with pytest.raises(ReferenceModelError, match=r"holds 3 of \d+ Gaussians whose scales are not finite"):
        load_pipeline(open_trained_run(run_dir / "config.yml"), "cpu", "inference")


class _CentreLosses:
    """Stands in for PhotoLosses: each photo's loss is the squared distance of its moved camera centre from where
    `truth` puts it (what a dense objective that sees the scale would prefer)."""

    def __init__(self, meta, truth: Sim3):
        from types import SimpleNamespace

        from sg_nerfstudio.geometry.alignment import camera_centres

        self.photos, self.centres = meta.photos, camera_centres(np.stack(meta.poses))
        self.target = truth.apply(self.centres)
        self.objective = SimpleNamespace(teacher=SimpleNamespace(grid_size=32))

    def __call__(self, transform, indices):
        moved = transform.numpy().apply(self.centres)
        return [torch.tensor(float(np.sum((moved[i] - self.target[i]) ** 2))) for i in indices], torch.ones(len(indices))


def test_the_scale_one_anchored_photo_leaves_free_is_found_about_its_camera(reference, meta, ground_truth):
    """One photo's anchors fix its camera but not the Sim(3)'s scale about it: a 2% scale change moves its keypoints
    by nothing, the search scales about that camera (which stays where it was) to the factor the other photos prefer;
    the anchors of two photos apart move by pixels, fix the scale, and nothing changes."""
    from sg_nerfstudio.geometry.alignment import camera_centres
    from sg_nerfstudio.registration.anchored_start.anchors import Anchoring, KeypointTerm, anchors_fix_scale

    first = meta.photos[0]
    centre = ground_truth.apply(camera_centres(first.cam_from_world[None])[0])
    start = Sim3.from_parts(1.35, np.eye(3), np.zeros(3)).about(centre) @ ground_truth
    exact = projected_keypoints(reference, meta, ground_truth, 40, 0.0, seed=1)
    world = reference.world_to_dataparser
    one, two = exact[:1], [k for k in exact if k.name in {first.name, meta.photos[-1].name}]
    motion, error = KeypointTerm(meta, one, world, 32, 1.0).scale_motion_px(world @ ground_truth)
    assert motion < 1e-6 and not anchors_fix_scale(motion, error)
    motion, error = KeypointTerm(meta, two, world, 32, 1.0).scale_motion_px(world @ ground_truth)
    assert motion > 0.1 and error < 1e-3 and anchors_fix_scale(motion, error)

    anchors = lambda keypoints: Anchoring(meta, keypoints, Sim3.identity(), 1.0)  # the stand-in objective works in the world frame
    settings = RegistrationSettings().changed(robust={"rule": "none"})
    found, record = scale_search.scale_the_anchors_leave_free(_CentreLosses(meta, ground_truth), anchors(one), meta, start, settings)
    assert record["photos"] == [first.name] and abs(record["factor"] - 1 / 1.35) < 0.02
    assert np.allclose(found.apply(camera_centres(first.cam_from_world[None])), centre[None], atol=1e-9)  # the anchored camera stays
    assert pose_errors(meta.poses, found, ground_truth).translation < 0.1 * pose_errors(meta.poses, start, ground_truth).translation
    unchanged, none = scale_search.scale_the_anchors_leave_free(_CentreLosses(meta, ground_truth), anchors(two), meta, ground_truth, settings)
    assert none is None and np.allclose(unchanged.matrix, ground_truth.matrix)


def test_a_registration_with_one_anchored_photo_searches_the_scale_it_leaves_free(reference, meta, ground_truth):
    """Anchors of one photo only, from a start 30% too large about that photo's camera: the keypoints alone cannot see
    the scale (the keypoint fit ends where it started in translation), the registration's scale search brings the
    other photos' cameras most of the way back, and records the search in the result."""
    from sg_nerfstudio.geometry.alignment import camera_centres

    anchors = projected_keypoints(reference, meta, ground_truth, 40, 0.0, seed=3)[:1]
    photo = next(p for p in meta.photos if p.name == anchors[0].name)
    centre = ground_truth.apply(camera_centres(photo.cam_from_world[None])[0])
    start = Sim3.from_parts(1.3, np.eye(3), np.zeros(3)).about(centre) @ ground_truth
    settings = FAST.changed(optimiser={"steps": 10}, objective={"kind": "teacher-on-render"}, anchors={"weight": 3.0, "prealign_steps": 200, "main_steps": 0})
    result = register(reference, meta, start, settings, keypoints=anchors)
    assert result.scale_search is not None and result.scale_search["photos"] == [photo.name]
    assert result.verdict.evidence.scale_rise is not None and result.verdict.evidence.scale_probe > 0
    before, after = (pose_errors(meta.poses, t, ground_truth).translation for t in (start, result.transform))
    assert after < 0.3 * before, (before, after, result.scale_search)


@pytest.mark.parametrize("teacher_input_size, held", [(256, True), (128, True), (64, False)])
def test_the_verdicts_probes_render_the_model_culled_at_the_result(teacher_input_size, held, reference, meta, ground_truth, monkeypatch):
    """The final losses and the 12 probes around the result all render the one model culled (and coarsened) at the
    result: no probe culls again (probes in opposite directions used to move the cull back and forth, seconds each
    on a reference of millions of Gaussians, and compared the result with models merged at other poses). Probes
    beyond the re-cull rotation (an 8-cell grid: about 7°) cull for their poses."""
    seen = {}
    original = optimize.gather_evidence

    def spying(losses, meta, final_ns, *args, **kwargs):
        seen["before"], seen["pose"] = losses.visible.culls, losses.visible.pose
        evidence = original(losses, meta, final_ns, *args, **kwargs)
        seen["after"], seen["final"] = losses.visible.culls, final_ns
        return evidence

    monkeypatch.setattr(optimize, "gather_evidence", spying)
    start = perturbed_start(meta, ground_truth, 7, 2.0, 0.02, 0.02)
    settings = FAST.changed(optimiser={"steps": 3}, objective={"kind": "teacher-on-render", "teacher_input_size": teacher_input_size})
    register(reference, meta, start, settings)
    if held:
        assert seen["after"] == seen["before"]
        np.testing.assert_array_equal(seen["pose"].matrix, seen["final"].matrix)
    else:
        assert seen["after"] > seen["before"]


def test_a_model_held_at_the_result_renders_every_probe_as_the_whole_model_does(reference, meta, ground_truth):
    """What `held_for_probes` relies on: the model culled at the result renders the verdict's 12 probes (here the tiny
    reference's 16-cell grid, probes of 3-4°, the largest the hold takes) as the whole model does (level of detail off:
    this checks the cull alone)."""
    settings = FAST.changed(objective={"kind": "teacher-on-render"}, level_of_detail={"voxel_pixels": 0.0})
    objective = build_objective(reference, settings)
    photos = prepare_photos(reference, meta, settings, objective)
    culled = PhotoLosses(reference, photos, objective, settings, 0.01)
    whole = PhotoLosses(reference, photos, objective, settings, 0.01, cull=False)
    result = (reference.world_to_dataparser @ perturbed_start(meta, ground_truth, 17, 1.0, 0.01, 0.01)).to_torch()
    rotation, translation = verdict.probe_sizes(meta, photos, objective.teacher.grid_size, result.numpy())
    assert 2.0 < np.degrees(rotation) <= optimize.MAX_ROTATION_DEG
    centre = torch.from_numpy(meta.centroid_under(result.numpy()))
    indices = list(range(len(photos)))
    with culled.visible.held_at(result), torch.no_grad():
        for delta in verdict.probes(rotation, translation):
            probe = Sim3.update(delta, centre) @ result
            ours, ours_coverage = culled(probe, indices)
            full, full_coverage = whole(probe, indices)
            torch.testing.assert_close(torch.stack(ours), torch.stack(full), rtol=1e-5, atol=1e-6)
            torch.testing.assert_close(ours_coverage, full_coverage, rtol=1e-5, atol=1e-6)
    assert culled.visible.culls == 1 and culled.visible.subset.count < reference.count
