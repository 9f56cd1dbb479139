"""sg-bench and sg-make-scene's benchmark suites: layout, runs, tables, resumption, bad layouts."""

from __future__ import annotations

import csv
import os
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from sg_nerfstudio.bench.layout import BenchmarkLayoutError, read_benchmark, read_benchmarks
from sg_nerfstudio.bench.photo_losses import occlusion_of, photo_ratios, separation
from sg_nerfstudio.bench.runs import trained_reference
from sg_nerfstudio.registration.settings import load_preset
from sg_nerfstudio.scripts.bench import main as bench_main
from sg_nerfstudio.scripts.make_scene import main as make_scene_main
from sg_nerfstudio.synthetic.generator import SUITES


@pytest.fixture(scope="module")
def suite(tmp_path_factory) -> Path:
    output = tmp_path_factory.mktemp("bench") / "suite"
    assert make_scene_main(["--preset", "tiny-benchmark", "--output", str(output)]) == 0
    return output


@pytest.fixture(scope="module")
def preset(tmp_path_factory) -> Path:
    values = {"base": "fast-cpu", "optimiser": {"steps": 4}}
    path = tmp_path_factory.mktemp("preset") / "short.yaml"
    path.write_text(yaml.safe_dump(values))
    return path


@pytest.fixture(scope="module")
def wide_preset(tmp_path_factory) -> Path:
    values = {"base": "wide-cpu", "optimiser": {"steps": 3}, "coarse_to_fine": {"factors": [2], "steps": 2}, "hypotheses": {"count": 2, "kept": 2},
              "last_stage": {"steps": 2}}
    path = tmp_path_factory.mktemp("preset") / "wide-short.yaml"
    path.write_text(yaml.safe_dump(values))
    return path


def test_benchmark_suite_definitions_follow_the_issue():
    """The default suite: at least 6 landmarks, 2-3 meta-images each, 8-60 photos (the issue's range), varied occluders and appearance."""
    scenes = SUITES["benchmark"]
    assert len(scenes) >= 6
    shapes = {(c.building.towers, c.building.roof, c.building.width, c.building.depth) for c in scenes.values()}
    assert len(shapes) == len(scenes)
    for config in scenes.values():
        counts = [int(entry.split(":")[1]) for entry in config.meta_images]
        assert 2 <= len(counts) <= 3 and all(8 <= n <= 60 for n in counts)
    assert len({c.occluder_rate for c in scenes.values()}) > 3 and len({c.appearance_strength for c in scenes.values()}) > 3


def test_another_draw_of_a_suite_moves_every_scene_s_seed_and_says_so(suite, tmp_path):
    """--draw N: each scene generated from its seed + N (other cameras, the same landmark shapes), recorded in
    benchmark.json; a negative draw is refused in one sentence with nothing written."""
    again = tmp_path / "draw-1"
    assert make_scene_main(["--preset", "tiny-benchmark", "--draw", "1", "--output", str(again)]) == 0
    assert json.loads((again / "benchmark.json").read_text())["draw"] == 1 and json.loads((suite / "benchmark.json").read_text())["draw"] == 0
    for name, config in SUITES["tiny-benchmark"].items():
        seeds = [json.loads((root / name / "scene.json").read_text())["config"]["seed"] for root in (suite, again)]
        assert seeds == [config.seed, config.seed + 1]
        assert (suite / name / "meta" / "front" / "sparse" / "0" / "images.bin").read_bytes() != (again / name / "meta" / "front" / "sparse" / "0" / "images.bin").read_bytes()
    assert make_scene_main(["--preset", "tiny-benchmark", "--draw", "-1", "--output", str(tmp_path / "bad")]) != 0
    assert not (tmp_path / "bad").exists()


def test_suite_layout_is_read_back(suite):
    scenes = read_benchmark(suite)
    assert [s.name for s in scenes] == list(SUITES["tiny-benchmark"])
    assert [[m.name for m in s.metas] for s in scenes] == [["front"], ["front", "rear"]]


