"""Bad inputs the commands must refuse with one sentence, a non-zero exit, nothing half-written and the user's files
untouched: outputs that would replace what a trained run points at, configs that carry code, corrupt run artefacts, a
dataset without its images, two commands writing one output, numbers out of range."""

from __future__ import annotations

import copy
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml

from sg_nerfstudio.registration.settings import SettingsRangeError, check_ranges, RegistrationSettings
from sg_nerfstudio.scripts.init_baseline import main as init_baseline_main
from sg_nerfstudio.scripts.make_scene import main as make_scene_main
from sg_nerfstudio.scripts.register_meta import main as register_main
from sg_nerfstudio.splat.trained import read_trainer_config


def snapshot(root: Path) -> dict[str, bytes]:
    """{relative path: bytes} of every file under `root`: what must be untouched."""
    return {str(path.relative_to(root)): path.read_bytes() for path in sorted(root.rglob("*")) if path.is_file()}


def one_sentence(code: int, capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert code == 1, err
    assert err and err.count("\n") == 0, err
    return err


@pytest.fixture
def run_copy(trained, tiny_scene, tmp_path) -> Path:
    """A copy of the session's trained run (config.yml, checkpoint, dataparser transforms) and of its dataset, the
    copied config pointing at the copied dataset: config.yml's path."""
    _, _, config = trained
    data = tmp_path / "dataset"
    shutil.copytree(tiny_scene / "reference", data)
    run = tmp_path / "run"
    shutil.copytree(config.get_base_dir(), run)
    loaded = read_trainer_config(run / "config.yml")
    loaded.pipeline.datamanager.data = data
    loaded.pipeline.datamanager.dataparser.data = data
    (run / "config.yml").write_text(yaml.dump(loaded))
    return run / "config.yml"


def meta_named(tiny_scene: Path, where: Path) -> Path:
    shutil.copytree(tiny_scene / "meta" / "front", where)
    return where


@pytest.mark.parametrize("case", ["checkpoint_directory", "dataset"])
def test_an_output_never_replaces_what_the_trained_run_points_at(case, run_copy, tiny_scene, tmp_path, capsys):
    """--output-dir <run> with a meta-image named like the checkpoint folder, or --output-dir <the dataset's parent> with
    one named like the dataset: with --overwrite each replaced an input the config points at."""
    run = run_copy.parent
    if case == "checkpoint_directory":
        out, meta = run, meta_named(tiny_scene, tmp_path / "metas" / "nerfstudio_models")
    else:
        out, meta = tmp_path, meta_named(tiny_scene, tmp_path / "metas" / "dataset")
    before = snapshot(tmp_path)
    code = register_main(["--load-config", str(run_copy), "--meta-image", str(meta), "--output-dir", str(out), "--overwrite",
                          "--optimiser.steps", "2"])
    err = one_sentence(code, capsys)
    assert "expected a directory apart from the inputs" in err and ("nerfstudio_models" in err or "dataset" in err), err
    assert snapshot(tmp_path) == before


def test_sg_init_baseline_never_replaces_the_trained_run(run_copy, tiny_scene, tmp_path, capsys):
    meta = meta_named(tiny_scene, tmp_path / "metas" / "front")
    before = snapshot(tmp_path)
    code = init_baseline_main(["--load-config", str(run_copy), "--meta-image", str(meta), "--output-dir", str(run_copy.parent / "nerfstudio_models"),
                               "--overwrite"])
    assert "expected a directory apart from the inputs" in one_sentence(code, capsys)
    assert snapshot(tmp_path) == before


def test_sg_bench_never_writes_into_the_benchmark(tmp_path, capsys):
    from sg_nerfstudio.scripts.bench import main as bench_main

    bench = tmp_path / "bench"
    (bench / "scene").mkdir(parents=True)
    (bench / "scene" / "notes.txt").write_text("the user's")
    code = bench_main([str(bench), "--output", str(bench)])
    assert "is the input" in one_sentence(code, capsys)
    assert snapshot(tmp_path) == {"bench/scene/notes.txt": b"the user's"}


@pytest.mark.parametrize("command", ["ns-register-meta", "sg-init-baseline"])
def test_a_config_that_carries_code_is_refused_before_anything_is_built(command, run_copy, tiny_scene, tmp_path, capsys, monkeypatch):
    marker = tmp_path / "code-ran"
    text = run_copy.read_text() + f"\nextra: !!python/object/apply:os.system ['touch {marker}']\n"
    run_copy.write_text(text)
    meta = meta_named(tiny_scene, tmp_path / "metas" / "front")
    args = ["--load-config", str(run_copy), "--meta-image", str(meta), "--output-dir", str(tmp_path / "out")]
    code = (register_main if command == "ns-register-meta" else init_baseline_main)([*args, *(["--init", "colmap"] if command == "sg-init-baseline" else [])])
    err = one_sentence(code, capsys)
    assert "holds the YAML tag !!python/object/apply:os.system" in err and "refused before building anything" in err, err
    assert not marker.exists() and not (tmp_path / "out").exists()


@pytest.mark.parametrize("case, expected", [
    ("truncated_checkpoint", "could not be read as a nerfstudio checkpoint"),
    ("foreign_checkpoint", "holds ['weights'], not a nerfstudio checkpoint"),
    ("code_in_checkpoint", "could not be read as a nerfstudio checkpoint"),
    ("transforms_not_json", "dataparser_transforms.json is not readable (JSONDecodeError)"),
    ("transforms_not_a_frame", "holds no usable frame"),
])
def test_a_corrupt_artefact_of_a_trained_run_is_one_sentence(case, expected, run_copy, tiny_scene, tmp_path, capsys):
    run = run_copy.parent
    checkpoint = sorted((run / "nerfstudio_models").glob("step-*.ckpt"))[-1]
    if case == "truncated_checkpoint":
        checkpoint.write_bytes(checkpoint.read_bytes()[: checkpoint.stat().st_size // 2])
    elif case == "foreign_checkpoint":
        torch.save({"weights": torch.zeros(3)}, checkpoint)
    elif case == "code_in_checkpoint":  # a pickle that names a callable: the weights-only loader refuses it
        torch.save({"pipeline": {}, "step": 1, "hook": Path}, checkpoint)
    elif case == "transforms_not_json":
        (run / "dataparser_transforms.json").write_text("{not json")
    else:
        (run / "dataparser_transforms.json").write_text(json.dumps({"transform": [[1, 0, 0]], "scale": 1.0}))
    meta = meta_named(tiny_scene, tmp_path / "metas" / "front")
    code = register_main(["--load-config", str(run_copy), "--meta-image", str(meta), "--output-dir", str(tmp_path / "out"),
                          "--init", str(meta / "gt_transform.json"), "--optimiser.steps", "2"])
    assert expected in one_sentence(code, capsys)
    assert not (tmp_path / "out").exists()


def test_a_dataset_without_its_images_stops_before_ns_train_writes_its_run(tiny_scene, tmp_path):
    from sg_nerfstudio.splat.datamanager import DatasetInputError
    from sg_nerfstudio.splat.method import sg_feature_splat_cpu

    data = tmp_path / "dataset"
    shutil.copytree(tiny_scene / "reference", data)
    shutil.rmtree(data / "images")
    config = copy.deepcopy(sg_feature_splat_cpu.config)
    config.output_dir = tmp_path / "outputs"
    config.pipeline.datamanager.data = data
    config.set_timestamp()
    with pytest.raises(DatasetInputError, match=r"The image folder .*images does not exist; expected the \d+ images the COLMAP model"):
        config.save_config()
    assert not (tmp_path / "outputs").exists()


def test_a_second_command_on_the_same_output_stops_before_its_work(run_copy, tiny_scene, tmp_path, capsys):
    out = tmp_path / "out"
    holder = subprocess.Popen(
        [sys.executable, "-c", f"import time\nfrom sg_nerfstudio.atomic import output_lock\nwith output_lock({str(out)!r}):\n"
                               "    print('held', flush=True)\n    time.sleep(60)\n"],
        stdout=subprocess.PIPE, text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        meta = meta_named(tiny_scene, tmp_path / "metas" / "front")
        code = register_main(["--load-config", str(run_copy), "--meta-image", str(meta), "--output-dir", str(out), "--optimiser.steps", "2"])
        assert f"is being written by a command still running (process {holder.pid})" in one_sentence(code, capsys)
        assert not out.exists()
    finally:
        holder.kill()
        holder.wait()
    from sg_nerfstudio.atomic import output_lock  # a crashed holder leaves no stuck lock

    with output_lock(out):
        pass


@pytest.mark.parametrize("flag, value, expected", [
    ("--reference-fov-deg", "nan", "--reference-fov-deg must be a finite number above 0 and below 180, got nan"),
    ("--occluder-rate", "inf", "--occluder-rate must be a finite number from 0 to 1, got inf"),
    ("--n-sparse-points", "0", "--n-sparse-points must be a whole number of 1 or more, got 0"),
    ("--height", "-1", "--height must be a finite number above 0, got -1.0"),
])
def test_a_scene_number_out_of_range_is_one_sentence(flag, value, expected, tmp_path, capsys):
    code = make_scene_main(["--preset", "tiny", "--output", str(tmp_path / "scene"), flag, value])
    assert expected in one_sentence(code, capsys)
    assert not (tmp_path / "scene").exists()


def test_a_real_scene_number_out_of_range_is_one_sentence(tmp_path):
    from sg_nerfstudio.photos.scene import RealSceneError, RealSceneSettings, build_real_scene

    with pytest.raises(RealSceneError, match=r"--scene\.photo-size must be a whole number of 16 or more, got -3"):
        build_real_scene(tmp_path / "photos", tmp_path / "scene", RealSceneSettings(photo_size=-3))
    with pytest.raises(RealSceneError, match=r"--scene\.occluder-coverage must be a finite number from 0 to 1, got nan"):
        build_real_scene(tmp_path / "photos", tmp_path / "scene", RealSceneSettings(occluder_coverage=(float("nan"), 0.3)))


@pytest.mark.parametrize("changes, expected", [
    ({"level_of_detail": {"render_budget": float("nan")}}, "render_budget (--level-of-detail.render-budget) must be a whole number"),
    ({"objective": {"kind": "feature"}}, "objective.kind (--objective.kind) must be one of features, teacher-on-render, photometric"),
    ({"camera_fit": {"focal": "yes"}}, "camera_fit.focal (--camera-fit.focal) must be true or false"),
    ({"hypotheses": {"rotation_deg": float("inf")}}, "hypotheses.rotation_deg (--hypotheses.rotation-deg) must be a finite number"),
])
def test_a_registration_setting_out_of_range_is_one_sentence(changes, expected):
    with pytest.raises(SettingsRangeError, match=expected.replace("(", r"\(").replace(")", r"\)").replace(".", r"\.")):
        check_ranges(RegistrationSettings().changed(**changes))


def test_a_meta_image_without_points_names_that_file(tiny_scene, tmp_path):
    from sg_nerfstudio.geometry.meta_image import MetaImageError, load_meta_image

    meta = meta_named(tiny_scene, tmp_path / "front")
    (meta / "sparse" / "0" / "points3D.bin").unlink()
    with pytest.raises(MetaImageError, match=r"sparse/0 has no points3D\.bin; expected cameras, images and points3D of one binary model"):
        load_meta_image(meta)


def test_copies_of_one_picture_are_named_as_the_reason_no_model_formed(tiny_scene, tmp_path, capsys):
    from sg_nerfstudio.scripts.meta_images import main as meta_images_main

    photos = tmp_path / "photos"
    photos.mkdir()
    source = sorted((tiny_scene / "meta" / "front" / "images").iterdir())[0]
    for index in range(5):
        shutil.copy(source, photos / f"copy_{index}{source.suffix}")
    code = meta_images_main([str(photos), "--output", str(tmp_path / "metas")])
    assert "5 of them are copies of one picture (copy_0" in one_sentence(code, capsys)
    assert not (tmp_path / "metas").exists()
