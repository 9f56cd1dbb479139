"""A trained sg-feature-splat on disk: its config.yml, checkpoint and dataparser frame, checked.

    <run>/config.yml                    nerfstudio's TrainerConfig (ours: an sg-feature-splat model)
    <run>/dataparser_transforms.json    reference world -> dataparser frame, x_ns = s (A x + b)
    <run>/nerfstudio_models/step-*.ckpt

Registration, the initialisers and the viewer read trained models only through here, so a wrong
`--load-config` gives the same sentence in every command.
"""

from __future__ import annotations

import dataclasses
import enum
import importlib
import json
import math
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
        text = config_path.read_text()
        refused = first_untrusted_tag(text)
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as error:
        raise ReferenceModelError(f"Config {config_path} is not a readable nerfstudio config ({type(error).__name__}).") from None
    if refused:
        raise ReferenceModelError(
            f"Config {config_path} holds the YAML tag {refused}, which no config of a trained sg-feature-splat holds; refused "
            "before building anything (a YAML config can run code)."
        )
    try:
        config = yaml.load(text, Loader=yaml.UnsafeLoader)  # every tag checked above: only configuration classes, paths, enums
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


TRUSTED_MODULES = ("nerfstudio.", "sg_nerfstudio.")
"""Modules whose configuration classes, enums and classes a trained config may name (nerfstudio's and this package's)."""
TRUSTED_NAMES = ("torch.optim.",)
"""Further modules whose classes a config may name by `!!python/name:` (the optimisers of nerfstudio's configs)."""
PATH_CLASSES = {"pathlib.Path", "pathlib.PosixPath", "pathlib.WindowsPath", "pathlib.PurePath", "pathlib.PurePosixPath", "pathlib.PureWindowsPath"}
PLAIN_TAGS = {f"tag:yaml.org,2002:{kind}" for kind in ("str", "int", "float", "bool", "null", "seq", "map", "python/tuple")}


def first_untrusted_tag(text: str) -> Optional[str]:
    """The first YAML tag of a config that could build anything but a configuration of ours (None when every tag is
    trusted), read from the composed node graph, so that nothing is constructed or imported from an untrusted name.

    nerfstudio writes a trained run's config.yml with PyYAML's Python tags, and its loader builds whatever a tag names
    (`!!python/object/apply:os.system [...]` runs a command). Trusted here: plain YAML values and tuples;
    `!!python/object:` of a dataclass from TRUSTED_MODULES (nerfstudio's and our configs); `!!python/object/apply:` of a
    pathlib path or an Enum from TRUSTED_MODULES; `!!python/name:` of a class from TRUSTED_MODULES or TRUSTED_NAMES."""
    root = yaml.compose(text, Loader=yaml.SafeLoader)
    seen, stack = set(), [root] if root is not None else []
    while stack:
        node = stack.pop()
        if id(node) in seen:
            continue
        seen.add(id(node))
        if not trusted_tag(node.tag):
            return node.tag.replace("tag:yaml.org,2002:", "!!")
        if isinstance(node, yaml.SequenceNode):
            stack.extend(node.value)
        elif isinstance(node, yaml.MappingNode):
            stack.extend(item for pair in node.value for item in pair)
    return None


def trusted_tag(tag: str) -> bool:
    """Whether a YAML tag builds only a configuration value (see `first_untrusted_tag`)."""
    if tag in PLAIN_TAGS:
        return True
    prefix = "tag:yaml.org,2002:python/"
    for kind, test in (("object/apply:", is_path_or_enum), ("object:", dataclasses.is_dataclass), ("name:", lambda _: True)):
        if tag.startswith(prefix + kind):
            name = tag[len(prefix + kind):]
            if kind == "object/apply:" and name in PATH_CLASSES:
                return True
            target = resolve_trusted_name(name, TRUSTED_MODULES + (TRUSTED_NAMES if kind == "name:" else ()))
            return isinstance(target, type) and bool(test(target))
    return False


def is_path_or_enum(target: type) -> bool:
    """What `!!python/object/apply:` may call: an Enum class (a path is recognised by name before any import)."""
    return issubclass(target, enum.Enum)


