"""A reference in the paper's setting for real photos: renders of a coarse model, not the photos themselves.

The paper's references are splats trained on Google Earth Studio renders of a mesh built from aerial imagery: the
model's content is smoothed, sits a little off the real surfaces, and is lit and coloured otherwise than any photo.
`sg-make-scene --from-photos ... --scene.reference-kind coarse-model` builds that kind of reference from the
reference photos of a real scene:

1. a coarse model: an sg-feature-splat trained for a few hundred CPU steps on the reference photos at a low resolution
   (`CoarseModelSettings.train_size`: the texture resolution of the model), with the photos' solution cameras;
2. its content moved off the true surfaces by a smooth random 3D displacement of its Gaussians (`displacement`, RMS
   per axis in scene units, over `displacement_wavelength`): the same in every view, it belongs to the model;
3. renders of it from the reference cameras and from `new_views` views in each gap between neighbouring reference
   cameras, lifted above them (`lift`) and aimed where their neighbours look: a virtual capture has more and higher viewpoints than the
   photos; each finished with a Google-Earth-like look (saturation, tint, aerial haze by rendered depth:
   `synthetic.appearance.ReferenceLook.finish`);
4. the same model and look rendered at every meta-image photo's true camera: the scene's photo/render pairs
   (`pairs/<meta-image>/photos|renders/`, the layout `sg-bench teacher` reads, measured by `bench.gap`).

Training uses this package's own trainer (`splat.training`) and renderer (`registration.reference`); the displacement
field and the new views are a few lines that no library offers in this form.
"""

from __future__ import annotations

import contextlib
import io
import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Iterator

import numpy as np
import pycolmap
import torch
from PIL import Image
from scipy.spatial.transform import Rotation, Slerp

from sg_nerfstudio.features import TeacherConfig
from sg_nerfstudio.geometry.alignment import camera_centres
from sg_nerfstudio.synthetic.appearance import ReferenceLook

if TYPE_CHECKING:
    from sg_nerfstudio.registration.reference import ReferenceModel

Array = np.ndarray


@dataclass(frozen=True)
class CoarseModelSettings:
    """How coarse the model behind a `coarse-model` reference is, and how its renders look (module docstring).
    Calibrated so that the photo/render pairs land in the range of the paper's own pairs (docs/gap-scenes.md)."""

    train_size: int = 160
    """Long side (pixels) of the reference photos the coarse model is trained on: the model's texture resolution."""
    steps: int = 600
    """CPU training steps of the coarse model."""
    displacement: float = 0.015
    """RMS displacement of the model's Gaussians off where the photos put them, per axis, as a share of the reference
    cameras' median scene depth: the synthetic gap look's texture misalignment (about 0.45 m RMS seen from about 30 m)."""
    displacement_wavelength: float = 0.4
    """Length over which the displacement changes, as a share of that depth (the synthetic look's 6 m cells seen from
    about 30 m): neighbouring content moves together, but a view's content does not all move one way."""
    new_views: int = 3
    """Views rendered between each two neighbouring reference cameras besides theirs, lifted by `lift`: a virtual
    capture has many more viewpoints than the photos (a Google Earth Studio capture: hundreds). With one view per gap
    8 of the real-photo gap scenes' 24 registrations from 5-30° starts ended accurate, 13 with three
    (docs/gap-scenes.md)."""
    lift: float = 0.1
    """How far the new views sit above the line between their neighbours (up: the cameras' mean up), as a share of
    that depth."""
    saturation: float = 0.6
    """Colour saturation of the renders (1: as rendered, 0: grey)."""
    tint: tuple[float, float, float] = (0.95, 0.98, 1.04)
    """Per-channel gain of the renders."""
    haze: float = 0.15
    """Aerial haze: 1 - exp(-haze * depth / the median depth) of a pixel is the haze colour."""


