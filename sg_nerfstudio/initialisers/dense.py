"""A start without SIFT: each photo found among the reference's images by its teacher map, then one Sim(3) that most
photos agree with.

Where the reference is a model trained on renders (the paper's Google Earth references; docs/gap-scenes.md), SIFT
rarely matches a photo to it and the SIFT initialisers (pipeline.py) fail. A weight-free teacher's map still tells
which reference image shows what a photo shows, and where, at a coarse level:

1. `ReferenceMaps`: every reference image described by the teacher at several scales (`DenseInitSettings.focal_cells`:
   the image resized so that its focal length spans that many cells), features projected on their first `dimensions`
   principal components (fitted on the reference's own maps);
2. `placements`: each photo's map (`photo_cells` cells on its long side) slid over every reference map at every scale by
   normalised cross-correlation (torch conv2d); per reference image, the best placement: its score, the scale and where
   the photo's centre lands;
3. `camera_hypothesis`: each of a photo's `candidates` best reference images proposes a camera: the reference camera
   turned to look where the photo's centre landed, moved along that direction so that the scene appears at the photo's
   scale (the reference image's median point depth times photo focal / reference focal at the scale);
4. `consensus_similarity`: every two hypotheses of different photos give a Sim(3) through the photos' poses in the
   meta-image (`geometry.alignment.align_cameras`); a photo agrees with it when one of its hypotheses lies within
   `max_rotation_deg` and `max_centre_error` of where it puts the photo; the Sim(3) whose agreeing photos have the
   highest summed score is refitted on them.

Why by hand: retrieval libraries (hloc's NetVLAD, DINOv2-based ones) need network weights this project cannot download,
and none places a query by sliding a dense descriptor map over scales; the pieces it uses (teacher maps, conv2d,
`align_cameras`) are the project's and torch's.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

import cv2
import numpy as np
import pycolmap
import torch
import torch.nn.functional as F

from sg_nerfstudio.errors import InputError
from sg_nerfstudio.features import TeacherConfig, build_teacher
from sg_nerfstudio.geometry.alignment import AlignmentError, align_cameras, camera_centres, camera_residuals
from sg_nerfstudio.geometry.meta_image import MetaImage
from sg_nerfstudio.geometry.sim3 import Sim3

Array = np.ndarray


class DenseInitError(InputError):
    """A reference the dense initialiser cannot use."""


@dataclass(frozen=True)
class DenseInitSettings:
    """Settings of the dense initialiser (module docstring)."""

    teacher: Literal["offline", "dense-sift", "hog-layout"] = "hog-layout"
    """Weight-free teacher whose maps are compared (hog-layout: made for photos against renders)."""
    photo_cells: int = 16
    """Cells on the long side of a photo's map: coarse, as the placement only has to land within the registration's reach."""
    focal_cells: tuple[float, ...] = tuple(float(v) for v in np.geomspace(6.0, 48.0, 12))
    """Scales a reference image is described at: its focal length in cells (a photo's is `photo_cells` times its
    focal / long side; the range covers photos from about half to three times a reference view's distance)."""
    dimensions: int = 24
    """Principal components of the teacher's features kept for the correlation."""
    min_overlap: float = 0.6
    """Smallest share of the photo's map that must lie on the reference image at a placement."""
    candidates: int = 8
    """Reference images (each its best placement) that propose a camera for each photo ..."""
    proposing: int = 3
    """... of which the best this many pair up with other photos' to propose a Sim(3) (all `candidates` are checked
    against each): the pairs grow with the square of the photos, 32 photos take seconds instead of minutes."""
    max_rotation_deg: float = 12.0
    """A photo agrees with a Sim(3) when one of its hypotheses is within this angle ..."""
    max_centre_error: float = 0.3
    """... and this distance, a share of the median distance of the reference cameras to their centroid."""
    min_agreeing: int = 3
    """Fewest photos that must agree on the Sim(3). Two agree by chance too often: five photos of flat grey and noise
    gave a "start" that two of them agreed with (their placements score as high as real photos')."""


@dataclass
class ReferenceView:
    """One reference image: its camera, pose and the median depth of the reference points it observes."""

    name: str
    camera: pycolmap.Camera
    cam_from_world: Array  # [3, 4]
    depth: float


@dataclass
class Placement:
    """Where a photo's map fits one reference view best."""

    view: int
    score: float
    focal_cells: float
    centre: Array  # [2] pixel of the reference image where the photo's centre lands (COLMAP convention)


@dataclass
class DenseStart:
    transform: Optional[Sim3]
    agreeing_photos: list[str]
    hypotheses: dict[str, list[Placement]]
    failure: Optional[str] = None


def read_rgb(path: Path) -> torch.Tensor:
    """[H, W, 3] float32 RGB in [0, 1]."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    return torch.from_numpy(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0)


def mean_focal(camera: pycolmap.Camera) -> float:
    matrix = camera.calibration_matrix()
    return float(0.5 * (matrix[0, 0] + matrix[1, 1]))


class ReferenceMaps:
    """The reference's images described at every scale, once per reference (module docstring, step 1)."""

    def __init__(self, reconstruction: pycolmap.Reconstruction, images_path: Path, settings: DenseInitSettings):
        self.settings = settings
        self.teacher = build_teacher(TeacherConfig(name=settings.teacher, device="cpu"))
        self.views = [view for image in reconstruction.images.values() if (view := _view(reconstruction, image)) is not None]
        if len(self.views) < 2:
            raise DenseInitError(
                f"The dense initialiser needs reference images that observe the reference's 3D points (for their depth); "
                f"{len(self.views)} of the model's {reconstruction.num_reg_images()} images do."
            )
        centres = camera_centres(np.stack([view.cam_from_world for view in self.views]))
        self.spread = float(np.median(np.linalg.norm(centres - centres.mean(0), axis=1)))
        middle = settings.focal_cells[len(settings.focal_cells) // 2]
        sample = torch.cat([self._describe(Path(images_path) / view.name, view.camera, middle).reshape(-1, self.teacher.feature_dim) for view in self.views])
        self.mean = sample.mean(0)
        centred = (sample - self.mean).double()
        _, vectors = torch.linalg.eigh(centred.T @ centred)  # exact and deterministic (pca_lowrank is randomised)
        self.basis = vectors[:, -min(settings.dimensions, sample.shape[1]):].flip(1).float()
        # Each image described and projected at once: its 324-d maps at every scale would take gigabytes for a large reference.
        projected = [[self.project(m) for m in self._describe_all(Path(images_path) / view.name, view.camera)] for view in self.views]
        self.stacks: list[list[tuple[list[int], torch.Tensor]]] = []
        """Per scale: (view indices, their projected maps [n, dimensions, rows, columns]) for each map size."""
        for scale in range(len(settings.focal_cells)):
            by_shape: dict[tuple, list[int]] = {}
            for index in range(len(self.views)):
                by_shape.setdefault(tuple(projected[index][scale].shape), []).append(index)
            self.stacks.append([(indices, torch.stack([projected[i][scale] for i in indices])) for indices in by_shape.values()])

    def _describe_all(self, path: Path, camera: pycolmap.Camera) -> list[torch.Tensor]:
        image = read_rgb(path)
        return [self._describe(image, camera, cells) for cells in self.settings.focal_cells]

    def _describe(self, image: torch.Tensor | Path, camera: pycolmap.Camera, cells: float) -> torch.Tensor:
        """[rows, columns, F] teacher map of the image (or image file) resized so that its focal length spans `cells`."""
        image = read_rgb(image) if isinstance(image, Path) else image
        scale = cells / mean_focal(camera)  # cells per pixel
        grid = (max(2, round(image.shape[0] * scale)), max(2, round(image.shape[1] * scale)))
        return self.teacher.describe(image, grid=grid)

    def project(self, teacher_map: torch.Tensor) -> torch.Tensor:
        """[rows, columns, F] teacher map -> [dimensions, rows, columns]."""
        return ((teacher_map - self.mean) @ self.basis).permute(2, 0, 1).contiguous()

    def photo_map(self, image: torch.Tensor) -> tuple[torch.Tensor, float]:
        """A photo's projected map [dimensions, rows, columns] and its cells per pixel."""
        long_side = max(image.shape[:2])
        grid = (max(2, round(self.settings.photo_cells * image.shape[0] / long_side)), max(2, round(self.settings.photo_cells * image.shape[1] / long_side)))
        return self.project(self.teacher.describe(image, grid=grid)), grid[1] / image.shape[1]


def _view(reconstruction: pycolmap.Reconstruction, image) -> Optional[ReferenceView]:
    pose = image.cam_from_world().matrix()
    ids = [point.point3D_id for point in image.points2D if point.has_point3D()]
    if not ids:
        return None
    points = np.array([reconstruction.points3D[i].xyz for i in ids])
    depths = (points @ pose[:, :3].T + pose[:, 3])[:, 2]
    depths = depths[depths > 0]
    if not len(depths):
        return None
    return ReferenceView(image.name, reconstruction.cameras[image.camera_id], pose, float(np.median(depths)))


def placements(photo_map: torch.Tensor, reference: ReferenceMaps) -> list[Placement]:
    """The best placement of `photo_map` [D, h, w] on each reference view over all scales, best first (step 2): one
    conv2d per scale and size of reference map (`ReferenceMaps.stacks`)."""
    kernel = photo_map / photo_map.norm().clamp_min(1e-12)
    _, h, w = kernel.shape
    padding = (w // 2, w // 2, h // 2, h // 2)
    ones = torch.ones(1, 1, h, w)
    best: dict[int, Placement] = {}
    for cells, stacks in zip(reference.settings.focal_cells, reference.stacks):
        for indices, maps in stacks:  # maps: [n, D, rows, columns], views of one map size
            padded = F.pad(maps, padding)
            correlation = F.conv2d(padded, kernel[None])[:, 0]
            energy = F.conv2d(padded.pow(2).sum(1, keepdim=True), ones)[:, 0].clamp_min(1e-12).sqrt()
            overlap = F.conv2d(F.pad(torch.ones(1, 1, *maps.shape[2:]), padding), ones)[0, 0]
            score = torch.where(overlap >= reference.settings.min_overlap * h * w, correlation / energy, torch.tensor(-1.0))
            values, flat = score.flatten(1).max(dim=1)
            for index, value, position in zip(indices, values.tolist(), flat.tolist()):
                if index in best and value <= best[index].score:
                    continue
                row, column = divmod(position, score.shape[2])
                per_pixel = cells / mean_focal(reference.views[index].camera)
                # The photo's centre sits at cell (row - h // 2 + h / 2, column - w // 2 + w / 2) of the unpadded map.
                centre = np.array([column - w // 2 + w / 2, row - h // 2 + h / 2]) / per_pixel
                best[index] = Placement(index, value, cells, centre)
    return sorted(best.values(), key=lambda p: -p.score)


def camera_hypothesis(placement: Placement, reference: ReferenceMaps, photo_focal_cells: float) -> Array:
    """The photo's [3, 4] cam_from_world in the reference world proposed by one placement (step 3)."""
    view = reference.views[placement.view]
    ray = np.append(view.camera.cam_from_img(placement.centre[None])[0], 1.0)
    ray /= np.linalg.norm(ray)
    axis = np.cross([0.0, 0.0, 1.0], ray)
    angle = float(np.arcsin(np.clip(np.linalg.norm(axis), 0.0, 1.0)))
    turn = cv2.Rodrigues(axis / np.linalg.norm(axis) * angle)[0] if angle > 1e-9 else np.eye(3)
    rotation = turn.T @ view.cam_from_world[:, :3]  # the photo's z axis is the ray
    centre = -view.cam_from_world[:, :3].T @ view.cam_from_world[:, 3]
    photo_depth = view.depth * photo_focal_cells / placement.focal_cells
    centre = centre + (view.depth - photo_depth) * (rotation.T @ np.array([0.0, 0.0, 1.0]))
    return np.concatenate([rotation, (-rotation @ centre)[:, None]], axis=1)


def consensus_similarity(
    cam_from_meta: Array, hypotheses: list[tuple[int, Array, float]], max_rotation_deg: float, max_centre_error: float,
    proposing: Optional[int] = None,
) -> Optional[tuple[Sim3, list[int]]]:
    """The Sim(3) meta -> reference most photos agree with (step 4), refitted on them, and those photos' indices.

    Args:
        cam_from_meta: [P, 3, 4] the photos' poses in the meta-image.
        hypotheses: (photo index, [3, 4] cam_from_reference, score), each photo's best first.
        proposing: how many of each photo's first hypotheses propose similarities (None: all).
    """
    photo_of = np.array([h[0] for h in hypotheses])
    proposed = np.stack([h[1] for h in hypotheses])
    scores = np.array([h[2] for h in hypotheses])
    rank = np.array([sum(1 for earlier in photo_of[:row] if earlier == photo) for row, photo in enumerate(photo_of)])
    proposers = [row for row in range(len(hypotheses)) if proposing is None or rank[row] < proposing]
    best = None
    for position, a in enumerate(proposers):
        for b in proposers[position + 1:]:
            if photo_of[a] == photo_of[b]:
                continue
            try:
                transform = align_cameras(cam_from_meta[photo_of[[a, b]]], proposed[[a, b]]).transform
            except AlignmentError:
                continue
            agreeing = _agreeing(transform, cam_from_meta, photo_of, proposed, scores, max_rotation_deg, max_centre_error)
            total = sum(score for score, _ in agreeing.values())
            if len(agreeing) >= 2 and (best is None or total > best[0]):
                best = (total, agreeing)
    if best is None:
        return None
    rows = [row for _, row in best[1].values()]
    transform = align_cameras(cam_from_meta[photo_of[rows]], proposed[rows]).transform
    agreeing = _agreeing(transform, cam_from_meta, photo_of, proposed, scores, max_rotation_deg, max_centre_error)
    return transform, sorted(agreeing if len(agreeing) >= 2 else best[1])


def _agreeing(transform: Sim3, cam_from_meta, photo_of, proposed, scores, max_rotation_deg, max_centre_error) -> dict[int, tuple[float, int]]:
    """Photo index -> (score, row) of its best-scoring hypothesis among those near where `transform` puts it."""
    rotation, centre = camera_residuals(transform, cam_from_meta[photo_of], proposed)
    near = (rotation < max_rotation_deg) & (centre < max_centre_error)
    agreeing: dict[int, tuple[float, int]] = {}
    for row in np.nonzero(near)[0]:
        photo = int(photo_of[row])
        if photo not in agreeing or scores[row] > agreeing[photo][0]:
            agreeing[photo] = (float(scores[row]), int(row))
    return agreeing


def dense_start(meta: MetaImage, reference: ReferenceMaps) -> DenseStart:
    """The dense initialiser on one meta-image (module docstring)."""
    settings = reference.settings
    hypotheses, found = [], {}
    for index, photo in enumerate(meta.photos):
        photo_map, per_pixel = reference.photo_map(read_rgb(photo.path))
        ranked = placements(photo_map, reference)[: settings.candidates]
        found[photo.name] = ranked
        focal_cells = mean_focal(photo.camera) * per_pixel
        hypotheses += [(index, camera_hypothesis(p, reference, focal_cells), p.score) for p in ranked]
    cam_from_meta = np.stack([photo.cam_from_world for photo in meta.photos])
    consensus = consensus_similarity(
        cam_from_meta, hypotheses, settings.max_rotation_deg, settings.max_centre_error * reference.spread, settings.proposing
    )
    agreeing = consensus[1] if consensus is not None else []
    if len(agreeing) < settings.min_agreeing:
        return DenseStart(None, [], found, failure=(
            f"the placements of its {len(meta.photos)} photos among the reference images give no Sim(3) that at least "
            f"{settings.min_agreeing} of them agree with (best: {len(agreeing)})"
        ))
    transform = consensus[0]
    return DenseStart(transform, [meta.photos[i].name for i in agreeing], found)