def resolve_trusted_name(name: str, modules: tuple[str, ...]) -> Optional[object]:
    """The object `module.attribute` names when its module starts with one of `modules` (imported only then), else None."""
    module, _, attribute = name.rpartition(".")
    if not module or not any(f"{module}.".startswith(prefix) for prefix in modules):
        return None
    try:
        return getattr(importlib.import_module(module), attribute, None)
    except ImportError:
        return None


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


def trained_run_inputs(config_path: Path) -> list[Path]:
    """Everything a command reads through a trained run's config.yml, for the rule that an output never replaces or
    holds an input (`atomic.check_apart_from_inputs`): the config, its checkpoint directory and dataparser transforms,
    the dataset it was trained on (images and COLMAP model) and the teacher's feature cache. ReferenceModelError for a
    config that is not one (`read_trainer_config`)."""
    from sg_nerfstudio.features.cache import default_cache_dir

    config_path = Path(config_path)
    config = read_trainer_config(config_path)
    datamanager = config.pipeline.datamanager
    data = datamanager.data or datamanager.dataparser.data
    teacher = getattr(datamanager, "teacher", None)
    cache = getattr(teacher, "cache_dir", None) or default_cache_dir()
    run = config_path.parent
    return [config_path, run / config.relative_model_dir, run / "dataparser_transforms.json", *([Path(data)] if data else []), Path(cache)]


def read_world_to_dataparser(config_path: Path) -> Sim3:
    """Reference world -> dataparser frame, x_ns = s (A x + b), from dataparser_transforms.json beside the config."""
    path = Path(config_path).parent / "dataparser_transforms.json"
    if not path.is_file():
        raise ReferenceModelError(f"{path} is missing; it is written by ns-train next to config.yml.")
    try:
        record = json.loads(path.read_text())
        scale, transform = float(record["scale"]), np.asarray(record["transform"], dtype=np.float64)
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as error:
        raise ReferenceModelError(
            f"{path} is not readable ({type(error).__name__}); expected the JSON ns-train writes, with a 'transform' (3 x 4) and a 'scale'."
        ) from None
    if transform.shape != (3, 4) or not np.isfinite(transform).all() or not math.isfinite(scale) or scale <= 0:
        raise ReferenceModelError(f"{path} holds no usable frame; expected a finite 3 x 4 'transform' and a positive 'scale'.")
    matrix = np.eye(4)
    matrix[:3, :4] = scale * transform
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
    pipeline = run.config.pipeline.setup(device=device, test_mode=test_mode)
    pipeline.eval()
    checkpoint_path = run.checkpoints[-1]  # step-%09d.ckpt: the latest sorts last
    state = read_checkpoint(checkpoint_path)
    try:
        pipeline.load_pipeline(state["pipeline"], state["step"])
    except (RuntimeError, KeyError, ValueError) as error:  # torch's size mismatches and missing keys
        raise ReferenceModelError(
            f"Checkpoint {checkpoint_path} does not fit the model its config.yml describes ({type(error).__name__}); expected the "
            "checkpoint ns-train wrote beside that config."
        ) from None
    check_finite_gaussians(pipeline.model, checkpoint_path)
    return pipeline, checkpoint_path, int(state["step"])


def read_checkpoint(path: Path) -> dict:
    """A nerfstudio checkpoint read with torch's weights-only unpickler (tensors and plain containers, no code), checked
    to hold a pipeline state and a step; ReferenceModelError for a truncated, foreign or code-carrying file."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # truncated zip (RuntimeError), a pickle that names code (UnpicklingError), not a file ...
        raise ReferenceModelError(
            f"Checkpoint {path} could not be read as a nerfstudio checkpoint ({type(error).__name__}: truncated, or not written "
            "by ns-train); expected the step-*.ckpt ns-train writes."
        ) from None
    if not isinstance(state, dict) or not isinstance(state.get("pipeline"), dict) or not isinstance(state.get("step"), int):
        keys = sorted(map(str, state))[:6] if isinstance(state, dict) else type(state).__name__
        raise ReferenceModelError(f"Checkpoint {path} holds {keys}, not a nerfstudio checkpoint (its 'pipeline' state and 'step').")
    return state


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