def test_several_benchmarks_are_read_as_one_suite_and_a_shared_scene_name_is_refused(suite, tmp_path, capsys):
    other = tmp_path / "other"
    shutil.copytree(suite / "tiny-a", other / "tiny-c")
    assert [s.name for s in read_benchmarks([suite, other])] == [*SUITES["tiny-benchmark"], "tiny-c"]
    shutil.copytree(suite / "tiny-b", other / "tiny-b")
    with pytest.raises(BenchmarkLayoutError, match="share the name 'tiny-b'"):
        read_benchmarks([suite, other])
    capsys.readouterr()
    assert bench_main([str(suite), str(other), "--output", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err.strip()
    assert "share the name 'tiny-b'" in err and len(err.splitlines()) == 1 and not (tmp_path / "out").exists()
    assert bench_main([str(suite), str(other), "--output", str(tmp_path / "out"), "--twin-anchors", str(tmp_path / "twins")]) == 1
    assert "expected one" in capsys.readouterr().err and not (tmp_path / "out").exists() and not (tmp_path / "twins").exists()
    assert bench_main(["--output", str(tmp_path / "out")]) == 1
    assert "No benchmark directory was given" in capsys.readouterr().err and not (tmp_path / "out").exists()


def test_sg_bench_writes_tables_and_resumes(suite, preset, wide_preset, tmp_path, capsys, monkeypatch):
    output = tmp_path / "results"
    args = [str(suite), "--output", str(output), "--config", str(preset), "--train-steps", "20",
            "--initialisers", "colmap", "perturbed", "--ablations", "none", "--noise-levels", "2", "8", "--sizes", "3",
            "--compare-config", str(wide_preset)]
    assert bench_main(args) == 0, capsys.readouterr().err
    records = [json.loads(p.read_text()) for p in sorted((output / "runs").glob("*/*/*.json"))]
    # per meta-image: 2 starts and 2 noise levels (twice: both presets) + 1 ablation + 1 subset of 3 photos; three meta-images
    assert len(records) == 3 * 10
    for record in records:
        if record["after"] is not None:
            assert record["verdict"] in {"registered", "uncertain", "failed"} and record["verdict_reasons"]
        if record["run"].startswith("noise-"):  # rotation with translation and scale in proportion
            assert record["before"]["dR"] == pytest.approx(float(record["label"]), abs=1e-6) and record["before"]["dT"] > 0
    assert {r["preset"] for r in records} == {preset.stem, wide_preset.stem}
    by_name = {(r["scene"], r["meta"], r["run"]): r for r in records}
    for (scene, meta, run), record in by_name.items():
        if run.endswith("@wide-short"):  # the compared preset starts where the main one does
            assert record["mode"] == "wide-short" and record["before"] == by_name[(scene, meta, run.split("@")[0])]["before"]
    for record in records:
        if record["run"] == "perturbed":
            assert record["before"]["dR"] == pytest.approx(5.0, abs=1e-6) and record["after"] is not None
        if record["run"].startswith("size-3"):
            assert record["photos"] == 3
    by_run = {(r["scene"], r["meta"], r["run"]): r for r in records}
    for scene, meta, run in by_run:
        if run == "perturbed":  # ablation rows start where the perturbed row does
            assert by_run[(scene, meta, "ablation-none")]["before"] == by_run[(scene, meta, run)]["before"]
    rows = list(csv.DictReader((output / "results.csv").open()))
    assert len(rows) == len(records)
    results = (output / "results.md").read_text()
    for expected in ("| perturbed (start) | 5.00 |", "| ours (perturbed init) |", "| ours (perturbed init, wide-short) |", "| colmap (start) |",
                     "| ours (colmap init, wide-short) |", "| colmap | colmap@wide-short | perturbed | perturbed@wide-short |", "MTA(3,0.1)", "| none |", "| tiny-b | rear | 4 |",
                     "| 8, 0.13, 8% | short | 3 |", "| 8, 0.13, 8% | wide-short | 3 |", "| outcome (ground truth) | registered |", "Accurate results flagged registered"):
        assert expected in results, expected
    assert (output / "robustness_noise.png").stat().st_size > 0 and (output / "robustness_size.png").stat().st_size > 0
    assert all(isinstance(r["anchored_photos"], int) for r in records if r["after"] is not None)

    # --anchored-photos reaches the runs (the tiny suite's SIFT gives no anchors: at most 1 either way; the choice
    # itself is test_anchored_photos_keeps_the_photos_with_the_most_correspondences).
    one = tmp_path / "one-anchor"
    shutil.copytree(output / "references", one / "references")
    assert bench_main([str(suite), "--output", str(one), "--config", str(preset), "--train-steps", "20", "--initialisers", "perturbed",
                       "--anchored-photos", "1"]) == 0, capsys.readouterr().err
    anchored = [json.loads(p.read_text()) for p in sorted((one / "runs").glob("*/*/*.json"))]
    assert len(anchored) == 3 and all(r["anchored_photos"] <= 1 for r in anchored)
    markers = sorted((one / "references").glob("*/reference.json"))
    assert markers and all(m.read_text() == (output / "references" / m.parent.name / "reference.json").read_text() for m in markers)  # reused
    assert all(not Path(json.loads(m.read_text())["config"]).is_absolute() for m in markers)  # the copy holds its own references

    # --twin-anchors builds the twin copies (the tiny photos give no SIFT anchors: the photo to copy comes from a stub)
    # and registers those; what a twin copy holds is test_a_twin_copy_has_its_photos_pose_zoomed_camera_and_observations.
    from sg_nerfstudio.bench import twins
    from sg_nerfstudio.initialisers.estimate import PhotoKeypoints

    class FirstPhotoMatches:
        def __init__(self, *args, **kwargs):
            pass

        def keypoints(self, meta):
            return [PhotoKeypoints(photo.name, np.zeros((9 - i, 2)), np.zeros((9 - i, 3))) for i, photo in enumerate(meta.photos)]

    monkeypatch.setattr(twins, "Initialiser", FirstPhotoMatches)
    twin_output, copies = tmp_path / "twin-results", tmp_path / "twins"
    shutil.copytree(output / "references", twin_output / "references")
    assert bench_main([str(suite), "--output", str(twin_output), "--twin-anchors", str(copies), "--config", str(preset), "--train-steps", "20",
                       "--initialisers", "perturbed"]) == 0, capsys.readouterr().err
    twinned = [json.loads(p.read_text()) for p in sorted((twin_output / "runs").glob("*/*/*.json"))]
    originals = {(r["scene"], r["meta"]): r["photos"] for r in records if r["run"] == "perturbed"}
    assert len(twinned) == 3 and all(r["photos"] == originals[(r["scene"], r["meta"])] + 1 for r in twinned)
    assert len(list(copies.glob("*/meta/*/twin.json"))) == 3 and not list(copies.glob("*/meta/*.partial"))

    # Resumption: finished runs and references are reused; a missing record is run again.
    stamps = {p: p.stat().st_mtime_ns for p in [*(output / "runs").glob("*/*/*.json"), *(output / "references").glob("*/reference.json")]}
    removed = output / "runs" / "tiny-b" / "rear" / "noise-8.json"
    removed.unlink()
    capsys.readouterr()
    assert bench_main(args) == 0
    printed = capsys.readouterr().out
    run_lines = [line for line in printed.splitlines() if line.startswith("tiny-")]
    assert len(run_lines) == 1 and run_lines[0].startswith("tiny-b/rear noise-8:"), printed
    assert removed.is_file()
    assert all(p.stat().st_mtime_ns == stamp for p, stamp in stamps.items() if p != removed)

    # bench.photo_losses reads the same references: every photo's loss ratio at the truth and 5° away.
    scene = read_benchmark(suite)[1]
    fractions = occlusion_of(scene)
    assert sorted(fractions) == ["front", "rear"] and all(len(photos) == 4 for photos in fractions.values())
    rows = photo_ratios(scene, trained_reference(output, scene.name)[0], load_preset(str(preset)), [0.0, 5.0], seed=0)
    assert len(rows) == 2 * 8 and all(np.isfinite(row["losses"]).all() and row["losses"].min() > 0 for row in rows)


def test_noise_table_names_the_preset_each_run_was_made_with():
    """Runs an earlier invocation made with another `--config` keep their preset's name in a later report."""
    from sg_nerfstudio.bench.report import noise_table

    def record(preset, dR):
        return {"family": "noise", "label": "30", "mode": "", "preset": preset, "refine_time_s": 10.0,
                "after": {"dR": dR, "dT": 0.01, "accurate": dR < 5, "outlier": dR > 10}}

    beside = lambda won: {**record("fast-cpu", 20.0 if won == "given" else 1.0), "other_starts": ["dense"], "start_won": won}
    rows = noise_table([record("wide-cpu", 1.0), record("wide-cpu", 3.0), record("fast-cpu", 20.0), {**record("", 2.0), "preset": None}], "fast-cpu")
    assert rows[2:] == [
        "| 30, 0.50, 30% | fast-cpu | 2 | 50 | 50 | 11.00 / 11.00 | 0.010 / 0.010 | 2.00 / 0.010 | - | 10 |",
        "| 30, 0.50, 30% | wide-cpu | 2 | 100 | 0 | 2.00 / 2.00 | 0.010 / 0.010 | 2.00 / 0.010 | - | 10 |",
    ]
    rows = noise_table([beside("dense"), beside("dense"), beside("given")], "fast-cpu")
    assert rows[2:] == ["| 30, 0.50, 30% | fast-cpu | 3 | 67 | 33 | 7.33 / 1.00 | 0.010 / 0.010 | 1.00 / 0.010 | 2 of 3 | 10 |"]
    at_truth = {**record("fast-cpu", 0.5), "label": "0"}  # the start at the ground truth itself comes first, named so
    rows = noise_table([record("fast-cpu", 1.0), at_truth], "fast-cpu")
    assert [row.split(" | ")[0] for row in rows[2:]] == ["| 0 (the ground truth itself)", "| 30, 0.50, 30%"]


def test_verdict_table_has_one_block_per_preset_and_counts_inaccurate_results_called_registered():
    from sg_nerfstudio.bench.report import verdict_table

    def record(preset, dR, verdict):
        return {"preset": preset, "verdict": verdict, "after": {"dR": dR, "dT": 0.01}}

    one = [record("fast-cpu", 1.0, "registered"), record("fast-cpu", 7.0, "registered"), record("fast-cpu", 20.0, "failed")]
    assert verdict_table(one) == [
        "| outcome (ground truth) | registered | uncertain | failed |", "|---|---|---|---|",
        "| accurate | 1 | 0 | 0 |", "| in between | 1 | 0 | 0 |", "| outlier | 0 | 0 | 1 |", "",
        "Accurate results flagged registered: 100% (1/1); outliers flagged uncertain or failed: 100% (1/1); "
        "inaccurate results flagged registered: 50% (1/2).",
    ]
    both = verdict_table([*one, record("wide-cpu", 7.0, "uncertain"), {**record("wide-cpu", 1.0, None)}])
    assert both[:2] == ["| preset | outcome (ground truth) | registered | uncertain | failed |", "|---|---|---|---|---|"]
    assert "| wide-cpu | in between | 0 | 1 | 0 |" in both and "| fast-cpu | accurate | 1 | 0 | 0 |" in both
    assert both[-1] == ("wide-cpu: Accurate results flagged registered: -; outliers flagged uncertain or failed: -; "
                        "inaccurate results flagged registered: 0% (0/1).")
    assert verdict_table([record("fast-cpu", 1.0, None)]) == []
    assert verdict_table([record(None, 1.0, "registered"), record("fast-cpu", 1.0, "registered")], "fast-cpu")[2] == "| accurate | 2 | 0 | 0 |"  # older records


def test_start_precision_table_counts_refinements_further_than_their_start_beyond_the_truths_residual(tmp_path):
    """Issue 19 §1 by bands of the start's ΔR: further than the start at all, and by more than gt_transform.json's residual."""
    from sg_nerfstudio.bench.layout import read_meta
    from sg_nerfstudio.bench.report import start_precision_table

    meta = tmp_path / "m"
    meta.mkdir()
    (meta / "gt_transform.json").write_text(json.dumps({"matrix": np.eye(4).tolist(), "residual_rotation_deg": [0.3, 0.4], "residual_centre": [0.0, 0.02]}))
    residual = read_meta(meta).truth_residual
    assert residual["dR"] == pytest.approx(np.sqrt(0.125)) and residual["dT"] == pytest.approx(np.sqrt(0.0002))
    (meta / "gt_transform.json").write_text(json.dumps({"matrix": np.eye(4).tolist()}))
    assert read_meta(meta).truth_residual is None

    def record(before, after, truth=None, run="colmap"):
        return {"family": "table1", "run": run, "start": "colmap", "mode": "", "truth_residual": truth,
                "before": {"dR": before[0], "dT": before[1]}, "after": {"dR": after[0], "dT": after[1]}}

    records = [
        record((0.06, 0.077), (0.28, 0.023), {"dR": 0.21, "dT": 0.013}),  # further in ΔR, by more than the residual
        record((0.43, 0.011), (0.44, 0.013), {"dR": 0.15, "dT": 0.012}),  # further in both, within the residual
        record((0.30, 0.010), (0.302, 0.0104)),  # under the printed precision: not further
        record((0.50, 0.010), (0.60, 0.020)),  # no residual known (synthetic): any change counts
        record((2.00, 0.100), (0.50, 0.010)),
        {**record((9.0, 0.3), (0.5, 0.01)), "after": None},  # a registration error: not counted
    ]
    assert start_precision_table(records, ("colmap", "generalized"))[2:] == [
        "| colmap | < 1° | 4 | 3 | 2 | 2 | 1 |",
        "| colmap | 1-5° | 1 | 0 | 0 | 0 | 0 |",
    ]
    assert start_precision_table([], ("colmap",)) == []
    # a scene with a point-based truth adds "by more than the two truths differ" to both
    records[0]["truth_disagreement"] = {"dR": 0.15, "dT": 0.0}  # 0.22° further: beyond 0.15°, and ΔT closer
    records[1]["truth_disagreement"] = {"dR": 0.02, "dT": 0.0005}  # 0.01° / 0.002 further: within 0.02°, beyond 0.0005 (+ 0.0005)
    assert start_precision_table(records, ("colmap",))[:3] == [
        "| start | start ΔR | starts | ΔR further | by more than the truth's residual | by more than the two truths differ "
        "| ΔT further | by more than the truth's residual | by more than the two truths differ |",
        "|---|---|---|---|---|---|---|---|---|",
        "| colmap | < 1° | 4 | 3 | 2 | 2 | 2 | 1 | 2 |",
    ]


def test_photo_loss_separation_is_the_auc_of_the_ratios():
    assert separation(np.array([1.3, 1.4]), np.array([0.9, 1.0])) == 1.0
    assert separation(np.array([0.9, 1.0]), np.array([1.3, 1.4])) == 0.0
    assert separation(np.array([1.0, 1.2]), np.array([1.0, 1.1])) == pytest.approx(0.625)  # one tie counts half


def test_bad_layout_is_one_sentence(suite, tmp_path, capsys):
    broken = tmp_path / "broken"
    shutil.copytree(suite / "tiny-a", broken / "tiny-a")
    (broken / "tiny-a" / "meta" / "front" / "gt_transform.json").unlink()
    capsys.readouterr()
    assert bench_main([str(broken), "--output", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err.strip()
    assert "gt_transform.json" in err and len(err.splitlines()) == 1 and not (tmp_path / "out").exists()
    with pytest.raises(BenchmarkLayoutError, match="does not exist"):
        read_benchmark(tmp_path / "nowhere")


def test_scaling_goals_are_judged_from_the_measured_records():
    """bench.scaling's closing table compares what the run measured with the issue's goals, row by row."""
    from rich.console import Console

    from sg_nerfstudio.bench.scaling import goals_table

    def record(size, mode, step, peak, **extra):
        return {"size": size, "mode": mode, "step_s": step, "peak_rss_gb": peak, "photos": 16, "gaussians": size or 46_942, **extra}

    report = {
        "args": {"training_steps": "1500"},
        "growth": [
            record(0, "today", 1.8, 2.0, register_s=120.0), record(0, "new", 1.6, 1.5, register_s=45.0),
            record(100_000, "today", 4.0, 2.6), record(100_000, "new", 2.5, 1.8),
            record(1_000_000, "today", 26.0, 12.0), record(1_000_000, "new", 8.0, 4.6, register_s=600.0),
        ],
        "concurrency": {"solo": {"register_s": 50.0}, "concurrent": [{"register_s": 70.0}, {"register_s": 110.0}]},
        "training": [
            {"scene": "stand-in", "train_s": 900.0, "held_out_psnr": 18.3, "train_psnr": 36.6},
            {"scene": "stand-in", "train_s": 380.0, "held_out_psnr": 17.5, "train_psnr": 36.8},
        ],
    }
    console = Console(record=True, width=250)
    goals_table(report, console)
    lines = {line.split("│")[1].strip(): [cell.strip() for cell in line.split("│")[2:-1]] for line in console.export_text().splitlines() if line.count("│") > 2}
    assert lines["registration of the meta-image against the model as trained (16 photos, 46,942 Gaussians) <= 60 s"] == ["45.0 s", "120.0 s", "yes"]
    assert lines["step at 1,000,000 <= 3x step at 100,000"] == ["3.20x", "6.50x", "no"]
    assert lines["1,000,000 Gaussians register within 24 GB (peak resident)"] == ["4.6 GB", "12.0 GB (step)", "yes"]
    assert lines["two registrations at once: each <= about 2x its solo time"] == ["2.20x (the slower)", "-", "no"]
    assert lines["training 1500 steps of stand-in <= 10 min"] == ["6.3 min", "15.0 min", "yes"]
    assert lines["... same PSNR (held-out / training views, dB)"][2] == "-0.80 / +0.20 dB"


def test_anchored_photos_keeps_the_photos_with_the_most_correspondences():
    """`sg-bench --anchored-photos N`: a run's anchors are those of the N photos with the most correspondences."""
    from sg_nerfstudio.bench.runs import BenchOptions, SceneRunner
    from sg_nerfstudio.initialisers.estimate import PhotoKeypoints
    from sg_nerfstudio.registration.settings import RegistrationSettings

    photos = [PhotoKeypoints(name, np.zeros((count, 2)), np.zeros((count, 3))) for name, count in (("a", 12), ("b", 40), ("c", 25))]
    runner = SceneRunner.__new__(SceneRunner)  # no reference or scene needed for the choice
    runner.initialiser = type("Stub", (), {"keypoints": lambda self, subject: photos})()
    runner.reference_unusable = None
    settings = RegistrationSettings().changed(anchors={"weight": 1.0})
    for count, expected in ((1, ["b"]), (2, ["b", "c"]), (0, ["a", "b", "c"])):
        runner.options = BenchOptions(settings=settings, anchored_photos=count)
        assert [k.name for k in runner.keypoints(None, settings)] == expected


def test_a_twin_copy_has_its_photos_pose_zoomed_camera_and_observations(suite, tmp_path):
    """bench/twins.py: the twin of a photo sits at the photo's pose with its focal lengths / zoom, observes the photo's
    points inside the crop where that camera projects them (its principal point off the centre), and carries the
    photo's central crop; the ground truth is
    copied unchanged. A twin run keeps the anchors of the twin and its photo only."""
    import pycolmap
    from PIL import Image

    from sg_nerfstudio.bench.runs import BenchOptions
    from sg_nerfstudio.bench.twins import TwinSceneRunner, add_twin
    from sg_nerfstudio.errors import InputError
    from sg_nerfstudio.geometry.meta_image import load_meta_image
    from sg_nerfstudio.initialisers.estimate import PhotoKeypoints
    from sg_nerfstudio.registration.settings import RegistrationSettings

    source = tmp_path / "source"  # a meta-image of the suite with the photo's principal point moved off the centre
    shutil.copytree(read_benchmark(suite)[0].metas[0].directory, source)
    photo = load_meta_image(source).photos[1].name
    given = pycolmap.Reconstruction(source / "sparse" / "0")
    off_centre = given.cameras[given.find_image_with_name(photo).camera_id]
    off_centre.params = np.array(off_centre.params) + np.isin(np.arange(len(off_centre.params)), off_centre.principal_point_idxs()) * 2.5
    given.write(source / "sparse" / "0")
    copy = tmp_path / "twin"
    name = add_twin(source, copy, photo, zoom=0.8)
    assert (copy / "gt_transform.json").read_bytes() == (source / "gt_transform.json").read_bytes()
    meta = load_meta_image(copy)
    assert len(meta.photos) == len(load_meta_image(source).photos) + 1
    model = pycolmap.Reconstruction(copy / "sparse" / "0")
    original, twin = model.find_image_with_name(photo), model.find_image_with_name(name)
    camera, twin_camera = model.cameras[original.camera_id], model.cameras[twin.camera_id]
    assert np.allclose(twin.cam_from_world().matrix(), original.cam_from_world().matrix())
    assert np.isclose(twin_camera.mean_focal_length(), camera.mean_focal_length() / 0.8)
    centre = np.array([camera.width, camera.height]) / 2
    observed = [p for p in twin.points2D if p.has_point3D()]
    assert 0 < len(observed) <= sum(p.has_point3D() for p in original.points2D)
    for observation in observed:
        xyz = model.points3D[observation.point3D_id].xyz
        in_photo = np.asarray(camera.img_from_cam(original.cam_from_world() * xyz))
        in_twin = np.asarray(twin_camera.img_from_cam(twin.cam_from_world() * xyz))
        assert np.allclose(in_twin, (in_photo - centre) / 0.8 + centre, atol=1e-6)
        assert 0 <= observation.xy[0] < camera.width and 0 <= observation.xy[1] < camera.height
    with Image.open(source / "images" / photo) as image, Image.open(copy / "images" / name) as zoomed:
        assert zoomed.size == image.size
        pixels = np.asarray(image.convert("RGB"), dtype=np.float64)
        w, h = image.size
        central = pixels[int(h * 0.1) : int(np.ceil(h * 0.9)), int(w * 0.1) : int(np.ceil(w * 0.9))]
        assert np.abs(np.asarray(zoomed, dtype=np.float64).mean((0, 1)) - central.mean((0, 1))).max() < 4.0
    with pytest.raises(InputError, match="not a photo"):
        add_twin(source, tmp_path / "other", "missing.png")

    photos = [PhotoKeypoints(n, np.zeros((5, 2)), np.zeros((5, 3))) for n in ("a", "b", "twin_a")]
    runner = TwinSceneRunner.__new__(TwinSceneRunner)
    runner.initialiser = type("Stub", (), {"keypoints": lambda self, subject: photos})()
    runner.reference_unusable = None
    runner.options = BenchOptions(settings=RegistrationSettings().changed(anchors={"weight": 1.0}))
    subject = type("Subject", (), {"photos": [type("P", (), {"name": n})() for n in ("a", "b", "twin_a")]})()
    assert [k.name for k in runner.keypoints(subject, runner.options.settings)] == ["a", "twin_a"]


@pytest.mark.parametrize("module, arguments", [
    ("registration", ["--scene", "{missing}"]),
    ("scaling", ["--meta-image", "{missing}", "--sizes", "1000", "--no-register", "--no-concurrency"]),  # through its child
])
def test_benchmark_modules_end_a_missing_reference_with_one_sentence(module, arguments, tmp_path):
    """`python -m sg_nerfstudio.bench.<module>` prints the sentence of a bad input and exits 1, without a traceback
    (bench.scaling: its measurement child's sentence, then its own)."""
    import subprocess
    import sys

    missing = tmp_path / "missing"
    command = [sys.executable, "-m", f"sg_nerfstudio.bench.{module}", "--load-config", str(missing / "config.yml"),
               *[argument.format(missing=missing) for argument in arguments], "--output", str(tmp_path / "out.json")]
    finished = subprocess.run(command, capture_output=True, text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert finished.returncode == 1
    assert f"Config {missing / 'config.yml'} does not exist" in finished.stderr and "Traceback" not in finished.stderr
    assert not (tmp_path / "out.json").exists()
