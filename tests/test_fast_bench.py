"""Fast checks of the benchmark modules on the tiny scene: a few training steps of bench.training and
bench.feature_splat, bench.rasterizer on a few hundred Gaussians, bench.registration's trials and bench.runs' runs
against the session's `quick_trained` reference (registrations of a few steps), bench.photo_losses' table, and
bench.runs' bookkeeping. sg-bench itself, end to end, is tests/test_bench.py's (slow)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import yaml
from rich.console import Console

from sg_nerfstudio.bench import feature_splat, photo_losses, rasterizer, training
from sg_nerfstudio.bench import registration as bench_registration
from sg_nerfstudio.bench.layout import read_scene
from sg_nerfstudio.bench.runs import (
    BenchOptions, RunSpec, SceneRunner, planned_runs, read_records, record_path, train_reference, trained_reference, write_json_atomically,
)
from sg_nerfstudio.registration.reference import load_reference
from sg_nerfstudio.registration.settings import load_preset
from sg_nerfstudio.render import rasterize

SHORT_PRESET = {"base": "fast-cpu", "optimiser": {"steps": 3}, "objective": {"kind": "features"}, "anchors": {"prealign_steps": 20, "main_steps": 2}, "last_stage": {"steps": 0}}
"""fast-cpu cut to a few steps, on the decoded features (no teacher run on every render): a registration of the tiny
meta-image in half a second."""


@pytest.fixture(autouse=True)
def private_caches(tmp_path, monkeypatch):
    """Feature and SIFT caches that default to ~/.cache go under the test's own directory."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg-cache"))


