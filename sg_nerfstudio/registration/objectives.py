"""What registration compares: one small class per objective, the photos prepared for it, and the per-photo
losses of the frozen model under a transform.

An `Objective` knows its target (what a photo becomes), what the model renders for it and how a render
reaches the target's grid:

- `features` (the paper, `DecodedFeatures`): the model's decoded feature field, resized to the teacher grid,
  against the photos' teacher maps.
- `teacher-on-render` (`TeacherOnRender`): the teacher applied (with gradients) to the model's rendered RGB,
  against the photo described the same way. Same appearance invariance, but as sharp as the colour model: a
  distilled feature field is a view-independent, blurred fit of the teacher, and with the weight-free
  offline teacher that blur flattens the objective around the answer. Practical for cheap teachers
  (offline); with DINOv2 every step runs the ViT on every render.
- `photometric` (`Photometric`): RGB against the photos' RGB on the teacher grid.

Frames: `PhotoLosses` takes the transform meta-image -> *dataparser* frame (the model's own frame) as a
`Sim3`; photos keep their COLMAP pose in the meta frame.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, replace
from typing import Callable, ClassVar

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from sg_nerfstudio.errors import InputError
from sg_nerfstudio.features import FeatureCache, Teacher, TeacherConfig, build_teacher, extract_all
from sg_nerfstudio.features.base import resize_bilinear
from sg_nerfstudio.geometry.frames import viewmat
from sg_nerfstudio.geometry.meta_image import MetaImage
from sg_nerfstudio.geometry.sim3 import Sim3
from sg_nerfstudio.registration.depth_agreement import PointPixels, log_depth_ratios
from sg_nerfstudio.registration.reference import ReferenceModel
from sg_nerfstudio.registration.robust import per_image_loss
from sg_nerfstudio.registration.settings import RegistrationSettings
from sg_nerfstudio.registration.visibility import CullingCamera, VisibleSubset

RENDER_BATCH_ELEMENTS = 2_000_000
"""Cameras x Gaussians rendered in one call: all 20 photos at once for a 20k-Gaussian CPU model, one or two
at a time for the millions of Gaussians of a real reconstruction (bounded memory)."""
Array = np.ndarray
Loader = Callable[[int], Tensor]
"""index -> [H, W, 3] uint8 undistorted photo."""


@dataclass
class PreparedPhoto:
    name: str
    cam_from_meta: Tensor  # [3, 4] float64, OpenCV world-to-camera in the meta frame
    K: Tensor  # [3, 3] float32, at render size, the model is rendered with (Photo.render_intrinsics_at)
    width: int
    height: int
    target: Tensor  # [rows, columns, D] teacher map or RGB on the teacher grid
    points: PointPixels  # its sparse points' pixels in the render and depths (depth_agreement.py)


class Objective(ABC):
    """One way of comparing the model with a photo (see the module docstring); `teacher` sets the grid."""

    name: ClassVar[str]

    def __init__(self, teacher: Teacher, teacher_config: TeacherConfig):
        self.teacher, self.teacher_config = teacher, teacher_config

    def render_cap(self) -> float:
        """Upper bound of a render's long side imposed by the objective (pixels)."""
        return float("inf")

    @abstractmethod
    def targets(self, load: Loader, sizes: list[tuple[int, int]], label: str) -> list[Tensor]:
        """Per photo [rows, columns, D]; `sizes` are the (width, height) each photo renders at."""

    def render(
        self, reference: ReferenceModel, viewmats: Tensor, Ks: Tensor, width: int, height: int, near_plane: float, backend: str,
        with_depth: bool = False,
    ) -> tuple[Tensor, Tensor]:
        """[C, H, W, C'] maps (with `with_depth`, the expected depth appended as one more channel) and
        [C, H, W, 1] alphas of the cameras (dataparser frame)."""
        return reference.render_rgb(viewmats, Ks, width, height, near_plane, backend, with_depth)

    def to_target_grid(self, rendered: Tensor, target: Tensor) -> Tensor:
        """[1, H, W, C'] render -> [1, rows, columns, D] comparable with the target [rows, columns, D]."""
        return resize_to(rendered, tuple(target.shape[:2]))


