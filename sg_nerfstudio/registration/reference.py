"""The frozen reference model: a trained sg-feature-splat loaded from its config, and differentiable
rendering of its features (or colours) from cameras given in the dataparser frame.

Frames: the checkpoint lives in nerfstudio's *dataparser frame*, x_ns = s_d (A x_world + b) with the
3x4 [A | b] and s_d from `dataparser_transforms.json` beside the config. `world_to_dataparser` is that
similarity as a 4x4 matrix; everything the user sees is in the original world frame.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import yaml
from torch import Tensor

from sg_nerfstudio.errors import InputError
from sg_nerfstudio.features import TeacherConfig
from sg_nerfstudio.features.base import resize_bilinear
from sg_nerfstudio.render import rasterize
from sg_nerfstudio.render.projection import covariances_from_quats_scales

Array = np.ndarray


class ReferenceModelError(InputError):
    """A --load-config that does not give a usable sg-feature-splat model."""


@dataclass
class ReferenceModel:
    config_path: Path
    checkpoint_path: Path
    model: "torch.nn.Module"
    world_to_dataparser: Array  # [4, 4] Sim(3)
    teacher: TeacherConfig
    means: Tensor
    covars: Tensor  # [N, 3, 3] world (dataparser-frame) covariances, precomputed since the model is frozen
    opacities: Tensor
    render_features: Tensor  # [N, C]: decoded per Gaussian when that is narrower (the decoder is linear)
    feature_bias: Tensor  # [D] added after rendering when render_features are pre-decoded, else empty
    colors: Tensor  # [N, K, 3] SH coefficients when sh_degree > 0, else [N, 3] RGB
    sh_degree: int
    background: Tensor  # [3] colour where no Gaussian covers the view (the model's eval background)

    @property
    def feature_dim(self) -> int:
        return int(self.model.teacher_feature_dim)

    def render(
        self, viewmats: Tensor, Ks: Tensor, width: int, height: int, near_plane: float,
        objective: Literal["features", "photometric"], backend: str = "auto",
    ) -> tuple[Tensor, Tensor]:
        """Render C cameras (dataparser frame, OpenCV world-to-camera) with gradients w.r.t. viewmats.

        Returns:
            maps [C, H, W, D] (decoded teacher-space features, or RGB in [0, 1]) and alphas [C, H, W, 1].
        """
        if objective == "photometric":
            rgb, alpha, _ = rasterize(
                self.means, None, None, self.opacities, self.colors, viewmats, Ks, width, height,
                near_plane=near_plane, sh_degree=self.sh_degree if self.sh_degree > 0 else None, backend=backend,
                covars=self.covars,
            )
            return (rgb + (1.0 - alpha) * self.background).clamp(0.0, 1.0), alpha
        rendered, alpha, _ = rasterize(
            self.means, None, None, self.opacities, self.render_features, viewmats, Ks, width, height,
            near_plane=near_plane, backend=backend, covars=self.covars,
        )
        if self.feature_bias.numel():
            return rendered + self.feature_bias, alpha
        decoded = self.model.feature_decoder(rendered.permute(0, 3, 1, 2))
        return decoded.permute(0, 2, 3, 1), alpha


def read_trainer_config(config_path: Path):
    config_path = Path(config_path)
    if not config_path.is_file():
        raise ReferenceModelError(f"Config {config_path} does not exist; expected the config.yml of a trained sg-feature-splat.")
    try:
        config = yaml.load(config_path.read_text(), Loader=yaml.Loader)
    except Exception as error:
        raise ReferenceModelError(f"Config {config_path} is not a readable nerfstudio config ({type(error).__name__}).") from None
    from nerfstudio.engine.trainer import TrainerConfig

    from sg_nerfstudio.model import FeatureSplatfactoModelConfig

    if not isinstance(config, TrainerConfig):
        raise ReferenceModelError(f"Config {config_path} is not a nerfstudio training config.")
    if not isinstance(config.pipeline.model, FeatureSplatfactoModelConfig):
        raise ReferenceModelError(
            f"Config {config_path} is a '{config.method_name}' model; expected an sg-feature-splat model "
            "(train one with `ns-train sg-feature-splat`)."
        )
    return config


def load_reference(config_path: Path, device: str = "cpu") -> ReferenceModel:
    """Load the trained model read-only: parameters frozen, eval mode, checkpoint untouched."""
    from nerfstudio.utils.eval_utils import eval_load_checkpoint

    config_path = Path(config_path)
    config = read_trainer_config(config_path)
    transforms_path = config_path.parent / "dataparser_transforms.json"
    if not transforms_path.is_file():
        raise ReferenceModelError(f"{transforms_path} is missing; it is written by ns-train next to config.yml.")
    data = Path(config.pipeline.datamanager.data or config.pipeline.datamanager.dataparser.data)
    if not data.exists():
        raise ReferenceModelError(
            f"The reference dataset {data} named in {config_path} was not found (nerfstudio needs it to rebuild the "
            "model); run from the directory you trained in or fix `data:` in the config."
        )
    config.load_dir = config_path.parent / config.relative_model_dir
    checkpoints = sorted(config.load_dir.glob("step-*.ckpt")) if config.load_dir.is_dir() else []
    if not checkpoints:
        raise ReferenceModelError(f"No checkpoint (step-*.ckpt) in {config.load_dir}.")
    pipeline = config.pipeline.setup(device=device, test_mode="inference")
    pipeline.eval()
    checkpoint_path, _ = eval_load_checkpoint(config, pipeline)
    model = pipeline.model
    for parameter in model.parameters():
        parameter.requires_grad_(False)

    record = json.loads(transforms_path.read_text())
    world_to_dataparser = np.eye(4)
    world_to_dataparser[:3, :4] = float(record["scale"]) * np.asarray(record["transform"], dtype=np.float64)

    with torch.no_grad():
        features = model.gauss_params["features"]
        weight = model.feature_decoder.weight[:, :, 0, 0]  # [D, F]
        if weight.shape[0] < weight.shape[1]:
            render_features, bias = features @ weight.T, model.feature_decoder.bias.clone()
        else:
            render_features, bias = features, torch.zeros(0)
        if model.config.sh_degree > 0:
            colors = torch.cat([model.gauss_params["features_dc"][:, None, :], model.gauss_params["features_rest"]], dim=1)
        else:
            colors = torch.sigmoid(model.gauss_params["features_dc"])
        reference = ReferenceModel(
            config_path=config_path,
            checkpoint_path=Path(checkpoint_path),
            model=model,
            world_to_dataparser=world_to_dataparser,
            teacher=config.pipeline.datamanager.teacher,
            means=model.means.detach().clone(),
            covars=covariances_from_quats_scales(model.quats, torch.exp(model.scales)).detach().clone(),
            opacities=torch.sigmoid(model.opacities).squeeze(-1).detach().clone(),
            render_features=render_features.detach().clone(),
            feature_bias=bias,
            colors=colors.detach().clone(),
            background=model._get_background_color().detach().cpu().clone(),
            sh_degree=model.config.sh_degree,
        )
    return reference


def resize_to(maps: Tensor, size: tuple[int, int]) -> Tensor:
    """[C, H, W, D] -> [C, h, w, D] on the teacher grid, exactly as in training (`resize_bilinear`)."""
    return resize_bilinear(maps.permute(0, 3, 1, 2), size).permute(0, 2, 3, 1)
