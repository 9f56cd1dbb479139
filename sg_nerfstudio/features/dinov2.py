"""DINOv2 ViT-S/14 patch tokens (384-d), the paper's teacher, with weights from local files only.

The architecture is `transformers.Dinov2Model` configured as ViT-S/14 (12 blocks, 6 heads, 384-d,
LayerScale); the output is the final-LayerNorm patch tokens, i.e. facebookresearch/dinov2's
`x_norm_patchtokens`. Weights cannot be downloaded here, so they come from, in order:

1. `TeacherConfig.weights`: a torch-hub checkpoint (`dinov2_vits14_pretrain.pth`), a Hugging Face weight
   file (`model.safetensors` / `pytorch_model.bin`) or a Hugging Face model directory;
2. the torch-hub cache: `<torch.hub.get_dir()>/checkpoints/dinov2_vits14_pretrain.pth` ($TORCH_HOME);
3. the Hugging Face cache: `<hub cache>/models--facebook--dinov2-small/snapshots/*/` ($HF_HUB_CACHE,
   $HF_HOME/hub, ~/.cache/huggingface/hub).

Missing everywhere, the error lists every path it looked at and how to provide one.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Optional

import torch
import torch.nn.functional as F
from torch import Tensor

from sg_nerfstudio.features.base import TeacherConfig, TeacherInputError, checked_grid, input_shape, resolve_device

PATCH_SIZE = 14
FEATURE_DIM = 384
DEFAULT_INPUT_SIZE = 1400
TORCH_HUB_FILENAME = "dinov2_vits14_pretrain.pth"
HF_REPO_DIR = "models--facebook--dinov2-small"
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def vits14_architecture():
    """An uninitialised-weights (random) DINOv2 ViT-S/14 as `transformers.Dinov2Model`."""
    from transformers import Dinov2Config, Dinov2Model

    config = Dinov2Config(
        hidden_size=FEATURE_DIM, num_hidden_layers=12, num_attention_heads=6, mlp_ratio=4,
        patch_size=PATCH_SIZE, image_size=518, layerscale_value=1.0, layer_norm_eps=1e-6,
    )
    return Dinov2Model(config).eval()


# facebookresearch/dinov2 (torch hub) and legacy Hugging Face names -> current transformers names
_RENAMES = [
    (r"^cls_token$", "embeddings.cls_token"),
    (r"^mask_token$", "embeddings.mask_token"),
    (r"^pos_embed$", "embeddings.position_embeddings"),
    (r"^patch_embed\.proj\.", "embeddings.patch_embeddings.projection."),
    (r"^blocks\.(\d+)\.norm1\.", r"encoder.layer.\1.norm1."),
    (r"^blocks\.(\d+)\.norm2\.", r"encoder.layer.\1.norm2."),
    (r"^blocks\.(\d+)\.attn\.proj\.", r"encoder.layer.\1.attention.o_proj."),
    (r"^blocks\.(\d+)\.ls1\.gamma$", r"encoder.layer.\1.layer_scale1.lambda1"),
    (r"^blocks\.(\d+)\.ls2\.gamma$", r"encoder.layer.\1.layer_scale2.lambda1"),
    (r"^blocks\.(\d+)\.mlp\.", r"encoder.layer.\1.mlp."),
    (r"^norm\.", "layernorm."),
    (r"\.attention\.attention\.query\.", ".attention.q_proj."),
    (r"\.attention\.attention\.key\.", ".attention.k_proj."),
    (r"\.attention\.attention\.value\.", ".attention.v_proj."),
    (r"\.attention\.output\.dense\.", ".attention.o_proj."),
]


def to_transformers_state_dict(state_dict: dict[str, Tensor]) -> dict[str, Tensor]:
    """Rename a torch-hub or (legacy) Hugging Face DINOv2 state dict to `transformers.Dinov2Model` keys."""
    if "model" in state_dict and isinstance(state_dict["model"], dict):
        state_dict = state_dict["model"]
    converted: dict[str, Tensor] = {}
    for key, value in state_dict.items():
        key = key.removeprefix("dinov2.").removeprefix("backbone.")
        qkv = re.match(r"^blocks\.(\d+)\.attn\.qkv\.(weight|bias)$", key)
        if qkv:
            block, kind = qkv.groups()
            for name, part in zip(("q_proj", "k_proj", "v_proj"), value.chunk(3, dim=0)):
                converted[f"encoder.layer.{block}.attention.{name}.{kind}"] = part.clone()
            continue
        for pattern, replacement in _RENAMES:
            key = re.sub(pattern, replacement, key)
        if key == "embeddings.mask_token" and value.dim() == 2 and value.shape[0] == 1:
            value = value.reshape(1, -1)
        converted[key] = value
    return converted


def weight_search_paths(explicit: Optional[Path]) -> list[Path]:
    """Every place the loader looks, in order."""
    paths: list[Path] = []
    if explicit is not None:
        paths.append(Path(explicit).expanduser())
    paths.append(Path(torch.hub.get_dir()) / "checkpoints" / TORCH_HUB_FILENAME)
    hub_caches = []
    if os.environ.get("HF_HUB_CACHE"):
        hub_caches.append(Path(os.environ["HF_HUB_CACHE"]))
    if os.environ.get("HF_HOME"):
        hub_caches.append(Path(os.environ["HF_HOME"]) / "hub")
    hub_caches.append(Path.home() / ".cache" / "huggingface" / "hub")
    for cache in dict.fromkeys(hub_caches):
        snapshots = sorted((cache / HF_REPO_DIR / "snapshots").glob("*"))
        paths.extend(snapshots or [cache / HF_REPO_DIR / "snapshots" / "<revision>"])
    return paths


def _read_weights(path: Path) -> dict[str, Tensor]:
    """State dict from a .pth/.pt/.bin file, a .safetensors file or a Hugging Face model directory."""
    if path.is_dir():
        for name in ("model.safetensors", "pytorch_model.bin"):
            if (path / name).is_file():
                return _read_weights(path / name)
        raise FileNotFoundError(f"no model.safetensors or pytorch_model.bin in {path}")
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        return load_file(str(path))
    return torch.load(path, map_location="cpu", weights_only=True)


def load_vits14(explicit: Optional[Path] = None):
    """The ViT-S/14 with the first weights found (see module docstring); one-sentence error otherwise."""
    searched = weight_search_paths(explicit)
    for path in searched:
        if not path.exists():
            if explicit is not None and path == searched[0]:
                raise TeacherInputError(f"DINOv2 weights file {path} (from --...teacher.weights) does not exist.")
            continue
        model = vits14_architecture()
        try:
            state = to_transformers_state_dict(_read_weights(path))
            missing, unexpected = model.load_state_dict(state, strict=False)
        except Exception as error:  # unreadable or wrong file: say which and why
            raise TeacherInputError(f"Could not read DINOv2 ViT-S/14 weights from {path}: {error}.") from None
        if missing or unexpected:
            raise TeacherInputError(
                f"{path} is not a DINOv2 ViT-S/14 checkpoint: {len(missing)} missing and {len(unexpected)} "
                f"unexpected parameters (e.g. {(missing + unexpected)[:3]})."
            )
        return model
    listed = "; ".join(str(p) for p in searched)
    raise TeacherInputError(
        f"No DINOv2 ViT-S/14 weights found; looked at: {listed}. Put {TORCH_HUB_FILENAME} (from the "
        "facebookresearch/dinov2 release) or a facebook/dinov2-small Hugging Face snapshot in one of those "
        "places, pass --pipeline.datamanager.teacher.weights PATH, or use the weight-free teacher with "
        "--pipeline.datamanager.teacher.name offline."
    )


class Dinov2Teacher:
    """DINOv2 ViT-S/14 dense features: image -> [rows, columns, 384] final-LayerNorm patch tokens (the
    image resized to `input_size` on its long side, aspect ratio kept; position embeddings interpolated)."""

    feature_dim = FEATURE_DIM

    def __init__(self, config: TeacherConfig, model=None):
        self.input_size = config.input_size or DEFAULT_INPUT_SIZE
        self.grid_size = checked_grid(self.input_size, PATCH_SIZE, "DINOv2 patch size")
        self.device = resolve_device(config.device)
        self.weights_source = "random (test)" if model is not None else str(config.weights or "local cache")
        self.model = (model if model is not None else load_vits14(config.weights)).to(self.device).eval()
        self.mean = torch.tensor(IMAGENET_MEAN, device=self.device).view(1, 3, 1, 1)
        self.std = torch.tensor(IMAGENET_STD, device=self.device).view(1, 3, 1, 1)
        self._fingerprint = _parameter_fingerprint(self.model)

    def settings(self) -> dict:
        return {"teacher": "dinov2_vits14", "input_size": self.input_size, "aspect": "kept", "weights": self._fingerprint}

    def grid_shape(self, height: int, width: int) -> tuple[int, int]:
        rows, columns = input_shape(height, width, self.input_size, PATCH_SIZE)
        return rows // PATCH_SIZE, columns // PATCH_SIZE

    @torch.no_grad()
    def extract(self, image: Tensor) -> Tensor:
        return self.describe(image.to(self.device, torch.float32)).float().cpu()

    def describe(self, image: Tensor, grid: Optional[tuple[int, int]] = None) -> Tensor:
        """Differentiable `extract` on the teacher's device: [H, W, 3] -> [rows, columns, 384].

        `grid` (rows, columns) forces the map's shape (the image is resized to grid * 14 pixels); by default
        it is `grid_shape(H, W)`.
        """
        rows, columns = grid or self.grid_shape(image.shape[0], image.shape[1])
        pixels = image.to(self.device).permute(2, 0, 1)[None]
        pixels = F.interpolate(pixels, size=(rows * PATCH_SIZE, columns * PATCH_SIZE), mode="bilinear", align_corners=False, antialias=True)
        pixels = (pixels - self.mean) / self.std
        tokens = self.model(pixel_values=pixels).last_hidden_state[0, 1:]  # drop the class token
        return tokens.reshape(rows, columns, FEATURE_DIM)


def _parameter_fingerprint(model: torch.nn.Module) -> str:
    """A cheap content fingerprint of the weights (different checkpoints -> different cache keys)."""
    total = torch.zeros((), dtype=torch.float64)
    for index, param in enumerate(model.parameters()):
        total += (index + 1) * param.detach().double().sum() + param.detach().double().abs().sum()
    return f"{total.item():.10e}"
