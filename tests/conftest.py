"""Shared fixtures: the tiny synthetic scene and a small sg-feature-splat trained on it (once per session)."""

from __future__ import annotations

from pathlib import Path

import pytest

from sg_nerfstudio.features import TeacherConfig
from sg_nerfstudio.scripts.make_scene import main as make_scene_main
from sg_nerfstudio.splat.training import cpu_config, save, train


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    output = tmp_path_factory.mktemp("scenes") / "tiny"
    assert make_scene_main(["--preset", "tiny", "--output", str(output), "--occluder-rate", "0.6"]) == 0
    return output


def make_config(data: Path, output: Path, steps: int, teacher: TeacherConfig):
    """A short CPU run whose densification and resolution schedule happen within `steps`."""
    config = cpu_config(data, output, steps, teacher)
    config.machine.seed = 0
    model = config.pipeline.model
    model.warmup_length, model.refine_every, model.reset_alpha_every = 60, 60, 1000
    model.resolution_schedule = 100
    model.feature_render_scale = 1.5  # the tiny scene's 48 px images: features apart at 1.5 x the 16-cell grid, 24 px
    return config


@pytest.fixture(scope="session")
def trained(tiny_scene, tmp_path_factory):
    """A 300-step CPU sg-feature-splat of the tiny scene (offline teacher): (trainer, loss history, config)."""
    output = tmp_path_factory.mktemp("train")
    config = make_config(tiny_scene / "reference", output, 300, TeacherConfig(name="offline", input_size=128, cache_dir=output / "cache"))
    history = []
    trainer = train(config, lambda step, trainer, losses: history.append(
        {name: float(value.detach()) for name, value in losses.items()} | {"n": trainer.pipeline.model.num_points}
    ))
    save(trainer, config)
    return trainer, history, config