COARSE_RANGES = {
    "train_size": dict(whole=True, minimum=16), "steps": dict(whole=True, minimum=1), "displacement": dict(minimum=0),
    "new_views": dict(whole=True, minimum=0),
    "displacement_wavelength": dict(minimum=1e-6), "lift": dict(minimum=0), "saturation": dict(minimum=0),
    "tint": dict(minimum=0), "haze": dict(minimum=0),
}
"""Every numeric coarse-model setting and its range (`errors.range_problem`'s bounds; tuples: each entry)."""
DISPLACEMENT_WAVES = 12
"""Plane waves summed into the displacement field (random directions and phases): enough to look irregular."""


@dataclass
class CoarseModel:
    """The trained, displaced coarse model, the depth its settings are relative to, and how long training took."""

    reference: "ReferenceModel"
    depth: float
    """Median scene depth of the reference cameras (scene units): the length the settings are shares of."""
    train_s: float
    gaussians: int


def train_coarse_model(source: Path, work: Path, settings: CoarseModelSettings, seed: int, depth: float) -> CoarseModel:
    """Train the coarse model on `source` (images/ at train_size and colmap/sparse/0 with their solution cameras and
    points, world = scene frame) in `work`, load it frozen and displace it (`displaced`); `depth`: the reference
    cameras' median scene depth."""
    from sg_nerfstudio.registration.reference import load_reference
    from sg_nerfstudio.splat.training import cpu_config, save, short_cpu_schedule, train

    teacher = TeacherConfig(name="offline", input_size=128, cache_dir=work / "feature_cache")
    config = short_cpu_schedule(cpu_config(source, work / "runs", settings.steps, teacher, experiment_name="coarse-model"))
    config.pipeline.datamanager.dataparser.eval_mode = "all"
    config.pipeline.model.densify_min_views = 0  # densified however few the photos: the model should cover the landmark
    config.machine.seed = seed
    started = time.perf_counter()
    with quiet_nerfstudio():
        trainer = train(config)
        train_s = time.perf_counter() - started
        reference = load_reference(save(trainer, config))
    return CoarseModel(displaced(reference, settings, seed, depth), depth, train_s, reference.count)


def displaced(reference: "ReferenceModel", settings: CoarseModelSettings, seed: int, depth: float) -> "ReferenceModel":
    """The model with every Gaussian moved by a smooth random field (module docstring, step 2; lengths: shares of the
    scene `depth`)."""
    if settings.displacement <= 0:
        return reference
    to_world = reference.world_to_dataparser.inverse()
    world = np.asarray(to_world.apply(reference.means.double().numpy()))
    moved = world + smooth_field(world, settings.displacement * depth, settings.displacement_wavelength * depth, seed)
    return replace(reference, means=torch.from_numpy(np.asarray(reference.world_to_dataparser.apply(moved))).to(reference.means.dtype))


