"""`sg-feature-splat` and `sg-feature-splat-cpu`: the nerfstudio methods registered through the
`nerfstudio.method_configs` entry point.

    ns-train sg-feature-splat colmap --data <scene>/reference          # the paper: 12000 steps, DINOv2 (local weights)
    ns-train sg-feature-splat-cpu colmap --data <scene>/reference      # CPU: sg-demo's 3000-step schedule, offline teacher

Both train on the GPU when the machine has one and on the CPU otherwise (`--machine.device-type` overrides).
`sg-feature-splat-cpu` is the short schedule of `short_cpu_schedule` with the weight-free offline teacher.

splatfacto's optimisers, plus the supplement's: per-Gaussian features Adam lr 0.05 -> 1.6e-6
(exponential decay, eps 1e-15) and the speedup decoder Adam lr 1e-3 (eps 1e-15); 12000 steps.

Learning-rate schedules decay over the paper's 12000 steps whatever the run's length (`MAX_STEPS`): rescaled
to a 1500-step run's own length they gave references that registered worse in the one benchmark run made
of them (README, "Training the reference model"), so short CPU runs keep the long decay.
An InputError raised while nerfstudio trains (e.g. missing images) ends `ns-train` with its sentence. A dataset whose
COLMAP model is missing or has no 3D points is refused before `ns-train` writes the run's config.yml
(`FeatureSplatTrainerConfig.save_config`), so such a run leaves no directory behind.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Type

import copy

import torch
from nerfstudio.configs.base_config import MachineConfig, ViewerConfig
from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParserConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig

from nerfstudio.engine.schedulers import ExponentialDecayScheduler
from nerfstudio.engine.schedulers import ExponentialDecaySchedulerConfig as _NerfstudioExponentialDecayConfig
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig
from nerfstudio.plugins.types import MethodSpecification

from sg_nerfstudio.errors import install_input_error_hook
from sg_nerfstudio.features import TeacherConfig
from sg_nerfstudio.splat.datamanager import FeatureDatamanagerConfig, check_dataset
from sg_nerfstudio.splat.model import FeatureSplatfactoModelConfig

MAX_STEPS = 12000
SPARSE_VIEWS = 20
"""`short_cpu_schedule` densifies only references trained on at least this many views: the real-photo scenes' 6-view
references registered closer without densification; the synthetic suite's 60-view references keep it (README,
"Training the reference model"). Nothing between 6 and 60 views was measured."""
CPU_STEPS = 3000
"""Steps of `sg-feature-splat-cpu` (sg-demo's reference: about 7 minutes of a 2-core CPU)."""
install_input_error_hook()


class ExponentialDecayScheduler_(ExponentialDecayScheduler):
    """nerfstudio's exponential decay with python-float learning rates.

    nerfstudio 1.1.5 computes them with numpy, so numpy scalars land in every checkpoint, and torch >= 2.6
    refuses to load those with `weights_only=True` (the default that `ns-viewer`, `ns-render` and
    `ns-export` use). Same schedule, plain floats.
    """

    def get_scheduler(self, optimizer, lr_init: float):
        scheduler = super().get_scheduler(optimizer, lr_init)
        scheduler.lr_lambdas = [lambda step, f=f: float(f(step)) for f in scheduler.lr_lambdas]
        scheduler._last_lr = [float(lr) for lr in scheduler._last_lr]
        for group in optimizer.param_groups:
            group["lr"] = float(group["lr"])
        return scheduler


@dataclass
class ExponentialDecaySchedulerConfig(_NerfstudioExponentialDecayConfig):
    _target: Type = field(default_factory=lambda: ExponentialDecayScheduler_)


def short_cpu_schedule(config: TrainerConfig) -> TrainerConfig:
    """Splatfacto's schedule scaled to a short CPU run of `config.max_num_iterations` steps (in place).

    Splatfacto doubles the training resolution every 3000 of its 30000 steps, starts densifying after 500
    steps and stops at step 15000; here the resolution doubles every sixth of the run, densification starts
    after a sixth (splatfacto's 500 for a 3000-step run) and stops at 40% of it, which bounds the Gaussian
    count (hence the CPU step time) and leaves most steps to refine at full size; references of fewer than
    `SPARSE_VIEWS` training views are not densified at all. The background is learned:
    the Gaussians that SfM points initialise never cover a smooth sky. Learning rates keep the 12000-step
    decay (see the module docstring).
    """
    steps = config.max_num_iterations
    config.pipeline.model.resolution_schedule = max(steps // 6, 1)
    config.pipeline.model.warmup_length = min(config.pipeline.model.warmup_length, max(steps // 6, 1))
    config.pipeline.model.stop_split_at = int(0.4 * steps)
    config.pipeline.model.background_color = "learned"
    config.pipeline.model.densify_min_views = SPARSE_VIEWS
    return config


def default_device() -> str:
    """What the machine has: 'cuda' with a CUDA device, else 'cpu' (nerfstudio's own default is always 'cuda')."""
    return "cuda" if torch.cuda.is_available() else "cpu"


def _adam(lr: float, lr_final: float | None = None, **scheduler) -> dict:
    return {
        "optimizer": AdamOptimizerConfig(lr=lr, eps=1e-15),
        "scheduler": ExponentialDecaySchedulerConfig(lr_final=lr_final, max_steps=MAX_STEPS, **scheduler) if lr_final else None,
    }


@dataclass
class FeatureSplatTrainerConfig(TrainerConfig):
    """nerfstudio's TrainerConfig, checking the dataset before the run directory is written (`ns-train` saves config.yml
    before it builds the datamanager)."""

    def save_config(self) -> None:
        if isinstance(self.pipeline.datamanager, FeatureDatamanagerConfig):
            check_dataset(self.pipeline.datamanager)
        super().save_config()


sg_feature_splat_config = FeatureSplatTrainerConfig(
    method_name="sg-feature-splat",
    steps_per_eval_image=100,
    steps_per_eval_batch=0,
    steps_per_save=2000,
    steps_per_eval_all_images=1000,
    max_num_iterations=MAX_STEPS,
    mixed_precision=False,
    machine=MachineConfig(device_type=default_device()),
    pipeline=VanillaPipelineConfig(
        datamanager=FeatureDatamanagerConfig(dataparser=ColmapDataParserConfig(load_3D_points=True)),
        model=FeatureSplatfactoModelConfig(),
    ),
    optimizers={
        "means": _adam(1.6e-4, 1.6e-6),
        "features_dc": _adam(0.0025),
        "features_rest": _adam(0.0025 / 20),
        "opacities": _adam(0.05),
        "scales": _adam(0.005),
        "quats": _adam(0.001),
        "features": _adam(0.05, 1.6e-6),
        "feature_decoder": _adam(1e-3),
        "background": _adam(1e-2),
        "camera_opt": _adam(1e-4, 5e-7, warmup_steps=1000, lr_pre_warmup=0),
        "bilateral_grid": _adam(2e-3, 1e-4, warmup_steps=1000, lr_pre_warmup=0),
    },
    viewer=ViewerConfig(num_rays_per_chunk=1 << 15),
    vis="viewer",
)

sg_feature_splat = MethodSpecification(
    config=sg_feature_splat_config,
    description="Scene Grounding In the Wild reference model: splatfacto with distilled per-Gaussian features (CPU and CUDA).",
)


def _cpu_config() -> TrainerConfig:
    config = copy.deepcopy(sg_feature_splat_config)
    config.method_name = "sg-feature-splat-cpu"
    config.max_num_iterations = CPU_STEPS
    config.steps_per_eval_image = config.steps_per_save = 500
    config.steps_per_eval_all_images = CPU_STEPS
    config.pipeline.datamanager.teacher = TeacherConfig(name="offline", input_size=256)
    return short_cpu_schedule(config)


sg_feature_splat_cpu = MethodSpecification(
    config=_cpu_config(),
    description="sg-feature-splat for a CPU: 3000 steps (sg-demo's schedule), the weight-free offline teacher.",
)
