"""The registration loop: optimise one Sim(3) of a whole meta-image against the frozen reference model.

Per step: transform the photos' cameras by T = U(delta) o T0 (dataparser frame), render the reference
model from them, compare with the photos (L1 or L2 per image), aggregate robustly (LTS by default), and
take an Adam step on the 7 parameters delta. Everything the caller passes in and gets back is in the
reference *world* frame.

What is compared (`objective`):
- `features` (the paper): the model's decoded feature field, resized to the teacher grid, against the
  photos' teacher maps.
- `teacher-on-render`: the teacher applied (with gradients) to the model's rendered RGB, against the same
  teacher maps. Same appearance invariance, but as sharp as the colour model: a distilled feature field
  is a view-independent, blurred fit of the teacher, and with the weight-free offline teacher that blur
  flattens the objective around the answer. Practical for cheap teachers (offline); with DINOv2 every
  step runs the ViT on every render.
- `photometric`: RGB against the photos' RGB on the teacher grid.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace
from typing import Callable, Literal, Optional

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from sg_nerfstudio.errors import InputError
from sg_nerfstudio.features import FeatureCache, Teacher, TeacherConfig, build_teacher, extract_all
from sg_nerfstudio.registration.meta_image import MetaImage
from sg_nerfstudio.registration.reference import ReferenceModel, resize_to
from sg_nerfstudio.registration.robust import LossKind, Robust, RobustAggregator, per_image_loss
from sg_nerfstudio.registration.sim3 import decompose, invert, update_matrix

Array = np.ndarray
ObjectiveKind = Literal["features", "teacher-on-render", "photometric"]
RENDER_BATCH_ELEMENTS = 2_000_000
"""Cameras x Gaussians rendered in one call: all 20 photos at once for a 20k-Gaussian CPU model, one or two
at a time for the millions of Gaussians of a real reconstruction (bounded memory)."""


class InitialisationError(InputError):
    """A start the optimisation cannot begin from."""


@dataclass
class RegistrationSettings:
    """How one meta-image is registered (defaults: the paper's settings)."""

    steps: int = 12000
    """Optimisation steps (paper: 12000)."""
    lr: float = 1e-3
    """Adam learning rate on delta = (omega, nu, log s) (paper: 1e-3)."""
    lr_final: Optional[float] = None
    """Exponential decay of the learning rate to this value at the last step; None keeps it constant (paper)."""
    adam_eps: float = 1e-8
    objective: ObjectiveKind = "features"
    """features: decoded feature field vs the photos' teacher maps (paper); teacher-on-render: the teacher
    applied to the rendered RGB vs the same maps; photometric: colours vs the photos."""
    loss: LossKind = "l1"
    robust: Robust = "lts"
    """lts (paper), fixed-lts, irls or none."""
    lts_percentile: float = 50.0
    """Images with a loss above this percentile of the previous iteration's losses are ignored (50 = median)."""
    images_per_step: int = 0
    """Photos rendered per step; 0 = all of them (paper)."""
    teacher_input_size: Optional[int] = None
    """Teacher input size for the photos; default: the one the reference model was trained with."""
    render_scale: float = 2.0
    """Long side of the renders as a multiple of the teacher grid (the paper renders at full resolution;
    1-2 keeps CPU cost low for `features`, whose renders are resized to the grid). Never more than the
    photo's own long side, and for teacher-on-render never more than the teacher's input size."""
    near_plane: float = 0.7
    """Near plane in dataparser units against floaters (paper: 0.7); lowered automatically to half the
    nearest sparse-point depth of the meta-image so it never cuts away what the photos see."""
    seed: int = 0
    backend: Literal["auto", "gsplat", "numba", "torch"] = "auto"


@dataclass
class PreparedPhoto:
    name: str
    cam_from_meta: Tensor  # [3, 4] float64
    K: Tensor  # [3, 3] float32, at render size
    width: int
    height: int
    target: Tensor  # [rows, columns, D] teacher map or RGB on the teacher grid


@dataclass
class RegistrationResult:
    transform: Array  # [4, 4] meta -> reference world
    initial_transform: Array
    final_losses: Array  # [P] per photo at the final transform
    initial_losses: Array
    final_trimmed_loss: float
    history: list[dict]  # per step and photo: step, image, loss, kept, weight
    ignored_fraction: Array  # [P] fraction of its evaluations in which each photo was ignored
    steps: int
    wall_time_s: float
    timings: dict
    near_plane: float
    settings: dict
    photo_names: list[str]
    coverage: Array  # [P] fraction of rendered pixels covered by the model at the initial transform


def registration_teacher(reference: ReferenceModel, settings: RegistrationSettings) -> tuple[TeacherConfig, Teacher]:
    """The reference model's teacher, at the input size the settings ask for."""
    config = replace(reference.teacher, input_size=settings.teacher_input_size or reference.teacher.input_size)
    return config, build_teacher(config)


def render_size(width: int, height: int, settings: RegistrationSettings, teacher: Teacher) -> tuple[int, int]:
    """(width, height) the model renders a photo of this size at: long side render_scale x teacher grid,
    capped at the photo's long side (and at the teacher's input size for teacher-on-render)."""
    long_side = min(settings.render_scale * teacher.grid_size, max(width, height))
    if settings.objective == "teacher-on-render":
        long_side = min(long_side, teacher.input_size)
    factor = max(8, round(long_side)) / max(width, height)
    return max(8, round(width * factor)), max(8, round(height * factor))


def prepare_photos(reference: ReferenceModel, meta: MetaImage, settings: RegistrationSettings) -> list[PreparedPhoto]:
    """Undistort each photo, compute (or load cached) teacher maps, and set up its render camera."""
    teacher_config, teacher = registration_teacher(reference, settings)
    images = [None] * len(meta.photos)

    def load(index: int) -> Tensor:
        if images[index] is None:
            images[index] = torch.from_numpy(meta.photos[index].load_undistorted())
        return images[index]

    sizes = [render_size(p.camera.width, p.camera.height, settings, teacher) for p in meta.photos]
    if settings.objective == "photometric":
        targets = [area_resize(load(i), teacher.grid_shape(*load(i).shape[:2])) for i in range(len(meta.photos))]
    elif settings.objective == "teacher-on-render":
        targets = [teacher_on_render_target(load(i), sizes[i], teacher) for i in range(len(meta.photos))]
    else:
        targets = extract_all(load, len(meta.photos), teacher, FeatureCache(teacher_config.cache_dir), f"Teacher features ({meta.name})")
    prepared = []
    for photo, target, (render_w, render_h) in zip(meta.photos, targets, sizes):
        width, height = photo.camera.width, photo.camera.height
        K = photo.pinhole_intrinsics().copy()
        K[0] *= render_w / width
        K[1] *= render_h / height
        prepared.append(PreparedPhoto(
            photo.name, torch.from_numpy(photo.cam_from_world), torch.from_numpy(K).float(), render_w, render_h, target.float(),
        ))
    return prepared


def area_resize(image: Tensor, size: tuple[int, int]) -> Tensor:
    """[H, W, 3] uint8 photo -> [rows, columns, 3] float in [0, 1], each output pixel the mean of its area."""
    pixels = image.permute(2, 0, 1)[None].float() / 255.0
    return F.interpolate(pixels, size=size, mode="area")[0].permute(1, 2, 0)


@torch.no_grad()
def teacher_on_render_target(image: Tensor, render_wh: tuple[int, int], teacher: Teacher) -> Tensor:
    """The teacher map a photo is compared with under teacher-on-render: [rows, columns, D].

    The photo is first reduced to the render's own size and then described on the teacher grid of the
    full photo, exactly the path the render takes (`Objective.on_target_grid`). Describing the full-size
    photo instead would compare a sharp photo with an upsampled, blurrier render, which biases the
    optimum towards poses that blur the render (too far away, wrong scale).
    """
    render_w, render_h = render_wh
    small = area_resize(image, (render_h, render_w))
    grid = teacher.grid_shape(image.shape[0], image.shape[1])
    return teacher.describe(small.to(teacher.device), grid).float().cpu()


def camera_viewmat(cam_from_meta: Tensor, linear: Tensor, translation: Tensor, scale: Tensor) -> Tensor:
    """World-to-camera [4, 4] (float32) of a meta camera moved by the similarity x -> linear x + translation.

    Args:
        cam_from_meta: [3, 4] OpenCV world-to-camera in the meta frame (float64).
        linear: [3, 3] = scale * R, translation: [3], scale: [] (float64, differentiable).
    """
    rotation_cw = cam_from_meta[:, :3]
    centre = -rotation_cw.T @ cam_from_meta[:, 3]
    new_centre = linear @ centre + translation
    new_rotation_cw = rotation_cw @ (linear / scale).T
    top = torch.cat([new_rotation_cw, (-new_rotation_cw @ new_centre)[:, None]], dim=1)
    bottom = torch.tensor([[0.0, 0.0, 0.0, 1.0]], dtype=top.dtype)
    return torch.cat([top, bottom], dim=0).float()


class Objective:
    """Per-photo loss of the frozen reference model under a meta -> dataparser similarity."""

    def __init__(self, reference: ReferenceModel, photos: list[PreparedPhoto], settings: RegistrationSettings, near_plane: float):
        self.reference, self.photos, self.settings, self.near_plane = reference, photos, settings, near_plane
        self.teacher = registration_teacher(reference, settings)[1] if settings.objective == "teacher-on-render" else None
        self.timings = {"render": 0.0, "loss": 0.0, "backward": 0.0}

    def __call__(self, matrix: Tensor, scale: Tensor, indices) -> tuple[list[Tensor], Tensor]:
        """B scalar losses and [B] covered fractions of the photos `indices` under `matrix` [4, 4] (float64).

        Photos of one render size are rendered in one batch (one projection graph for all their cameras).
        The losses stay separate tensors so that a robust objective that ignores a photo never
        backpropagates through its render."""
        losses, coverage = [None] * len(indices), [None] * len(indices)
        for size, positions in self.same_size_groups(indices):
            start = time.perf_counter()
            photos = [self.photos[indices[position]] for position in positions]
            viewmats = torch.stack([camera_viewmat(photo.cam_from_meta, matrix[:3, :3], matrix[:3, 3], scale) for photo in photos])
            rendered, alpha = self.reference.render(
                viewmats, torch.stack([photo.K for photo in photos]), size[0], size[1], self.near_plane,
                "features" if self.settings.objective == "features" else "photometric", self.settings.backend,
            )
            middle = time.perf_counter()
            for position, photo, render, covered in zip(positions, photos, rendered.unbind(0), alpha.detach()):
                on_grid = self.on_target_grid(render[None], photo.target)
                losses[position] = per_image_loss(on_grid, photo.target[None], self.settings.loss)[0]
                coverage[position] = covered.mean()
            self.timings["render"] += middle - start
            self.timings["loss"] += time.perf_counter() - middle
        return losses, torch.stack(coverage)

    def same_size_groups(self, indices) -> list[tuple[tuple[int, int], list[int]]]:
        """Positions in `indices` grouped by the (width, height) their photos render at, in batches of at most
        RENDER_BATCH_ELEMENTS // N cameras (the CPU renderer holds [cameras, N] tensors while culling)."""
        groups: dict[tuple[int, int], list[int]] = {}
        for position, index in enumerate(indices):
            groups.setdefault((self.photos[index].width, self.photos[index].height), []).append(position)
        per_batch = max(1, RENDER_BATCH_ELEMENTS // max(int(self.reference.means.shape[0]), 1))
        return [(size, positions[i : i + per_batch]) for size, positions in groups.items() for i in range(0, len(positions), per_batch)]

    def on_target_grid(self, rendered: Tensor, target: Tensor) -> Tensor:
        """[1, H, W, C] render -> [1, rows, columns, D] comparable with the target map [rows, columns, D]."""
        grid = tuple(target.shape[:2])
        if self.teacher is None:
            return resize_to(rendered, grid)
        return self.teacher.describe(rendered[0], grid).to(target.device)[None]


def effective_near_plane(meta: MetaImage, initial_ns: Array, requested: float) -> float:
    """min(requested, half the 5th-percentile depth of the sparse points seen by the photos, in dataparser units)."""
    depths = np.concatenate([p.point_depths for p in meta.photos]) if meta.photos else np.zeros(0)
    depths = depths[depths > 0]
    if len(depths) == 0:
        return requested
    scale, _, _ = decompose(initial_ns)
    return float(min(requested, 0.5 * scale * np.percentile(depths, 5)))


def register(
    reference: ReferenceModel,
    meta: MetaImage,
    initial_world: Array,
    settings: RegistrationSettings,
    photos: Optional[list[PreparedPhoto]] = None,
    on_step: Optional[Callable[[int, Array], None]] = None,
) -> RegistrationResult:
    """Estimate the Sim(3) meta -> reference world starting from `initial_world` [4, 4].

    `on_step(step, transform)` is called after every step with the current estimate [4, 4] (meta -> world).
    """
    started = time.perf_counter()
    photos = photos if photos is not None else prepare_photos(reference, meta, settings)
    world_to_ns = reference.world_to_dataparser
    ns_to_world = invert(world_to_ns)
    initial_ns = world_to_ns @ initial_world
    near_plane = effective_near_plane(meta, initial_ns, settings.near_plane)
    objective = Objective(reference, photos, settings, near_plane)
    scale0, _, _ = decompose(initial_ns)
    t0 = torch.from_numpy(initial_ns)
    centre = torch.from_numpy(meta.centroid_under(initial_ns))
    all_indices = list(range(len(photos)))

    with torch.no_grad():
        initial_losses, coverage = objective(t0, torch.tensor(scale0, dtype=torch.float64), all_indices)
        initial_losses = torch.stack(initial_losses)
    if float(coverage.max()) < 1e-3:
        raise InitialisationError(
            f"From the initial transform the reference model renders nothing for any photo of meta-image '{meta.name}' "
            "(every camera sees empty space); expected a start near the answer (see --init)."
        )
    aggregator = RobustAggregator(settings.robust, settings.lts_percentile, initial_losses.double().numpy())

    delta = torch.zeros(7, dtype=torch.float64, requires_grad=True)
    optimizer = torch.optim.Adam([delta], lr=settings.lr, eps=settings.adam_eps)
    gamma = (settings.lr_final / settings.lr) ** (1.0 / max(settings.steps, 1)) if settings.lr_final else 1.0
    scheduler = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=gamma)
    rng = np.random.default_rng(settings.seed)
    batch_size = settings.images_per_step or len(photos)
    queue: list[int] = []
    history: list[dict] = []
    ignored = np.zeros(len(photos))
    evaluated = np.zeros(len(photos))
    for step in range(settings.steps):
        if batch_size >= len(photos):
            batch = all_indices
        else:
            while len(queue) < batch_size:
                queue.extend(rng.permutation(len(photos)).tolist())
            batch, queue = queue[:batch_size], queue[batch_size:]
        update = update_matrix(delta, centre)
        matrix = update @ t0
        scale = torch.exp(delta[6]) * scale0
        losses, _ = objective(matrix, scale, batch)
        value, kept, weights = aggregator(losses, np.asarray(batch))
        start = time.perf_counter()
        optimizer.zero_grad()
        value.backward()
        optimizer.step()
        scheduler.step()
        objective.timings["backward"] += time.perf_counter() - start
        if not torch.isfinite(delta).all():
            raise FloatingPointError(f"The registration of '{meta.name}' diverged to NaN at step {step}.")
        for index, loss, keep, weight in zip(batch, [float(loss.detach()) for loss in losses], kept, weights):
            history.append({"step": step, "image": photos[index].name, "loss": loss, "kept": bool(keep), "weight": float(weight)})
            ignored[index] += not keep
            evaluated[index] += 1
        if on_step is not None:
            with torch.no_grad():
                current_ns = (update_matrix(delta, centre) @ t0).numpy()
            on_step(step, ns_to_world @ current_ns)

    with torch.no_grad():
        final_ns = (update_matrix(delta, centre) @ t0).numpy()
        final_scale = torch.tensor(decompose(final_ns)[0], dtype=torch.float64)
        final_losses, _ = objective(torch.from_numpy(final_ns), final_scale, all_indices)
    final_losses = torch.stack(final_losses).double().numpy()
    trimmed = final_losses[final_losses <= np.percentile(final_losses, settings.lts_percentile)] if settings.robust != "none" else final_losses
    return RegistrationResult(
        transform=ns_to_world @ final_ns,
        initial_transform=np.asarray(initial_world, dtype=np.float64),
        final_losses=final_losses,
        initial_losses=initial_losses.double().numpy(),
        final_trimmed_loss=float(trimmed.mean()),
        history=history,
        ignored_fraction=ignored / np.maximum(evaluated, 1),
        steps=settings.steps,
        wall_time_s=time.perf_counter() - started,
        timings=dict(objective.timings),
        near_plane=near_plane,
        settings=asdict(settings),
        photo_names=[p.name for p in photos],
        coverage=coverage.double().numpy(),
    )