def smooth_field(points: Array, rms: float, wavelength: float, seed: int) -> Array:
    """[N, 3] displacements at `points` [N, 3]: a sum of DISPLACEMENT_WAVES plane waves of `wavelength` with random
    directions and phases, RMS `rms` per axis; the same points and seed give the same field."""
    rng = np.random.default_rng([seed, 31337])
    directions = rng.normal(size=(DISPLACEMENT_WAVES, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    phases = rng.uniform(0.0, 2.0 * np.pi, size=(DISPLACEMENT_WAVES, 3))
    angles = (points @ directions.T * (2.0 * np.pi / wavelength))[:, :, None] + phases[None]  # [N, K, 3]
    return rms * np.sqrt(2.0 / DISPLACEMENT_WAVES) * np.sin(angles).sum(axis=1)


def new_view_poses(cam_from_world: Array, depth: Array, lift: float, per_gap: int = 1) -> Array:
    """[(N - 1) * per_gap, 3, 4] views between neighbouring cameras `cam_from_world` [N, 3, 4] (ordered along the path),
    `per_gap` evenly spaced in each gap: rotation interpolated (slerp), centre interpolated and lifted by `lift` along
    the cameras' mean up, turned down to look at the point that the interpolated camera saw at its neighbours' mean
    scene depth `depth` [N]."""
    centres = camera_centres(cam_from_world)
    up = -np.mean(cam_from_world[:, 1, :3], axis=0)  # OpenCV y points down; row 1 of R_cw is the camera's y in world
    up /= np.linalg.norm(up)
    views = []
    for i in range(len(cam_from_world) - 1):
        between = Slerp([0.0, 1.0], Rotation.from_matrix(cam_from_world[i:i + 2, :, :3]))
        for fraction in np.arange(1, per_gap + 1) / (per_gap + 1):
            rotation = between(fraction).as_matrix()  # world -> camera
            centre = (1.0 - fraction) * centres[i] + fraction * centres[i + 1]
            target = centre + 0.5 * (depth[i] + depth[i + 1]) * rotation[2]  # the optical axis in world is row 2
            lifted = centre + lift * up
            rotation = look_at(lifted, target, rotation)
            views.append(np.concatenate([rotation, (-rotation @ lifted)[:, None]], axis=1))
    return np.stack(views) if views else np.zeros((0, 3, 4))


def look_at(centre: Array, target: Array, rotation: Array) -> Array:
    """World -> camera rotation of a camera at `centre` whose optical axis points at `target`, turned from `rotation`
    [3, 3] by the smallest rotation that does it (so it keeps its roll)."""
    axis = target - centre
    axis /= np.linalg.norm(axis)
    turn, _ = Rotation.align_vectors(axis[None], rotation[2][None])
    return rotation @ turn.as_matrix().T


def median_depths(cam_from_world: Array, points: Array) -> Array:
    """[N] median depth of the `points` [M, 3] in front of each camera [N, 3, 4] (1 where none is)."""
    depths = np.einsum("nij,mj->nmi", cam_from_world[:, :, :3], points)[..., 2] + cam_from_world[:, None, 2, 3]
    return np.asarray([np.median(d[d > 0]) if np.any(d > 0) else 1.0 for d in depths])


def render_view(model: CoarseModel, camera: pycolmap.Camera, cam_from_world: Array, settings: CoarseModelSettings) -> Image.Image:
    """The coarse model from a pinhole `camera` (its distortion ignored) at `cam_from_world` [3, 4] (scene world),
    finished with the look of `settings`."""
    reference = model.reference
    scale = float(reference.world_to_dataparser.scale)
    pose = np.asarray(reference.world_to_dataparser.move_camera(np.asarray(cam_from_world, np.float64)))
    viewmat = torch.eye(4)
    viewmat[:3] = torch.from_numpy(pose).float()
    K = torch.from_numpy(np.asarray(camera.calibration_matrix(), np.float32))
    with torch.no_grad():
        rendered, alpha = reference.render_rgb(viewmat[None], K[None], int(camera.width), int(camera.height), near_plane=0.01 * scale, with_depth=True)
    rgb = rendered[0, ..., :3].numpy().astype(np.float64)
    depth = np.where(alpha[0, ..., 0].numpy() > 0.5, rendered[0, ..., 3].numpy() / (scale * model.depth), np.inf)
    return Image.fromarray(np.clip(finish(rgb, depth, settings) * 255.0 + 0.5, 0, 255).astype(np.uint8))


def finish(rgb: Array, depth: Array, settings: CoarseModelSettings) -> Array:
    """[H, W, 3] render in [0, 1] with its depth [H, W] (shares of the scene depth, inf = background) -> the
    Google-Earth-like look."""
    grey = rgb.mean(axis=2, keepdims=True)
    saturated = grey + settings.saturation * (rgb - grey)
    return ReferenceLook(saturation=1.0, tint=settings.tint, haze=settings.haze).finish(saturated, depth)


@contextlib.contextmanager
def quiet_nerfstudio() -> Iterator[None]:
    """nerfstudio's console lines, prints and deprecation warnings (config saved, logging events, dataparser notes, torch's
    GradScaler) held back: the coarse model is a step of the builder, whose own status line says what it does."""
    from nerfstudio.utils.rich_utils import CONSOLE

    was = CONSOLE.quiet
    CONSOLE.quiet = True
    try:
        with contextlib.redirect_stdout(io.StringIO()), warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)
            yield
    finally:
        CONSOLE.quiet = was