class DecodedFeatures(Objective):
    name = "features"

    def targets(self, load: Loader, sizes: list[tuple[int, int]], label: str) -> list[Tensor]:
        return extract_all(load, len(sizes), self.teacher, FeatureCache(self.teacher_config.cache_dir), f"Teacher features ({label})")

    def render(self, reference, viewmats, Ks, width, height, near_plane, backend, with_depth=False):
        return reference.render_features(viewmats, Ks, width, height, near_plane, backend, with_depth)


class TeacherOnRender(Objective):
    name = "teacher-on-render"

    def render_cap(self) -> float:
        return float(self.teacher.input_size)

    def targets(self, load: Loader, sizes: list[tuple[int, int]], label: str) -> list[Tensor]:
        return [teacher_on_render_target(load(i), size, self.teacher) for i, size in enumerate(sizes)]

    def to_target_grid(self, rendered: Tensor, target: Tensor) -> Tensor:
        return self.teacher.describe(rendered[0], tuple(target.shape[:2])).to(target.device)[None]


class Photometric(Objective):
    name = "photometric"

    def targets(self, load: Loader, sizes: list[tuple[int, int]], label: str) -> list[Tensor]:
        return [area_resize(load(i), self.teacher.grid_shape(*load(i).shape[:2])) for i in range(len(sizes))]


OBJECTIVES: dict[str, type[Objective]] = {kind.name: kind for kind in (DecodedFeatures, TeacherOnRender, Photometric)}


class ObjectiveSettingsError(InputError):
    """Registration settings that name a teacher the objective cannot use."""


def objective_teacher_config(reference: ReferenceModel, settings: RegistrationSettings) -> TeacherConfig:
    """The teacher the objective describes photos with: the reference's own, or `render_teacher` (teacher-on-render
    and photometric only), at `teacher_input_size` when set, else the reference's input size for its own teacher
    and the render teacher's default for another one."""
    check_objective_settings(settings)
    name = settings.objective.render_teacher or reference.teacher.name
    if name == reference.teacher.name:
        return replace(reference.teacher, input_size=settings.objective.teacher_input_size or reference.teacher.input_size)
    return replace(reference.teacher, name=name, input_size=settings.objective.teacher_input_size)


def check_objective_settings(settings: RegistrationSettings) -> None:
    """One sentence (ObjectiveSettingsError) for a render teacher given to the features objective, before any work."""
    if settings.objective.render_teacher is not None and settings.objective.kind == "features":
        raise ObjectiveSettingsError(
            f"--objective.render-teacher {settings.objective.render_teacher} describes rendered images (--objective.kind teacher-on-render or "
            "photometric), but the features objective compares the reference's distilled feature field; leave --objective.render-teacher unset or "
            "change the objective."
        )


def refine_settings(settings: RegistrationSettings) -> RegistrationSettings:
    """The settings of the refine stage: the main stage's, or with a `last_stage.teacher` that descriptor applied to the
    renders and the photos (teacher-on-render, whatever the main objective) at its default input size."""
    if settings.last_stage.teacher is None:
        return settings
    same_teacher = settings.objective.kind == "teacher-on-render" and settings.last_stage.teacher == settings.objective.render_teacher
    return settings.changed(objective={
        "kind": "teacher-on-render", "render_teacher": settings.last_stage.teacher,
        "teacher_input_size": settings.objective.teacher_input_size if same_teacher else None,
    })


def build_objective(reference: ReferenceModel, settings: RegistrationSettings) -> Objective:
    """The objective the settings name, with its teacher (`objective_teacher_config`)."""
    config = objective_teacher_config(reference, settings)
    return OBJECTIVES[settings.objective.kind](build_teacher(config), config)


def render_size(width: int, height: int, settings: RegistrationSettings, objective: Objective) -> tuple[int, int]:
    """(width, height) the model renders a photo of this size at: long side render_scale x teacher grid,
    capped at the photo's long side and at the objective's cap (the teacher's input size for teacher-on-render)."""
    long_side = min(settings.objective.render_scale * objective.teacher.grid_size, max(width, height), objective.render_cap())
    factor = max(8, round(long_side)) / max(width, height)
    return max(8, round(width * factor)), max(8, round(height * factor))


