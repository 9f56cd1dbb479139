"""Feature-augmented splatfacto: the paper's reference model ("The reference model", supplement).

Every Gaussian carries a learnable feature vector (default 128-d) next to its colour, rendered through
`sg_nerfstudio.render.rasterize` (gsplat on CUDA, the CPU rasterizer otherwise). Colour is rendered at the
training resolution; features at `feature_render_scale` x the teacher grid on the long side (4: the size the
fast-cpu registration renders them at, about 128 px for the offline teacher), in a second rasterization of the
same Gaussians and camera where that is at most half the training resolution, else in the colour's own call
([rgb | features]) at the training resolution, as always with scale 0 (the paper). The rendered feature map
goes through the *speedup decoder* `Conv2d(feature_dim, D_teacher, 1)` and is compared with the teacher map
after a bilinear resize to the teacher grid (antialiased when shrinking, `resize_bilinear`):

    L = L_rgb (splatfacto: (1 - l) L1 + l (1 - SSIM)) + feature_loss_weight * |F_teacher - resize(decoder(F))|_1

Differences from `SplatfactoModel` besides the features: nothing calls `.cuda()`; LPIPS is built only
when its AlexNet weights are already on disk (else skipped with one warning); densification uses plain
means2d gradients on the CPU backend (absgrad needs gsplat's CUDA backward).

Why a separate feature render: the loss only sees the teacher grid (32 cells for the offline teacher), and
compositing 128 channels at 480x320 was most of a CPU training step (0.83 s of which the compositor's forward
and backward 0.45 s and the 128-channel resize 0.1 s, fountain-P11 reference; docs/measurements.md "Training speed").

Viewer outputs: rgb, depth, accumulation, decoded `features` [H, W, D_teacher] (upsampled bilinearly from a
separate feature render) and `feature_pca` [H, W, 3], a projection on a PCA basis fixed at construction from
teacher features and saved in the checkpoint, so colours are stable across views and sessions.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Tuple, Type, Union

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.nn import Parameter

from gsplat.strategy import DefaultStrategy
from nerfstudio.cameras.camera_optimizers import CameraOptimizer
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.model_components.lib_bilagrid import BilateralGrid
from nerfstudio.models.splatfacto import (
    RGB2SH, SplatfactoModel, SplatfactoModelConfig, num_sh_bases, random_quat_tensor,
)
from nerfstudio.utils.colors import get_color
from nerfstudio.utils.rich_utils import CONSOLE
from pytorch_msssim import SSIM

from sg_nerfstudio.features.base import resize_bilinear
from sg_nerfstudio.geometry.frames import viewmats_from_camera_to_worlds
from sg_nerfstudio.render import rasterize, resolve_backend
from sg_nerfstudio.render.spherical_harmonics import evaluate_sh

ALEXNET_WEIGHTS = "alexnet-owt-7be5be79.pth"


@dataclass
class FeatureSplatfactoModelConfig(SplatfactoModelConfig):
    """splatfacto plus per-Gaussian features distilled from a 2D teacher."""

    _target: Type = field(default_factory=lambda: FeatureSplatfactoModel)
    feature_dim: int = 128
    """Length of the feature vector carried by each Gaussian."""
    feature_loss_weight: float = 1.0
    """Weight of the L1 feature loss against splatfacto's colour loss."""
    feature_render_scale: float = 4.0
    """Long side of the rendered feature map as a multiple of the teacher grid, in a rasterization of its own where
    that is at most half the training resolution's long side; otherwise (and with 0, the paper) features render at
    the training resolution, in the colour's rasterization."""
    rasterizer_backend: Literal["auto", "gsplat", "numba", "torch"] = "auto"
    """auto: gsplat's CUDA kernels on CUDA, the pure-PyTorch rasterizer on CPU."""
    densify_grad_thresh_without_absgrad: float = 0.0002
    """Densification gradient threshold where absgrad is unavailable (CPU backend); gsplat's default for
    plain means2d gradients, which are smaller than absgrad's."""
    densify: bool = True
    """Grow (split, duplicate) and prune Gaussians between `warmup_length` and `stop_split_at`, as splatfacto does.
    False keeps the Gaussians the model starts with (the SfM points) for the whole run; the opacity resets still
    happen."""
    densify_min_views: int = 0
    """Densify only when the model trains on at least this many views (0: whatever their number). With few views
    the grown Gaussians fit the training photos, not the views between them: on 6-view real-photo references
    (1500 CPU steps) densification raised training-view PSNR by 2-3 dB, left held-out views where they were and
    made registration worse (README, "Training the reference model"). `short_cpu_schedule` sets 20."""
    background_color: Literal["random", "black", "white", "learned"] = "random"
    """splatfacto's choices plus "learned": one RGB colour optimised with the model, shown wherever no
    Gaussian covers the view (a stand-in for a sky that short CPU runs cannot fill with Gaussians; it raises
    PSNR but lets registration drift towards views of empty space, so it is not the default)."""


