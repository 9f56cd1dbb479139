"""A trained sg-feature-splat on disk: its config.yml, checkpoint and dataparser frame, checked.

    <run>/config.yml                    nerfstudio's TrainerConfig (ours: an sg-feature-splat model)
    <run>/dataparser_transforms.json    reference world -> dataparser frame, x_ns = s (A x + b)
    <run>/nerfstudio_models/step-*.ckpt

Registration, the initialisers and the viewer read trained models only through here, so a wrong
`--load-config` gives the same sentence in every command.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import torch
import yaml

from sg_nerfstudio.errors import InputError
from sg_nerfstudio.geometry.sim3 import Sim3


class ReferenceModelError(InputError):
    """A --load-config that does not give a usable sg-feature-splat model."""


@dataclass
class TrainedRun:
    """The checked files of a trained sg-feature-splat.

    Attributes:
        config: nerfstudio TrainerConfig read from config.yml.
        config_path: that config.yml.
        checkpoints: step-*.ckpt files, sorted.
        world_to_dataparser: reference world -> nerfstudio's dataparser frame.
    """

    config: object
    config_path: Path
    checkpoints: list[Path]
    world_to_dataparser: Sim3


def read_trainer_config(config_path: Path):
    """The TrainerConfig of an sg-feature-splat model at `config_path` (ReferenceModelError otherwise)."""
    config_path = Path(config_path)
    if config_path.is_dir():
        inside = config_path / "config.yml"
        hint = f" (this one has {inside})" if inside.is_file() else ""
        raise ReferenceModelError(f"Config {config_path} is a directory; expected the config.yml of a trained sg-feature-splat{hint}.")
    if not config_path.is_file():
        raise ReferenceModelError(f"Config {config_path} does not exist; expected the config.yml of a trained sg-feature-splat.")
    try:
        config = yaml.load(config_path.read_text(), Loader=yaml.Loader)
    except Exception as error:
        raise ReferenceModelError(f"Config {config_path} is not a readable nerfstudio config ({type(error).__name__}).") from None
    from nerfstudio.engine.trainer import TrainerConfig

    from sg_nerfstudio.splat.model import FeatureSplatfactoModelConfig

    if not isinstance(config, TrainerConfig):
        raise ReferenceModelError(f"Config {config_path} is not a nerfstudio training config.")
    if not isinstance(config.pipeline.model, FeatureSplatfactoModelConfig):
        raise ReferenceModelError(
            f"Config {config_path} is a '{config.method_name}' model; expected an sg-feature-splat model "
            "(train one with `ns-train sg-feature-splat`)."
        )
    resolve_relative_paths(config, config_path)
    return config


def training_directory(config, config_path: Path) -> Optional[Path]:
    """The directory `ns-train` ran in, when the config's run directory (output_dir / experiment / method / timestamp)
    is relative and `config_path` lies in it; None otherwise. nerfstudio stores the paths it was given, so a run
    trained with `--data scenes/x` in /work names `scenes/x`, which only /work can resolve."""
    base = Path(config.get_base_dir())
    run_dir = Path(config_path).resolve().parent
    if base.is_absolute() or len(base.parts) >= len(run_dir.parts) or run_dir.parts[-len(base.parts):] != base.parts:
        return None
    return Path(*run_dir.parts[: -len(base.parts)])


def resolve_relative_paths(config, config_path: Path) -> None:
    """Make a relative dataset path of `config` (datamanager and dataparser `data`) absolute when it does not exist
    from the current directory but does from the directory the run was trained in (`training_directory`): a trained
    reference, an sg-bench results folder, is then usable from anywhere. Paths that resolve from here are left as
    they are. A relative teacher feature cache (sg-bench's) is taken from the training directory likewise, so that
    loading the model elsewhere neither misses it nor creates a copy under the current directory."""
    origin = training_directory(config, config_path)
    if origin is None:
        return
    datamanager = config.pipeline.datamanager
    for holder in (datamanager, datamanager.dataparser):
        data = getattr(holder, "data", None)
        if data is not None and not Path(data).is_absolute() and not Path(data).exists() and (origin / data).exists():
            holder.data = origin / data
    teacher = getattr(datamanager, "teacher", None)
    cache = getattr(teacher, "cache_dir", None)
    if cache is not None and not Path(cache).is_absolute() and not Path(cache).exists() and (origin / cache).exists():
        teacher.cache_dir = origin / cache


def read_world_to_dataparser(config_path: Path) -> Sim3:
    """Reference world -> dataparser frame, x_ns = s (A x + b), from dataparser_transforms.json beside the config."""
    path = Path(config_path).parent / "dataparser_transforms.json"
    if not path.is_file():
        raise ReferenceModelError(f"{path} is missing; it is written by ns-train next to config.yml.")
    record = json.loads(path.read_text())
    matrix = np.eye(4)
    matrix[:3, :4] = float(record["scale"]) * np.asarray(record["transform"], dtype=np.float64)
    return Sim3(matrix)


def open_trained_run(config_path: Path) -> TrainedRun:
    """Check everything nerfstudio needs to rebuild the model (config, dataset, frame, checkpoint)."""
    config_path = Path(config_path)
    config = read_trainer_config(config_path)
    world_to_dataparser = read_world_to_dataparser(config_path)
    data = Path(config.pipeline.datamanager.data or config.pipeline.datamanager.dataparser.data)
    if not data.exists():
        raise ReferenceModelError(
            f"The reference dataset {data} named in {config_path} was not found (nerfstudio needs it to rebuild the "
            "model); run from the directory you trained in or fix `data:` in the config."
        )
    model_dir = config_path.parent / config.relative_model_dir
    checkpoints = sorted(model_dir.glob("step-*.ckpt")) if model_dir.is_dir() else []
    if not checkpoints:
        raise ReferenceModelError(f"No checkpoint (step-*.ckpt) in {model_dir}.")
    config.load_dir = model_dir
    return TrainedRun(config, config_path, checkpoints, world_to_dataparser)


def load_pipeline(run: TrainedRun, device: str, test_mode: str):
    """(pipeline in eval mode, checkpoint path, step) of a checked run, as nerfstudio's `eval_setup` builds them but from
    `run.config`: its dataset path resolved (`resolve_relative_paths`) and its checkpoint directory beside config.yml,
    where `eval_setup` would re-read config.yml and look for both relative to the current directory."""
    from nerfstudio.utils.eval_utils import eval_load_checkpoint

    pipeline = run.config.pipeline.setup(device=device, test_mode=test_mode)
    pipeline.eval()
    checkpoint_path, step = eval_load_checkpoint(run.config, pipeline)
    check_finite_gaussians(pipeline.model, Path(checkpoint_path))
    return pipeline, Path(checkpoint_path), step


def check_finite_gaussians(model, checkpoint_path: Path) -> None:
    """ReferenceModelError when a Gaussian parameter of the loaded model is NaN or infinite (a training that diverged):
    the CPU rasterizer would silently drop such Gaussians and gsplat's CUDA kernels may not."""
    for name, parameter in model.gauss_params.items():
        finite = torch.isfinite(parameter.detach()).reshape(parameter.shape[0], -1).all(dim=1)
        if not bool(finite.all()):
            raise ReferenceModelError(
                f"Checkpoint {checkpoint_path} holds {int((~finite).sum())} of {parameter.shape[0]} Gaussians whose {name} are "
                "not finite (NaN or infinite); expected a model whose training did not diverge (train it again)."
            )