def prepare_photos(reference: ReferenceModel, meta: MetaImage, settings: RegistrationSettings, objective: Objective | None = None) -> list[PreparedPhoto]:
    """Undistort each photo once, compute its target (teacher maps cached on disk) and set up its render camera."""
    objective = objective or build_objective(reference, settings)
    images: list[Tensor | None] = [None] * len(meta.photos)

    def load(index: int) -> Tensor:
        if images[index] is None:
            images[index] = torch.from_numpy(meta.photos[index].load_undistorted())
        return images[index]

    sizes = [render_size(p.camera.width, p.camera.height, settings, objective) for p in meta.photos]
    targets = objective.targets(load, sizes, meta.name)
    return [
        PreparedPhoto(
            photo.name, torch.from_numpy(photo.cam_from_world), torch.from_numpy(photo.render_intrinsics_at(w, h)).float(), w, h, target.float(),
            PointPixels.of(photo.points_camera, photo.intrinsics_at(w, h), w, h),
        )
        for photo, target, (w, h) in zip(meta.photos, targets, sizes)
    ]


def with_camera_changes(photos: list[PreparedPhoto], factors: dict[str, float], poses: dict[str, Array]) -> list[PreparedPhoto]:
    """`photos` rendered with their focal lengths times `factors[name]` and from `poses[name]` ([3, 4] cam_from_meta)
    (photos not named keep theirs; targets and the sparse points' observed pixels do not change)."""
    changed = []
    for photo in photos:
        K = photo.K.clone()
        K[0, 0] *= factors.get(photo.name, 1.0)
        K[1, 1] *= factors.get(photo.name, 1.0)
        pose = torch.from_numpy(np.asarray(poses[photo.name], dtype=np.float64)) if photo.name in poses else photo.cam_from_meta
        changed.append(replace(photo, K=K, cam_from_meta=pose))
    return changed


def resize_to(maps: Tensor, size: tuple[int, int]) -> Tensor:
    """[C, H, W, D] -> [C, h, w, D] on the teacher grid, exactly as in training (`resize_bilinear`)."""
    return resize_bilinear(maps.permute(0, 3, 1, 2), size).permute(0, 2, 3, 1)


def area_resize(image: Tensor, size: tuple[int, int]) -> Tensor:
    """[H, W, 3] uint8 photo -> [rows, columns, 3] float in [0, 1], each output pixel the mean of its area."""
    pixels = image.permute(2, 0, 1)[None].float() / 255.0
    return F.interpolate(pixels, size=size, mode="area")[0].permute(1, 2, 0)


@torch.no_grad()
def teacher_on_render_target(image: Tensor, render_wh: tuple[int, int], teacher: Teacher) -> Tensor:
    """The teacher map a photo is compared with under teacher-on-render: [rows, columns, D].

    The photo is first reduced to the render's own size and then described on the teacher grid of the
    full photo, exactly the path the render takes (`TeacherOnRender.to_target_grid`). Describing the
    full-size photo instead would compare a sharp photo with an upsampled, blurrier render, which biases the
    optimum towards poses that blur the render (too far away, wrong scale).
    """
    render_w, render_h = render_wh
    small = area_resize(image, (render_h, render_w))
    grid = teacher.grid_shape(image.shape[0], image.shape[1])
    return teacher.describe(small.to(teacher.device), grid).float().cpu()