class FeatureSplatfactoModel(SplatfactoModel):
    config: FeatureSplatfactoModelConfig

    def populate_modules(self):
        self._populate_gaussians()
        metadata = self.kwargs.get("metadata") or {}
        teacher_dim = int(metadata.get("teacher_feature_dim", 0))
        if teacher_dim <= 0:
            raise ValueError("FeatureSplatfactoModel needs metadata['teacher_feature_dim'] from the FeatureDatamanager.")
        self.teacher_feature_dim = teacher_dim
        self.teacher_grid_size = int(metadata.get("teacher_grid_size", 0))
        """Cells on the long side of the teacher's maps; 0 (unknown) renders features at full resolution."""
        self.feature_decoder = torch.nn.Conv2d(self.config.feature_dim, teacher_dim, kernel_size=1)
        self._init_pca_basis(metadata.get("teacher_feature_sample"), teacher_dim)

        self.camera_optimizer: CameraOptimizer = self.config.camera_optimizer.setup(num_cameras=self.num_train_data, device="cpu")
        from torchmetrics.image import PeakSignalNoiseRatio

        self.psnr = PeakSignalNoiseRatio(data_range=1.0)
        self.ssim = SSIM(data_range=1.0, size_average=True, channel=3)
        self.lpips = _local_lpips()
        self._lpips_warned = False
        self.step = 0
        self.crop_box = None
        if self.config.background_color == "random":
            self.background_color = torch.tensor([0.1490, 0.1647, 0.2157])  # viser's background, as splatfacto
        elif self.config.background_color == "learned":
            self.background_logit = Parameter(torch.zeros(3))
            self.background_color = torch.full((3,), 0.5)
        else:
            self.background_color = get_color(self.config.background_color)
        if self.config.use_bilateral_grid:
            self.bil_grids = BilateralGrid(
                num=self.num_train_data, grid_X=self.config.grid_shape[0], grid_Y=self.config.grid_shape[1], grid_W=self.config.grid_shape[2]
            )
        self.densifies = self.config.densify and self.num_train_data >= self.config.densify_min_views
        """Whether the strategy grows and prunes Gaussians in this run (`densify`, `densify_min_views`)."""
        self.strategy = DefaultStrategy(
            prune_opa=self.config.cull_alpha_thresh,
            grow_grad2d=self.config.densify_grad_thresh,
            grow_scale3d=self.config.densify_size_thresh,
            grow_scale2d=self.config.split_screen_size,
            prune_scale3d=self.config.cull_scale_thresh,
            prune_scale2d=self.config.cull_screen_size,
            refine_scale2d_stop_iter=self.config.stop_screen_size_at,
            # gsplat grows and prunes at steps after refine_start_iter and before refine_stop_iter, and resets
            # opacities before refine_stop_iter: without densification the first never comes, the second still does.
            refine_start_iter=self.config.warmup_length if self.densifies else self.config.stop_split_at,
            refine_stop_iter=self.config.stop_split_at,
            reset_every=self.config.reset_alpha_every * self.config.refine_every,
            refine_every=self.config.refine_every,
            pause_refine_after_reset=self.num_train_data + self.config.refine_every,
            absgrad=self.config.use_absgrad,
            revised_opacity=False,
            verbose=False,
        )
        self.strategy_state = self.strategy.initialize_state(scene_scale=1.0)
        self._strategy_backend: Optional[str] = None

    def _populate_gaussians(self) -> None:
        """splatfacto's initialisation (SfM points or random), device-agnostic, plus zero features."""
        if self.seed_points is not None and not self.config.random_init:
            means = Parameter(self.seed_points[0].float())
        else:
            means = Parameter((torch.rand((self.config.num_random, 3)) - 0.5) * self.config.random_scale)
        distances, _ = self.k_nearest_sklearn(means.data, 3)
        avg_dist = torch.from_numpy(distances).mean(dim=-1, keepdim=True)
        num_points = means.shape[0]
        dim_sh = num_sh_bases(self.config.sh_degree)
        if self.seed_points is not None and not self.config.random_init and self.seed_points[1].shape[0] > 0:
            shs = torch.zeros((num_points, dim_sh, 3))
            rgb = self.seed_points[1].float() / 255
            shs[:, 0, :3] = RGB2SH(rgb) if self.config.sh_degree > 0 else torch.logit(rgb, eps=1e-10)
            features_dc, features_rest = Parameter(shs[:, 0, :]), Parameter(shs[:, 1:, :])
        else:
            features_dc = Parameter(torch.rand(num_points, 3))
            features_rest = Parameter(torch.zeros((num_points, dim_sh - 1, 3)))
        self.gauss_params = torch.nn.ParameterDict({
            "means": means,
            "scales": Parameter(torch.log(avg_dist.repeat(1, 3))),
            "quats": Parameter(random_quat_tensor(num_points)),
            "features_dc": features_dc,
            "features_rest": features_rest,
            "opacities": Parameter(torch.logit(0.1 * torch.ones(num_points, 1))),
            "features": Parameter(torch.zeros(num_points, self.config.feature_dim)),
        })

    def _init_pca_basis(self, sample: Optional[Tensor], dim: int) -> None:
        """Fixed 3-component PCA of teacher features (from the datamanager's sample; loaded from the
        checkpoint otherwise). Component signs are fixed so the largest loading is positive."""
        mean, components = torch.zeros(dim), torch.eye(dim, 3)
        low, high = -torch.ones(3), torch.ones(3)
        if sample is not None and sample.shape[0] >= 3:
            sample = sample.double()
            mean = sample.mean(0)
            centred = sample - mean
            _, vectors = torch.linalg.eigh(centred.T @ centred / centred.shape[0])
            components = vectors[:, -3:].flip(1)  # largest eigenvalue first
            signs = torch.sign(components.gather(0, components.abs().argmax(0, keepdim=True)))
            components = components * signs
            projected = centred @ components
            low, high = torch.quantile(projected, 0.01, dim=0), torch.quantile(projected, 0.99, dim=0)
        self.register_buffer("pca_mean", mean.float())
        self.register_buffer("pca_components", components.float())
        self.register_buffer("pca_low", low.float())
        self.register_buffer("pca_high", high.float())

    @property
    def features(self) -> Tensor:
        return self.gauss_params["features"]

    def get_gaussian_param_groups(self) -> Dict[str, List[Parameter]]:
        groups = super().get_gaussian_param_groups()
        groups["features"] = [self.gauss_params["features"]]
        return groups

    def get_training_callbacks(self, training_callback_attributes):
        """splatfacto's callbacks; says when the views are too few to densify (at training only, not at every load)."""
        if self.config.densify and not self.densifies:
            CONSOLE.print(
                f"[yellow]{self.num_train_data} training views (< densify_min_views {self.config.densify_min_views}): "
                "the Gaussians stay those the model starts with (no densification).[/yellow]"
            )
        return super().get_training_callbacks(training_callback_attributes)

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        groups = super().get_param_groups()
        groups["feature_decoder"] = list(self.feature_decoder.parameters())
        if self.config.background_color == "learned":
            groups["background"] = [self.background_logit]
        return groups

    def _get_background_color(self) -> Tensor:
        if self.config.background_color == "learned":
            return torch.sigmoid(self.background_logit)
        return super()._get_background_color()

    def _configure_strategy(self, backend: str) -> None:
        """Densify on plain gradients when absgrad is unavailable (CPU backend); once per backend."""
        if backend == self._strategy_backend:
            return
        self._strategy_backend = backend
        if backend != "gsplat" and self.strategy.absgrad:
            self.strategy.absgrad = False
            self.strategy.grow_grad2d = self.config.densify_grad_thresh_without_absgrad
            if self.densifies:
                CONSOLE.print(
                    "[yellow]CPU rasterizer: densifying on means2d gradients (threshold "
                    f"{self.config.densify_grad_thresh_without_absgrad}) since absgrad needs gsplat's CUDA backward.[/yellow]"
                )

    def get_outputs(self, camera: Cameras) -> Dict[str, Union[Tensor, List]]:
        """Render rgb, depth, accumulation and the raw feature map `feature_render` [H, W, feature_dim]."""
        if not isinstance(camera, Cameras):
            return {}
        if self.training:
            assert camera.shape[0] == 1, "Only one camera at a time"
            camera_to_world = self.camera_optimizer.apply_to_camera(camera)
        else:
            camera_to_world = camera.camera_to_worlds
        params = {name: value for name, value in self.gauss_params.items()}
        if self.crop_box is not None and not self.training:
            inside = self.crop_box.within(self.means).squeeze()
            if inside.sum() == 0:
                return self.get_empty_outputs(int(camera.width.item()), int(camera.height.item()), self._get_background_color().detach())
            params = {name: value[inside] for name, value in params.items()}

        scale = self._get_downscale_factor()
        camera.rescale_output_resolution(1 / scale)
        viewmat = viewmats_from_camera_to_worlds(camera_to_world)
        K = camera.get_intrinsics_matrices().to(self.device)
        width, height = int(camera.width.item()), int(camera.height.item())
        self.last_size = (height, width)
        camera.rescale_output_resolution(scale)

        backend = resolve_backend(self.config.rasterizer_backend, self.device)
        self._configure_strategy(backend)
        render_depth = self.config.output_depth_during_training or not self.training
        feature_size = self.feature_render_size(width, height)
        colors = self._view_colors(params, camera_to_world[0, :3, 3])
        if feature_size is None:
            colors = torch.cat([colors, params["features"]], dim=1)
        render, alpha, self.info = self._rasterize(
            params, colors, viewmat, K, (width, height), backend,
            render_mode="RGB+ED" if render_depth else "RGB", absgrad=self.strategy.absgrad and backend == "gsplat",
        )
        if feature_size is None:
            feature_render = render[0, ..., 3 : 3 + self.config.feature_dim]
        else:
            feature_render = self._render_features(params, viewmat, K, (width, height), feature_size, backend)
        if self.training:
            self.strategy.step_pre_backward(self.gauss_params, self.optimizers, self.strategy_state, self.step, self.info)

        background = self._get_background_color()
        rgb = torch.clamp(render[..., :3] + (1 - alpha) * background, 0.0, 1.0)
        if self.config.use_bilateral_grid and self.training and camera.metadata is not None and "cam_idx" in camera.metadata:
            rgb = self._apply_bilateral_grid(rgb, camera.metadata["cam_idx"], height, width)
        depth = None
        if render_depth:
            depth = render[..., -1:]
            depth = torch.where(alpha > 0, depth, depth.detach().max()).squeeze(0)
        if background.shape[0] == 3 and not self.training:
            background = background.expand(height, width, 3)
        return {
            "rgb": rgb.squeeze(0),
            "depth": depth,
            "accumulation": alpha.squeeze(0),
            "background": background,
            "feature_render": feature_render,
        }

    def feature_render_size(self, width: int, height: int) -> Optional[Tuple[int, int]]:
        """(width, height) of the feature render for a training image of this size, or None when the features
        are rendered with the colour at (width, height): scale 0, unknown teacher grid, or a long side above half
        the image's (a second rasterization projects every Gaussian again, which costs more than it saves there:
        on the demo's 160x120 images and 46k Gaussians a 128 px feature render made a CPU step 0.26 s, not 0.19 s)."""
        long_side = round(self.config.feature_render_scale * self.teacher_grid_size)
        if long_side <= 0 or 2 * long_side > max(width, height):
            return None
        factor = long_side / max(width, height)
        return max(1, round(width * factor)), max(1, round(height * factor))

    def _rasterize(self, params, colors: Tensor, viewmat: Tensor, K: Tensor, size: Tuple[int, int], backend: str, **options):
        """`rasterize` of the (cropped) Gaussians with these [N, D] colours for one camera at size (width, height)."""
        return rasterize(
            means=params["means"], quats=params["quats"], scales=torch.exp(params["scales"]),
            opacities=torch.sigmoid(params["opacities"]).squeeze(-1), colors=colors, viewmats=viewmat, Ks=K,
            width=size[0], height=size[1], near_plane=0.01, far_plane=1e10,
            rasterize_mode=self.config.rasterize_mode, backend=backend, **options,
        )

    def _render_features(self, params, viewmat: Tensor, K: Tensor, size: Tuple[int, int], feature_size: Tuple[int, int], backend: str) -> Tensor:
        """[h, w, feature_dim] feature map at feature_size (w, h) of the camera whose intrinsics K [1, 3, 3] are
        for size (width, height); outside the training loop upsampled to (height, width) for the viewer."""
        scaled = K.clone()
        scaled[:, 0, :] *= feature_size[0] / size[0]
        scaled[:, 1, :] *= feature_size[1] / size[1]
        render, _, _ = self._rasterize(params, params["features"], viewmat, scaled, feature_size, backend, render_mode="RGB")
        if self.training:
            return render[0]
        return resize_bilinear(render[0].permute(2, 0, 1)[None], (size[1], size[0]))[0].permute(1, 2, 0)

    def _view_colors(self, params: Dict[str, Tensor], camera_centre: Tensor) -> Tensor:
        """[N, 3] colours for one view: SH up to the current degree, or sigmoid colours when sh_degree = 0."""
        if self.config.sh_degree == 0:
            return torch.sigmoid(params["features_dc"])
        degree = min(self.step // self.config.sh_degree_interval, self.config.sh_degree)
        shs = torch.cat([params["features_dc"][:, None, :], params["features_rest"]], dim=1)
        return torch.clamp_min(evaluate_sh(degree, params["means"] - camera_centre, shs) + 0.5, 0.0)

    def decode_features(self, feature_render: Tensor, size: Optional[Tuple[int, int]] = None) -> Tensor:
        """Speedup decoder, optionally after the resize to `size` (`resize_bilinear`; the two commute: both linear).

        Args:
            feature_render: [H, W, feature_dim] rendered Gaussian features.
            size: (height, width) of the output, e.g. the teacher grid; None keeps H x W.

        Returns:
            [h, w, D_teacher] decoded features.
        """
        maps = feature_render.permute(2, 0, 1)[None]
        if size is not None:
            maps = resize_bilinear(maps, size)
        return self.feature_decoder(maps)[0].permute(1, 2, 0)

    def feature_pca(self, features: Tensor) -> Tensor:
        """[H, W, D_teacher] decoded features -> [H, W, 3] colours on the fixed PCA basis."""
        projected = (features - self.pca_mean) @ self.pca_components
        return ((projected - self.pca_low) / (self.pca_high - self.pca_low).clamp(min=1e-6)).clamp(0.0, 1.0)

    def _teacher_grid_prediction(self, outputs: Dict, batch: Dict) -> Tuple[Tensor, Tensor]:
        teacher = batch["teacher_features"].to(self.device)
        if "features_on_teacher_grid" not in outputs:
            outputs["features_on_teacher_grid"] = self.decode_features(outputs["feature_render"], tuple(teacher.shape[:2]))
        return outputs["features_on_teacher_grid"], teacher

    def get_metrics_dict(self, outputs, batch) -> Dict[str, Tensor]:
        metrics = super().get_metrics_dict(outputs, batch)
        if "teacher_features" in batch:
            predicted, teacher = self._teacher_grid_prediction(outputs, batch)
            metrics["feature_cosine"] = F.cosine_similarity(predicted.detach(), teacher, dim=-1).mean()
        return metrics

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, Tensor]:
        losses = super().get_loss_dict(outputs, batch, metrics_dict)
        if "teacher_features" in batch:
            predicted, teacher = self._teacher_grid_prediction(outputs, batch)
            losses["feature_loss"] = self.config.feature_loss_weight * torch.abs(teacher - predicted).mean()
        return losses

    @torch.no_grad()
    def get_outputs_for_camera(self, camera: Cameras, obb_box=None) -> Dict[str, Tensor]:
        """Viewer / eval outputs: the raw feature map is replaced by decoded `features` and `feature_pca`."""
        outputs = super().get_outputs_for_camera(camera, obb_box)
        if "feature_render" in outputs:
            features = self.decode_features(outputs.pop("feature_render"))
            outputs["features"] = features
            outputs["feature_pca"] = self.feature_pca(features)
        return outputs

    def get_image_metrics_and_images(self, outputs, batch) -> Tuple[Dict[str, float], Dict[str, Tensor]]:
        gt_rgb = self.composite_with_background(self.get_gt_img(batch["image"]), outputs["background"])
        predicted_rgb = outputs["rgb"]
        gt, pred = torch.moveaxis(gt_rgb, -1, 0)[None], torch.moveaxis(predicted_rgb, -1, 0)[None]
        metrics = {"psnr": float(self.psnr(gt, pred).item()), "ssim": float(self.ssim(gt, pred))}
        if self.lpips is not None:
            metrics["lpips"] = float(self.lpips(gt, pred))
        elif not self._lpips_warned:  # said where the metric is missing (evaluation), not on every model load
            CONSOLE.print(f"[yellow]LPIPS left out of the metrics: its AlexNet weights are not at {_lpips_weights()} and cannot be downloaded here.[/yellow]")
            self._lpips_warned = True
        images = {"img": torch.cat([gt_rgb, predicted_rgb], dim=1)}
        if "teacher_features" in batch and "features" in outputs:
            teacher = batch["teacher_features"].to(self.device)
            on_grid = resize_bilinear(outputs["features"].permute(2, 0, 1)[None], tuple(teacher.shape[:2]))
            metrics["feature_cosine"] = float(F.cosine_similarity(on_grid[0].permute(1, 2, 0), teacher, dim=-1).mean())
            images["feature_pca"] = outputs["feature_pca"]
        return metrics, images


def _lpips_weights() -> Path:
    """Where torchmetrics' LPIPS looks for AlexNet's weights (the torch-hub cache)."""
    return Path(torch.hub.get_dir()) / "checkpoints" / ALEXNET_WEIGHTS


def _local_lpips():
    """torchmetrics' LPIPS when AlexNet's weights are already in the torch-hub cache, else None (the first evaluation
    says so: loading a model to register against it needs no LPIPS and prints nothing about it)."""
    if not _lpips_weights().is_file():
        return None
    from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

    return LearnedPerceptualImagePatchSimilarity(normalize=True)
