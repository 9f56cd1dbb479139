"""The frozen reference model: a trained sg-feature-splat loaded from its config, and differentiable
rendering of its features or colours from cameras given in the dataparser frame.

Frames: the checkpoint lives in nerfstudio's *dataparser frame*, x_ns = s_d (A x_world + b) with the
3x4 [A | b] and s_d from `dataparser_transforms.json` beside the config. `world_to_dataparser` is that
similarity; everything the user sees is in the original world frame.

Everything about the Gaussians that does not depend on the camera (3D covariances, activated opacities,
colours, features pre-multiplied by the linear decoder when that is narrower) is computed once at load.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import torch
from torch import Tensor

from sg_nerfstudio.features import TeacherConfig
from sg_nerfstudio.geometry.sim3 import Sim3
from sg_nerfstudio.render import rasterize
from sg_nerfstudio.render.projection import covariances_from_quats_scales
from sg_nerfstudio.splat.trained import load_pipeline, open_trained_run


@dataclass
class ReferenceModel:
    config_path: Path
    checkpoint_path: Path
    model: "torch.nn.Module"
    world_to_dataparser: Sim3
    teacher: TeacherConfig
    means: Tensor
    covars: Tensor  # [N, 3, 3] world (dataparser-frame) covariances, precomputed since the model is frozen
    opacities: Tensor
    gaussian_features: Tensor  # [N, C]: splatted as they are, decoded per Gaussian when that is narrower (the decoder is linear)
    feature_bias: Tensor  # [D] added after rendering when gaussian_features are pre-decoded, else empty
    colors: Tensor  # [N, K, 3] SH coefficients when sh_degree > 0, else [N, 3] RGB
    sh_degree: int
    background: Tensor  # [3] colour where no Gaussian covers the view (the model's eval background)

    @property
    def feature_dim(self) -> int:
        return int(self.model.teacher_feature_dim)

    @property
    def count(self) -> int:
        """N, the Gaussians this (possibly culled) reference renders."""
        return int(self.means.shape[0])

    def subset(self, ids: Tensor) -> "ReferenceModel":
        """The same model restricted to the Gaussians `ids` [M] (int64 or bool mask)."""
        return replace(
            self, means=self.means[ids], covars=self.covars[ids], opacities=self.opacities[ids],
            gaussian_features=self.gaussian_features[ids], colors=self.colors[ids],
        )

    def render_rgb(
        self, viewmats: Tensor, Ks: Tensor, width: int, height: int, near_plane: float, backend: str = "auto", with_depth: bool = False,
    ) -> tuple[Tensor, Tensor]:
        """Colours of C cameras (dataparser frame, OpenCV world-to-camera [C, 4, 4]) with gradients w.r.t. viewmats.

        Returns:
            RGB in [0, 1] over the model's background [C, H, W, 3] (with `with_depth`, [C, H, W, 4]: the expected
            depth, camera z in dataparser units, appended) and alphas [C, H, W, 1].
        """
        rendered, alpha, _ = rasterize(
            self.means, None, None, self.opacities, self.colors, viewmats, Ks, width, height,
            near_plane=near_plane, sh_degree=self.sh_degree if self.sh_degree > 0 else None, backend=backend,
            covars=self.covars, render_mode="RGB+ED" if with_depth else "RGB",
        )
        rgb = (rendered[..., :3] + (1.0 - alpha) * self.background.to(rendered.device)).clamp(0.0, 1.0)
        return (torch.cat([rgb, rendered[..., 3:]], dim=-1) if with_depth else rgb), alpha

    def render_features(
        self, viewmats: Tensor, Ks: Tensor, width: int, height: int, near_plane: float, backend: str = "auto", with_depth: bool = False,
    ) -> tuple[Tensor, Tensor]:
        """Decoded teacher-space features [C, H, W, D] (with `with_depth`, [C, H, W, D + 1]: the expected depth
        appended) and alphas [C, H, W, 1] (as `render_rgb`)."""
        rendered, alpha, _ = rasterize(
            self.means, None, None, self.opacities, self.gaussian_features, viewmats, Ks, width, height,
            near_plane=near_plane, backend=backend, covars=self.covars, render_mode="RGB+ED" if with_depth else "RGB",
        )
        features = rendered[..., :-1] if with_depth else rendered
        if self.feature_bias.numel():
            decoded = features + self.feature_bias
        else:
            decoded = self.model.feature_decoder(features.permute(0, 3, 1, 2)).permute(0, 2, 3, 1)
        return (torch.cat([decoded, rendered[..., -1:]], dim=-1) if with_depth else decoded), alpha


def load_reference(config_path: Path, device: str = "cpu") -> ReferenceModel:
    """Load the trained model read-only: parameters frozen, eval mode, checkpoint untouched."""
    run = open_trained_run(config_path)
    config = run.config
    pipeline, checkpoint_path, _ = load_pipeline(run, device, "inference")
    model = pipeline.model
    for parameter in model.parameters():
        parameter.requires_grad_(False)

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
            config_path=run.config_path,
            checkpoint_path=Path(checkpoint_path),
            model=model,
            world_to_dataparser=run.world_to_dataparser,
            teacher=config.pipeline.datamanager.teacher,
            means=model.means.detach().clone(),
            covars=covariances_from_quats_scales(model.quats, torch.exp(model.scales)).detach().clone(),
            opacities=torch.sigmoid(model.opacities).squeeze(-1).detach().clone(),
            gaussian_features=render_features.detach().clone(),
            feature_bias=bias,
            colors=colors.detach().clone(),
            background=model._get_background_color().detach().cpu().clone(),
            sh_degree=model.config.sh_degree,
        )
    return reference