class PhotoLosses:
    """Per-photo loss of the frozen reference model under a meta -> dataparser similarity.

    With `cull` (the default) the model is first restricted to what the photos can see around the pose
    (`visibility.VisibleSubset`: the same renders, at a cost that follows the visible Gaussians) and, with
    `settings.level_of_detail.voxel_pixels`, coarsened to the render's pixels (`level_of_detail`; coarser beyond
    `settings.level_of_detail.render_budget` Gaussians)."""

    def __init__(
        self, reference: ReferenceModel, photos: list[PreparedPhoto], objective: Objective, settings: RegistrationSettings,
        near_plane: float, cull: bool = True,
    ):
        self.reference, self.photos, self.objective, self.settings, self.near_plane = reference, photos, objective, settings, near_plane
        cameras = [CullingCamera(p.cam_from_meta, p.K, p.width, p.height) for p in photos]
        self.visible = VisibleSubset(reference, cameras, settings.level_of_detail.voxel_pixels, settings.level_of_detail.render_budget) if cull else None
        self.timings = {"render": 0.0, "loss": 0.0, "backward": 0.0}

    def __call__(self, meta_to_dataparser: Sim3, indices: list[int]) -> tuple[list[Tensor], Tensor]:
        """B scalar losses and [B] covered fractions of the photos `indices` under `meta_to_dataparser`
        (a torch Sim3, float64); `evaluate` without depth."""
        losses, coverage, _ = self.evaluate(meta_to_dataparser, indices)
        return losses, coverage

    def evaluate(self, meta_to_dataparser: Sim3, indices: list[int], with_depth: bool = False) -> tuple[list[Tensor], Tensor, list[Tensor]]:
        """B scalar losses, [B] covered fractions and (with `with_depth`, else []) B tensors [M_b] of the photos'
        sparse points' log depth ratios (`depth_agreement.log_depth_ratios`) under `meta_to_dataparser`.

        Photos of one render size are rendered in one batch (one projection graph for all their cameras).
        The losses stay separate tensors so that a robust objective that ignores a photo never
        backpropagates through its render; with depth the expected depth is one more channel of that render."""
        losses, coverage, ratios = [None] * len(indices), [None] * len(indices), [None] * len(indices)
        start = time.perf_counter()
        reference = self.visible.for_pose(meta_to_dataparser) if self.visible is not None else self.reference
        self.timings["render"] += time.perf_counter() - start
        log_scale = torch.log(torch.as_tensor(meta_to_dataparser.scale, dtype=torch.float64)) if with_depth else None
        for size, positions in self.same_size_groups(indices, reference.count):
            start = time.perf_counter()
            photos = [self.photos[indices[position]] for position in positions]
            device = reference.means.device  # the model's (CUDA: gsplat renders); targets and losses stay on the CPU
            viewmats = torch.stack([viewmat(meta_to_dataparser.move_camera(photo.cam_from_meta)) for photo in photos]).float().to(device)
            rendered, alpha = self.objective.render(
                reference, viewmats, torch.stack([photo.K for photo in photos]).to(device), size[0], size[1], self.near_plane, self.settings.backend,
                with_depth,
            )
            middle = time.perf_counter()
            for position, photo, render, covered in zip(positions, photos, rendered.unbind(0), alpha.detach()):
                if with_depth:
                    render, depth = render[..., :-1], render[..., -1]
                    ratios[position] = log_depth_ratios(depth.cpu(), covered[..., 0].cpu(), photo.points, log_scale)
                on_grid = self.objective.to_target_grid(render[None], photo.target).to(photo.target.device)
                losses[position] = per_image_loss(on_grid, photo.target[None], self.settings.objective.loss)[0]
                coverage[position] = covered.mean().cpu()
            self.timings["render"] += middle - start
            self.timings["loss"] += time.perf_counter() - middle
        return losses, torch.stack(coverage), ratios if with_depth else []

    def same_size_groups(self, indices: list[int], gaussians: int | None = None) -> list[tuple[tuple[int, int], list[int]]]:
        """Positions in `indices` grouped by the (width, height) their photos render at, in batches of at most
        RENDER_BATCH_ELEMENTS // N cameras for N `gaussians` (default: the whole model; the CPU renderer holds
        [cameras, N] tensors while culling)."""
        groups: dict[tuple[int, int], list[int]] = {}
        for position, index in enumerate(indices):
            groups.setdefault((self.photos[index].width, self.photos[index].height), []).append(position)
        per_batch = max(1, RENDER_BATCH_ELEMENTS // max(gaussians or self.reference.count, 1))
        return [(size, positions[i : i + per_batch]) for size, positions in groups.items() for i in range(0, len(positions), per_batch)]