@pytest.fixture(scope="module")
def short_preset(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("preset") / "short.yaml"
    path.write_text(yaml.safe_dump(SHORT_PRESET))
    return path


@pytest.fixture(scope="module")
def reference(quick_trained):
    return load_reference(quick_trained)


@pytest.fixture
def bench_dir(tiny_scene, tmp_path) -> Path:
    """A benchmark directory of this test's own (variants and records are written next to the scene) holding the tiny
    scene as its one scene, `tiny`."""
    shutil.copytree(tiny_scene, tmp_path / "benchmark" / "tiny")
    return tmp_path / "benchmark"


def table_rows(text: str) -> list[list[str]]:
    """The body rows of the rich tables printed in `text`, as lists of stripped cells."""
    return [[cell.strip() for cell in line.split("│")[1:-1]] for line in text.splitlines() if line.count("│") > 2]


# ----------------------------------------------------------------------------------------------- bench.training


def test_training_benchmark_trains_each_arm_and_scores_held_out_and_training_views(tiny_scene, tmp_path, capsys):
    rows = training.run(training.Args(scenes=[tiny_scene], steps=2, scales=[4.0], output=tmp_path, threads=2, log_every=1, seeds=[5]))
    assert len(rows) == 1
    row = rows[0]
    assert (row["scene"], row["scale"], row["seed"]) == ("tiny", 4.0, 5) and row["gaussians"] > 0 and row["train_s"] > 0
    assert (row["held_out_views"], row["train_views"]) == (2, 14)  # colmap's split of the 16 reference images: every 8th held out
    assert all(np.isfinite(row[key]) for key in ("held_out_psnr", "train_psnr", "held_out_cosine", "train_cosine"))
    assert Path(row["config"]).is_file() and Path(row["config"]).is_relative_to(tmp_path)
    printed = capsys.readouterr().out
    assert "tiny-scale-4-seed-5 step 1:" in printed and "Reference training, 2 steps on CPU (2 threads)" in printed


def test_training_table_gives_each_arm_as_a_ratio_to_the_first_of_its_scene_and_seed():
    row = lambda scene, seed, scale, seconds: {
        "scene": scene, "seed": seed, "scale": scale, "train_s": seconds, "gaussians": 10, "held_out_psnr": 20.0, "held_out_cosine": 0.5,
        "held_out_views": 2, "train_psnr": 21.0, "train_cosine": 0.6, "train_views": 14,
    }
    console = Console(record=True, width=200)
    console.print(training.training_table([row("a", 1, 0.0, 100.0), row("a", 1, 4.0, 40.0), row("a", 2, 0.0, 50.0), row("a", 2, 4.0, 75.0)], 10, 2))
    assert [row[4] for row in table_rows(console.export_text())] == ["1.00", "0.40", "1.00", "1.50"]


# ------------------------------------------------------------------------------------------ bench.feature_splat


def test_feature_splat_benchmark_trains_evaluates_the_held_out_views_and_judges_the_goal(tiny_scene, tmp_path, capsys):
    result = feature_splat.run(feature_splat.Args(scene=tiny_scene, output=tmp_path, steps=2, teacher_input_size=64, feature_dim=16, log_every=1, threads=2))
    assert result["held_out_views"] == 2 and result["steps"] == 2 and result["gaussians"] > 0
    assert np.isfinite(result["psnr"]) and -1.0 <= result["feature_cosine"] <= 1.0
    assert sorted(result["timings"]) == ["evaluation", "scene", "setup + training"] and Path(result["config"]).is_relative_to(tmp_path)
    printed = capsys.readouterr().out
    assert "step 1:" in printed and "MISSED (PSNR>=24, cos>=0.8, <=900 s)" in printed  # two steps are far from the goal


# --------------------------------------------------------------------------------------------- bench.rasterizer


def test_rasterizer_case_is_the_landmark_seen_from_the_reference_ring_with_seeded_colours():
    case = rasterizer.landmark_case(400, 24, 5, seed=3)
    assert case["means"].shape == (400, 3) and case["colors"].shape == (400, 5) and case["viewmats"].shape == (1, 4, 4)
    assert torch.equal(case["colors"], rasterizer.landmark_case(400, 24, 5, seed=3)["colors"])
    assert not torch.equal(case["colors"], rasterizer.landmark_case(400, 24, 5, seed=4)["colors"])
    with torch.no_grad():
        _, alpha, info = rasterize(**case, backend="torch")
    assert int((info["radii"] > 0).sum()) > 100 and float(alpha.mean()) > 0.1  # the camera sees the landmark


def test_timed_reports_the_median_of_each_phase_after_a_warm_up():
    samples = iter([(9.0, 9.0), (0.001, 0.004), (0.003, 0.002), (0.002, 0.003)])
    forward, backward = rasterizer.timed(lambda: next(samples), 3)
    assert forward == pytest.approx(2.0) and backward == pytest.approx(3.0)  # milliseconds; the warm-up's 9 s left out


def test_rasterizer_benchmark_times_every_backend_and_the_brute_force_compositor(monkeypatch, capsys):
    """The benchmark's two cases shrunk to a few hundred Gaussians on 16 px: its table, one verdict per backend and case,
    and its notes (the verdicts themselves are about the full-size cases: not asserted)."""
    original = rasterizer.landmark_case
    monkeypatch.setattr(rasterizer, "landmark_case", lambda n, size, channels: original(n // 100, 16, channels))
    rasterizer.main(rasterizer.Args(repeats=1, threads=2, channels=4))
    printed = capsys.readouterr().out
    for case in ("20k, 64x64", "100k, 128x128"):
        for backend in ("numba", "torch"):
            assert f"{case} {backend}: pose-only backward =" in printed
    assert "brute force" in printed and "Speed-up of the numba backend over the brute-force compositor (20k, 64x64)" in printed
    assert printed.count("(met)") + printed.count("(MISSED)") == 4


# ------------------------------------------------------------------------------------------ bench.registration


def test_prune_keeps_the_most_opaque_gaussians(reference):
    pruned = bench_registration.prune(reference, 100)
    assert pruned.means.shape[0] == 100
    assert float(pruned.opacities.min()) >= float(torch.sort(reference.opacities, descending=True).values[99])
    assert bench_registration.prune(reference, reference.means.shape[0]) is reference


def test_registration_benchmark_writes_accuracy_and_ablation_results(quick_trained, bench_dir, short_preset, tmp_path, capsys):
    """One accuracy trial on the scene at the benchmark's start noise, one ablation trial on its heavily occluded
    variant (built next to it, same reference capture) at the asked noise, the raw results in one JSON file."""
    output = tmp_path / "registration.json"
    args = bench_registration.Args(
        load_config=quick_trained, scene=bench_dir / "tiny", config=str(short_preset), trials=1, ablation_trials=1,
        ablation_rows=("none",), ablation_start=(3.0, 0.05, 0.1), skip=("speed",), output=output, threads=2,
    )
    bench_registration.main(args)
    report = json.loads(output.read_text())
    assert report["gaussians"] == load_reference(quick_trained).means.shape[0] and report["settings"]["optimiser"]["steps"] == 3
    (accuracy,) = report["accuracy"]["rows"]
    assert (accuracy["meta"], accuracy["seed"], accuracy["steps"]) == ("front", 0, 3) and accuracy["dR_before"] == pytest.approx(5.0, abs=1e-6)
    assert report["accuracy"]["success_rate"] == float(accuracy["dR"] < 1.0 and accuracy["dT"] < 0.05)
    assert accuracy["verdict"] in {"registered", "uncertain", "failed"} and accuracy["timings"]["render"] > 0 and isinstance(accuracy["accurate"], bool)
    (ablation,) = report["ablations"]["none"]
    assert ablation["seed"] == 100 and ablation["dR_before"] == pytest.approx(3.0, abs=1e-6)
    variant = bench_dir / "tiny-occluded"
    assert (variant / "reference").is_dir() and [p.name for p in (variant / "meta").iterdir()] == ["front"]
    for name in ("cameras.bin", "images.bin"):  # the variant shares the reference capture
        model = Path("reference") / "colmap" / "sparse" / "0" / name
        assert (variant / model).read_bytes() == (bench_dir / "tiny" / model).read_bytes()
    printed = capsys.readouterr().out
    assert "Accuracy: 1 starts" in printed and "none: mean ΔR" in printed and "Raw results:" in printed
    with pytest.raises(SystemExit, match="Unknown ablation row"):
        bench_registration.main(bench_registration.Args(load_config=quick_trained, scene=bench_dir / "tiny", ablation_rows=("nothing",)))


def test_registration_speed_case_registers_with_and_without_the_anchors(reference, quick_trained, bench_dir, short_preset, monkeypatch, capsys):
    """The speed part on the tiny meta-image. SIFT finds no correspondence between 48-px photos (the tiny reference
    gives no SIFT cloud), so the anchors come from a stand-in: 20 of each photo's own sparse points, exact
    (test_fast_registration.own_anchors)."""
    from test_fast_registration import own_anchors

    (meta, truth), = bench_registration.load_metas(bench_dir / "tiny")
    world = own_anchors(meta, truth, 20, seed=0)
    monkeypatch.setattr(bench_registration, "reference_keypoints", lambda config, subject: world if config == quick_trained else [])
    report = bench_registration.speed(reference, quick_trained, bench_dir / "tiny", load_preset(str(short_preset)), Console(record=True, width=250))
    assert report["anchored_photos"] == len(meta.photos) and report["anchors_s"] >= 0
    assert report["anchored"]["dR_before"] == report["dense"]["dR_before"] == pytest.approx(5.0, abs=1e-6)
    assert report["anchored"]["steps"] == 2 and report["dense"]["steps"] == 3  # anchored: the preset's anchors.main_steps
    assert report["anchored"]["dR"] < 1.0  # exact anchors hold the pose


# --------------------------------------------------------------------------------------------------- bench.runs


def test_planned_runs_name_every_run_of_a_meta_image_in_order():
    options = BenchOptions(
        settings=load_preset("fast-cpu"), initialisers=("colmap", "perturbed"), ablations=("none",), noise_levels=(2.0, 7.5),
        noise_samples=2, sizes=(2, 3, 5, 8), size_samples=2, alternatives={"wide": load_preset("wide-cpu")},
    )
    runs = planned_runs(options, 5)
    assert [run.name for run in runs] == [
        "colmap", "perturbed", "colmap@wide", "perturbed@wide", "ablation-none",
        "noise-2", "noise-2@wide", "noise-2-s1", "noise-2-s1@wide", "noise-7.5", "noise-7.5@wide", "noise-7.5-s1", "noise-7.5-s1@wide",
        "size-3-0", "size-3-1",  # sizes below 3 or not below the meta-image's 5 photos are left out
    ]
    by_name = {run.name: run for run in runs}
    assert by_name["ablation-none"].overrides == {"robust": {"rule": "none"}} and by_name["ablation-none"].start == "perturbed"
    assert (by_name["noise-7.5-s1@wide"].rotation_noise_deg, by_name["noise-7.5-s1@wide"].sample, by_name["noise-7.5-s1@wide"].mode) == (7.5, 1, "wide")
    assert (by_name["size-3-1"].subset_size, by_name["size-3-1"].sample, by_name["size-3-1"].family) == (3, 1, "size")
    assert [run.name for run in planned_runs(BenchOptions(settings=options.settings, initialisers=()), 5)] == []


def test_records_are_written_atomically_and_read_back_in_order(tmp_path):
    assert read_records(tmp_path) == []
    for scene, meta, run, value in (("b", "front", "perturbed", 2), ("a", "rear", "colmap", 1), ("a", "front", "noise-5", np.float32(0.5))):
        path = record_path(tmp_path, scene, meta, run)
        assert path == tmp_path / "runs" / scene / meta / f"{run}.json"
        write_json_atomically(path, {"run": run, "value": value})
    write_json_atomically(record_path(tmp_path, "a", "rear", "colmap"), {"run": "colmap", "value": 3})  # replaced whole
    assert read_records(tmp_path) == [{"run": "noise-5", "value": 0.5}, {"run": "colmap", "value": 3}, {"run": "perturbed", "value": 2}]
    assert not list((tmp_path / "runs").rglob(".*.tmp"))  # no staging file left behind


def test_a_trained_reference_is_reused_while_its_config_exists(tmp_path):
    assert trained_reference(tmp_path, "tiny") is None
    config = tmp_path / "run" / "config.yml"
    write_json_atomically(tmp_path / "references" / "tiny" / "reference.json", {"config": str(config), "train_s": 12.5})
    assert trained_reference(tmp_path, "tiny") is None
    config.parent.mkdir()
    config.write_text("")
    assert trained_reference(tmp_path, "tiny") == (config, 12.5)
    scene = SimpleNamespace(name="tiny")  # reused: nothing of the scene is read, no step is trained
    assert train_reference(scene, tmp_path, 10, lambda step: pytest.fail("trained again")) == (config, 12.5)


def test_a_trained_reference_is_found_from_another_directory_and_in_a_moved_output(tmp_path, monkeypatch):
    """The marker names the config relative to its own folder (what train_reference writes); a marker of an earlier
    version, relative to the directory sg-bench ran in, is still read there."""
    output = tmp_path / "results"
    config = output / "references" / "tiny" / "runs" / "tiny" / "sg-feature-splat" / "t" / "config.yml"
    config.parent.mkdir(parents=True)
    config.write_text("")
    marker = output / "references" / "tiny" / "reference.json"
    write_json_atomically(marker, {"config": "runs/tiny/sg-feature-splat/t/config.yml", "train_s": 3.0})
    monkeypatch.chdir(config.parent)
    assert trained_reference(output, "tiny") == (marker.parent / "runs/tiny/sg-feature-splat/t/config.yml", 3.0)
    moved = tmp_path / "moved"
    output.rename(moved)
    assert trained_reference(moved, "tiny")[0].resolve() == (moved / "references" / "tiny" / "runs" / "tiny" / "sg-feature-splat" / "t" / "config.yml").resolve()
    monkeypatch.chdir(tmp_path)
    write_json_atomically(moved / "references" / "tiny" / "reference.json", {"config": "moved/references/tiny/runs/tiny/sg-feature-splat/t/config.yml", "train_s": 3.0})
    assert trained_reference(Path("moved"), "tiny") == (Path("moved/references/tiny/runs/tiny/sg-feature-splat/t/config.yml"), 3.0)


def test_a_scene_runner_registers_a_perturbed_start_and_records_why_the_initialisers_cannot(quick_trained, bench_dir, short_preset, tmp_path):
    """A perturbed run and a 3-photo subset run register and write their records; the tiny reference gives no SIFT
    cloud, so the keypoints are none (and the dense start runs beside the perturbed one, as fast-cpu asks) and the
    colmap initialiser's run records that sentence without registering."""
    from sg_nerfstudio.geometry.meta_image import load_meta_image

    scene = read_scene(bench_dir / "tiny")
    (meta,) = scene.metas
    loaded = load_meta_image(meta.directory)
    runner = SceneRunner(scene, quick_trained, BenchOptions(settings=load_preset(str(short_preset)), preset="short"), tmp_path)
    steps = []
    record = runner.run(meta, loaded, RunSpec("perturbed", "table1", "perturbed", "perturbed"), lambda step, total: steps.append((step, total)))
    assert record == json.loads(record_path(tmp_path, "tiny", "front", "perturbed").read_text())
    assert record["before"]["dR"] == pytest.approx(5.0, abs=1e-6) and record["after"] is not None and record["anchored_photos"] == 0
    assert record["preset"] == "short" and record["photos"] == len(loaded.photos) and record["verdict"] in {"registered", "uncertain", "failed"}
    assert record["other_starts"] == ["dense"] and record["start_won"] in {"given", "dense"}  # no anchors: the dense start runs beside
    assert [h["start"] for h in record["hypotheses"]] == ["given", "dense"] and min(h["rotation_from_winner_deg"] for h in record["hypotheses"]) < 1e-5
    assert len(steps) == 2 * 3 and {total for _, total in steps} == {6}
    subset = runner.run(meta, loaded, RunSpec("size-3-0", "size", "perturbed", "3", subset_size=3), lambda *_: None)
    assert subset["photos"] == 3 and subset["truth_residual"] is None and subset["after"] is not None
    failed = runner.run(meta, loaded, RunSpec("colmap", "table1", "colmap", "colmap"), lambda *_: None)
    assert failed["before"] is None and failed["after"] is None and "SIFT" in failed["init_failure"]
    assert [r["run"] for r in read_records(tmp_path)] == ["colmap", "perturbed", "size-3-0"]
    assert [spec.name for spec in runner.pending(meta, len(loaded.photos))] == ["generalized"]  # colmap is recorded


def test_noise_starts_share_a_direction_and_differ_only_in_magnitude(bench_dir):
    """Every noise run of a meta-image starts from the same random direction: the rotation grows with the level, the
    translation and scale in proportion (NOISE_PER_DEGREE)."""
    from sg_nerfstudio.geometry.meta_image import load_meta_image
    from sg_nerfstudio.registration.metrics import pose_errors

    scene = read_scene(bench_dir / "tiny")
    (meta,) = scene.metas
    loaded = load_meta_image(meta.directory)
    runner = SceneRunner.__new__(SceneRunner)  # the noise starts need no reference
    starts = {level: runner.start(meta, loaded, RunSpec(f"noise-{level}", "noise", "noise", rotation_noise_deg=level), np.random.default_rng(7))[0]
              for level in (6.0, 12.0)}
    errors = {level: pose_errors(loaded.poses, start, meta.ground_truth) for level, start in starts.items()}
    assert errors[6.0].rotation_deg == pytest.approx(6.0, abs=1e-6) and errors[12.0].rotation_deg == pytest.approx(12.0, abs=1e-6)
    assert errors[12.0].translation == pytest.approx(2 * errors[6.0].translation, rel=0.05)
    relative = [np.asarray(start.rotation) @ np.asarray(meta.ground_truth.rotation).T for start in starts.values()]
    axes = [np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) for r in relative]
    assert np.dot(axes[0], axes[1]) / np.linalg.norm(axes[0]) / np.linalg.norm(axes[1]) == pytest.approx(1.0, abs=1e-9)


# ------------------------------------------------------------------------------------------ bench.photo_losses


def test_photo_losses_table_compares_occluded_and_clean_photos_per_offset(quick_trained, bench_dir, tmp_path, capsys):
    args = photo_losses.Args(benchmark=bench_dir, output=tmp_path / "bench-output", offsets=[0.0, 5.0], z=[2.0])
    photo_losses.run(args)
    assert "tiny: skipped (no trained reference in" in capsys.readouterr().out
    write_json_atomically(args.output / "references" / "tiny" / "reference.json", {"config": str(quick_trained), "train_s": 1.0})
    photo_losses.run(args)
    rows = {row[0]: row[1:] for row in table_rows(capsys.readouterr().out)}
    assert sorted(rows) == ["0", "5"]
    for offset in ("0", "5"):
        occluded, ratio_occluded, clean, ratio_clean, auc, *dropped = rows[offset]
        assert (occluded, clean) == ("3", "2")  # the tiny front meta-image: 3 photos occluded by 20-32%, 2 clean
        assert 0.0 <= float(auc) <= 1.0 and len(ratio_occluded.split("/")) == len(ratio_clean.split("/")) == 3
        assert len(dropped) == 2  # lts and outlier-lts z=2
        occluded_dropped, clean_kept = (int(n) for n in dropped[0].split(" / "))
        assert occluded_dropped + (2 - clean_kept) == 2  # the median rule drops the 2 of 5 photos above the median
