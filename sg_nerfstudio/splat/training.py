"""Programmatic sg-feature-splat training on CPU (for the demo, benchmarks and tests).

`ns-train sg-feature-splat ...` is the user-facing way; this runs the same Trainer step by step so a
caller can watch progress and losses without the viewer or log writers. `short_cpu_schedule` (defined with
the method, re-exported here) is the schedule of the demo, sg-bench and `sg-feature-splat-cpu`.
"""

from __future__ import annotations

import copy
import random
from pathlib import Path
from typing import Callable, Optional

import numpy as np
import torch
from nerfstudio.engine.callbacks import TrainingCallbackLocation
from nerfstudio.engine.trainer import Trainer, TrainerConfig

from sg_nerfstudio.features import TeacherConfig
from sg_nerfstudio.splat.method import sg_feature_splat_config, short_cpu_schedule


def cpu_config(data: Path, output: Path, steps: int, teacher: TeacherConfig, experiment_name: Optional[str] = None) -> TrainerConfig:
    """The sg-feature-splat config for a CPU run of `steps` steps on the COLMAP dataset `data`."""
    config = copy.deepcopy(sg_feature_splat_config)
    config.machine.device_type = "cpu"
    config.output_dir = Path(output)
    config.experiment_name = experiment_name
    config.vis = "tensorboard"
    config.max_num_iterations = steps
    config.steps_per_eval_image = config.steps_per_eval_all_images = 10**9
    config.pipeline.datamanager.data = Path(data)
    config.pipeline.datamanager.teacher = teacher
    config.set_timestamp()
    return config


def train(config: TrainerConfig, on_step: Optional[Callable[[int, Trainer, dict], None]] = None) -> Trainer:
    """Run `config.max_num_iterations` steps as nerfstudio's Trainer does (callbacks around each step).

    `on_step(step, trainer, loss_dict)` is called after every step. Seeded from `config.machine.seed` first, as ns-train
    seeds its runs (`seed_everything`): the same config trains the same model.
    """
    seed_everything(config.machine.seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    for step in range(config.max_num_iterations):
        trainer.pipeline.train()
        for callback in trainer.callbacks:
            callback.run_callback_at_location(step, location=TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
        _, loss_dict, _ = trainer.train_iteration(step)
        for callback in trainer.callbacks:
            callback.run_callback_at_location(step, location=TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
        if on_step is not None:
            on_step(step, trainer, loss_dict)
    return trainer


def seed_everything(seed: int) -> None:
    """Python's, numpy's and torch's random generators from `seed`: what ns-train does before it sets up its Trainer
    (`nerfstudio.scripts.train._set_random_seed`, private there). Without it the splats' random orientations, the
    random background colours and the order of the training images differed from run to run: two sg-demo runs of the
    tiny scene trained models whose Gaussians' means differed by up to 0.09 and registered the same start to 1.92° and
    2.12°. The CPU rasterizer sums its gradients in a fixed order for a given thread count (`render.numba_compositor`),
    so a seeded run repeats bit for bit at the same `--threads`."""
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def save(trainer: Trainer, config: TrainerConfig) -> Path:
    """Write checkpoint, config.yml and dataparser_transforms.json like ns-train; returns config.yml."""
    trainer.save_checkpoint(config.max_num_iterations - 1)
    config.save_config()
    trainer.pipeline.datamanager.train_dataparser_outputs.save_dataparser_transform(trainer.base_dir / "dataparser_transforms.json")
    return config.get_base_dir() / "config.yml"


__all__ = ["cpu_config", "save", "seed_everything", "short_cpu_schedule", "train"]
