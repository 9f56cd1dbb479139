"""Fast checks of sg-demo (scripts/demo.py) without its training: the perturbed starts it registers from, the reference
it trains (two steps), and its refusal of an output directory that holds something. The whole demo from a wheel is
tests/test_install.py's (slow)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from rich.console import Console

from sg_nerfstudio.errors import InputError
from sg_nerfstudio.geometry.meta_image import load_meta_image
from sg_nerfstudio.geometry.sim3 import Sim3
from sg_nerfstudio.registration.metrics import pose_errors
from sg_nerfstudio.scripts import demo


def starts(tiny_scene, output, **changes) -> dict[str, Sim3]:
    """The demo's perturbed start per meta-image of the tiny scene, written under `output`."""
    output.mkdir(parents=True, exist_ok=True)
    metas, inits, gts = demo.perturbed_initialisations(tiny_scene, output, demo.DemoArgs(output=output, **changes))
    assert [m.name for m in metas] == ["front"] and gts == [tiny_scene / "meta" / "front" / "gt_transform.json"]
    assert [p.parent for p in inits] == [output]
    return {meta.name: Sim3.read_json(path, "Start") for meta, path in zip(metas, inits)}


def test_the_demo_starts_each_meta_image_at_its_truth_moved_by_the_asked_noise(tiny_scene, tmp_path):
    meta = load_meta_image(tiny_scene / "meta" / "front")
    truth = Sim3.read_json(tiny_scene / "meta" / "front" / "gt_transform.json", "Ground truth")
    start = starts(tiny_scene, tmp_path / "a", seed=4)["front"]
    assert pose_errors(meta.poses, start, truth).rotation_deg == pytest.approx(5.0, abs=1e-6)  # DemoArgs' default 5 deg
    assert abs(start.scale / truth.scale - 1.0) == pytest.approx(0.1, abs=1e-9)  # and 10% scale
    assert np.array_equal(start.matrix, starts(tiny_scene, tmp_path / "b", seed=4)["front"].matrix)  # seeded
    assert not np.allclose(start.matrix, starts(tiny_scene, tmp_path / "c", seed=5)["front"].matrix)
    wide = starts(tiny_scene, tmp_path / "d", seed=4, perturbation_deg=12.0, perturbation_translation=0.0, perturbation_scale=0.0)["front"]
    assert pose_errors(meta.poses, wide, truth).rotation_deg == pytest.approx(12.0, abs=1e-6) and wide.scale == pytest.approx(truth.scale)
    assert json.loads((tmp_path / "a" / "init_front.json").read_text())["matrix"] == np.asarray(start).tolist()


def test_the_demo_trains_its_reference_on_the_scene_it_generated(tiny_scene, tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))  # the demo's teacher caches its features there
    config = demo.train_reference(tiny_scene, tmp_path / "demo", 2, Console(quiet=True))
    assert config.name == "config.yml" and config.is_relative_to(tmp_path / "demo" / "reference")
    assert list(config.parent.glob("nerfstudio_models/*.ckpt")) and (config.parent / "dataparser_transforms.json").is_file()
    assert list((tmp_path / "cache").rglob("*")), "the teacher's features were cached under XDG_CACHE_HOME"


def test_the_demo_refuses_an_output_directory_that_holds_something(tmp_path, capsys):
    output = tmp_path / "used"
    output.mkdir()
    (output / "keep.txt").write_text("mine")
    with pytest.raises(InputError, match="exists and is not empty"):
        demo.run(demo.DemoArgs(output=output, scene="tiny"), Console(quiet=True))
    assert demo.main(["--output", str(output), "--scene", "tiny"]) == 1
    error = capsys.readouterr().err.strip()
    assert "exists and is not empty" in error and len(error.splitlines()) == 1
    assert [p.name for p in output.iterdir()] == ["keep.txt"]


def test_the_demo_generates_the_scene_and_registers_each_meta_image_from_its_perturbed_start(quick_trained, tmp_path, monkeypatch):
    """The demo end to end on the tiny scene, with the session's quick reference for the one it would train and a
    registration of a few steps: the scene, the start and the registration's outputs with the ground truth's errors."""
    preset = tmp_path / "short.yaml"
    preset.write_text(json.dumps({"base": "fast-cpu", "optimiser": {"steps": 2}, "last_stage": {"steps": 0}}))  # YAML reads JSON
    monkeypatch.setattr(demo, "train_reference", lambda scene, output, steps, console: quick_trained)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    output = tmp_path / "demo"
    console = Console(record=True, width=200)
    assert demo.run(demo.DemoArgs(output=output, scene="tiny", config=str(preset), threads=2), console) == 0
    assert (output / "scene" / "meta" / "front" / "gt_transform.json").is_file() and (output / "init_front.json").is_file()
    record = json.loads((output / "registrations" / "front" / "transform.json").read_text())
    assert record["verdict"] in {"registered", "uncertain", "failed"}
    assert "Demo finished" in console.export_text()
