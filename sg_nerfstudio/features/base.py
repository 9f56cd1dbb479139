"""What every teacher shares: its settings, the extractor interface, and the load error."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional, Protocol

import torch
from torch import Tensor

from sg_nerfstudio.errors import InputError


class TeacherInputError(InputError):
    """A teacher that cannot be built from the given settings or files."""


@dataclass
class TeacherConfig:
    """The 2D feature extractor whose maps the feature splat distils (the paper's "teacher")."""

    name: Literal["dinov2", "offline", "dense-sift", "hog-layout"] = "dinov2"
    """dinov2: ViT-S/14 patch tokens (384-d, needs local weights); offline: dense oriented-gradient
    descriptor that needs no weights (for machines without DINOv2); dense-sift: kornia's dense RootSIFT
    (128-d, no weights); hog-layout: the layout of oriented-gradient histograms at three scales (324-d, no
    weights), made for photos against renders of a reference model."""
    input_size: Optional[int] = None
    """Long side the image is resized to before extraction (default 1400 for dinov2, a 100-patch grid as
    in the paper; 256 for offline, 32 cells). The aspect ratio is kept: the short side is rounded to a
    multiple of the patch/cell size, so portrait and landscape photos of any size see the scene
    undistorted. Must be a multiple of the patch/cell size."""
    weights: Optional[Path] = None
    """dinov2 only: a local checkpoint (torch-hub .pth, Hugging Face .safetensors/.bin, or a Hugging Face
    model directory). When unset, the torch-hub and Hugging Face caches are searched."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """Where extraction runs; auto = CUDA when available."""
    cache_dir: Optional[Path] = None
    """Feature cache directory; default $XDG_CACHE_HOME/sg_nerfstudio/features (~/.cache/...)."""


class Teacher(Protocol):
    """Maps an image to a dense feature grid."""

    feature_dim: int
    grid_size: int
    """Cells along the long side of every map."""

    def settings(self) -> dict:
        """Everything that changes the output, for cache keys."""

    def grid_shape(self, height: int, width: int) -> tuple[int, int]:
        """(rows, columns) of the map of an image of this size."""

    def extract(self, image: Tensor) -> Tensor:
        """image [H, W, 3] float in [0, 1] -> features [rows, columns, feature_dim] float32 (CPU)."""

    def describe(self, image: Tensor, grid: Optional[tuple[int, int]] = None) -> Tensor:
        """`extract` with gradients, on the image's device; `grid` = (rows, columns) forces the map's shape."""


class CellDescriptor(ABC):
    """A weight-free teacher that describes every cell of `cell` x `cell` pixels of the image resized to
    `input_size` on its long side (aspect ratio kept). Subclasses set `cell`, `default_input_size`, `cell_name`
    and `feature_dim` and implement `describe_resized`."""

    cell: int
    default_input_size: int
    cell_name: str
    feature_dim: int

    def __init__(self, config: TeacherConfig):
        self.input_size = config.input_size or self.default_input_size
        self.grid_size = checked_grid(self.input_size, self.cell, self.cell_name)
        self.device = resolve_device(config.device)

    def grid_shape(self, height: int, width: int) -> tuple[int, int]:
        rows, columns = input_shape(height, width, self.input_size, self.cell)
        return rows // self.cell, columns // self.cell

    @torch.no_grad()
    def extract(self, image: Tensor) -> Tensor:
        return self.describe(image.to(self.device, torch.float32)).cpu()

    def describe(self, image: Tensor, grid: Optional[tuple[int, int]] = None) -> Tensor:
        """Differentiable `extract` on the image's device: [H, W, 3] -> [rows, columns, feature_dim].

        `grid` (rows, columns) forces the map's shape (the image is resized to grid * cell pixels); by default
        it is `grid_shape(H, W)`. Registration uses it to describe renders whose size differs from the photo's.
        """
        rows, columns = grid or self.grid_shape(image.shape[0], image.shape[1])
        pixels = resize_bilinear(image.permute(2, 0, 1)[None], (rows * self.cell, columns * self.cell))
        return self.describe_resized(pixels)[0].permute(1, 2, 0)

    @abstractmethod
    def describe_resized(self, pixels: Tensor) -> Tensor:
        """[1, 3, rows * cell, columns * cell] in [0, 1] -> [1, feature_dim, rows, columns]."""


def resolve_device(device: str) -> torch.device:
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device == "cuda" and not torch.cuda.is_available():
        raise TeacherInputError("Teacher device 'cuda' was requested but CUDA is not available; use --...teacher.device cpu.")
    return torch.device(device)


def checked_grid(input_size: int, step: int, what: str) -> int:
    """input_size / step, or a one-sentence error when it is not a positive multiple."""
    if input_size <= 0 or input_size % step != 0:
        raise TeacherInputError(
            f"Teacher input size {input_size} is not a positive multiple of the {what} ({step} pixels); "
            f"use e.g. {max(step, (input_size // step) * step) if input_size > 0 else step * 32}."
        )
    return input_size // step


def input_shape(height: int, width: int, input_size: int, step: int) -> tuple[int, int]:
    """(h, w) an image is resized to: the long side becomes `input_size`, the short side keeps the aspect
    ratio, rounded to a multiple of `step` (at least one step)."""
    short = max(step, round(input_size * min(height, width) / max(height, width) / step) * step)
    return (input_size, short) if height >= width else (short, input_size)


def resize_bilinear(maps: Tensor, size: tuple[int, int]) -> Tensor:
    """[B, C, H, W] -> [B, C, size[0], size[1]], bilinear (align_corners=False), antialiased when shrinking.

    Shrinking averages each output cell over about its own footprint, as a teacher's cell or patch pools
    the image; plain bilinear would sample only the 2 x 2 inputs nearest each cell centre (and leave the
    others without a gradient). Enlarging gives the same values without antialiasing (to 1e-7) at a third
    of the cost, so it is skipped there; a same-size map is returned as is.
    """
    if tuple(maps.shape[-2:]) == tuple(size):
        return maps
    shrinking = size[0] < maps.shape[-2] or size[1] < maps.shape[-1]
    return torch.nn.functional.interpolate(maps, size=size, mode="bilinear", align_corners=False, antialias=shrinking)
