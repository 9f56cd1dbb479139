"""Anchors from one spot, the stress study: twin copies of a benchmark, registered with the anchors of a photo and its twin.

Internet photos are often taken from the same few spots. A photo and a zoomed-in one from where it was taken fix the
Sim(3)'s scale no better than one photo: scaling the world about their shared camera centre moves neither image. This
study checks that the registration notices (`keypoints.anchors_fix_scale`: the camera fit then leaves the scale to the
dense objective, `scale_search.scale_the_anchors_leave_free`, and the verdict probes it) on real meta-images:

1. `build_twins` copies every scene of a benchmark (layout: bench/layout.py; the reference linked, not copied) and gives
   each meta-image a twin of its photo with the most keypoint correspondences (A): A cropped to its central `zoom`
   and enlarged back to A's size, with A's pose, A's camera with the focal lengths / `zoom` and A's observations mapped
   into it (`add_twin`). The ground truth is unchanged. Each meta-image directory records the pair in `twin.json`.
2. The benchmark then runs as `sg-bench` does, with the keypoint anchors of A and its twin only (`TwinSceneRunner`):
   the other photos still enter the dense objective, but give no anchors.

    sg-bench real-scenes --twin-anchors real-twins --output twin-results --initialisers --noise-levels 5 15 30 --noise-samples 2

Figures: docs/measurements.md, "Anchors from one spot" and "The camera adjustment, re-tested".
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Optional

import numpy as np
import pycolmap
from PIL import Image
from rich.console import Console

from sg_nerfstudio.bench.layout import read_benchmark
from sg_nerfstudio.bench.runs import SceneRunner
from sg_nerfstudio.errors import InputError
from sg_nerfstudio.geometry.meta_image import load_meta_image
from sg_nerfstudio.initialisers import Initialiser, InitialiserSettings, ReferenceSource
from sg_nerfstudio.initialisers.estimate import PhotoKeypoints

ZOOM = 0.8
"""The twin's crop: this fraction of its photo's width and height, about the centre."""
TWIN_PREFIX = "twin_"
"""A twin's file name is this prefix and its photo's."""


def add_twin(meta: Path, output: Path, photo: str, zoom: float = ZOOM) -> str:
    """Copy the meta-image directory `meta` (images/ + sparse/0 + gt_transform.json) to `output`, adding the twin of
    `photo` (module docstring); returns the twin's name. The crop is about the image centre, so every pixel xy of the
    photo is (xy - centre) / zoom + centre in the twin: the twin's camera is a copy of the photo's with every focal
    length divided by `zoom` and its principal point moved by that map (distortion unchanged: it acts on the same
    normalised coordinates), and each of the photo's observations with a 3-D point that stays inside the crop is an
    observation of the twin there."""
    shutil.copytree(meta, output)
    model = pycolmap.Reconstruction(output / "sparse" / "0")
    original = model.find_image_with_name(photo)
    if original is None:
        raise InputError(f"{photo} is not a photo of the meta-image {meta}; expected one of its images.")
    camera = model.cameras[original.camera_id]
    twin_camera = pycolmap.Camera(camera.todict())
    twin_camera.camera_id = max(model.cameras) + 1
    centre = np.array([camera.width, camera.height], dtype=np.float64) / 2
    params = np.array(camera.params)
    params[list(camera.focal_length_idxs())] /= zoom
    principal = list(camera.principal_point_idxs())
    params[principal] = (params[principal] - centre) / zoom + centre
    twin_camera.params = params
    model.add_camera_with_trivial_rig(twin_camera)
    points2D, observed = [], []
    for observation in original.points2D:
        xy = (np.asarray(observation.xy) - centre) / zoom + centre
        if observation.has_point3D() and 0 <= xy[0] < camera.width and 0 <= xy[1] < camera.height:
            observed.append((len(points2D), observation.point3D_id))
            points2D.append(pycolmap.Point2D(xy))
    name = TWIN_PREFIX + photo
    twin = pycolmap.Image(name=name, points2D=pycolmap.Point2DList(points2D), camera_id=twin_camera.camera_id, image_id=max(model.images) + 1)
    model.add_image_with_trivial_frame(twin, original.cam_from_world())
    for index, point_id in observed:
        model.add_observation(point_id, pycolmap.TrackElement(twin.image_id, index))
    model.write(output / "sparse" / "0")
    with Image.open(meta / "images" / photo) as image:
        width, height = image.size
        crop = [width * (1 - zoom) / 2, height * (1 - zoom) / 2, width * (1 + zoom) / 2, height * (1 + zoom) / 2]
        # EXTENT takes the fractional box as it is (crop() would round it to whole pixels, off the mapped observations)
        image.convert("RGB").transform((width, height), Image.Transform.EXTENT, crop, Image.Resampling.BICUBIC).save(output / "images" / name, quality=95)
    (output / "twin.json").write_text(json.dumps({"photo": photo, "twin": name, "zoom": zoom}, indent=2))
    return name


def build_twins(benchmark: Path, output: Path, zoom: float = ZOOM, console: Optional[Console] = None) -> None:
    """Twin copies of every scene of `benchmark` under `output` (module docstring, step 1). Each meta-image's copy is
    written beside its place and renamed into it when complete, so copies already made (an interrupted build) are kept
    and nothing half-written is left; a scene gets its directory only with its first copy."""
    for scene in read_benchmark(benchmark):
        target = output / scene.name
        initialiser = Initialiser(ReferenceSource(scene.reference / scene.reference_model, scene.reference / "images"), InitialiserSettings())
        for meta in scene.metas:
            copy = target / "meta" / meta.directory.name
            if copy.is_dir():
                continue
            counts = {k.name: len(k.points2D) for k in initialiser.keypoints(load_meta_image(meta.directory))}
            if not counts or max(counts.values()) == 0:
                raise InputError(f"No photo of {meta.directory} has keypoint correspondences with its reference; expected one to copy as a twin.")
            photo = max(counts, key=counts.get)
            copy.parent.mkdir(parents=True, exist_ok=True)
            if not (target / "reference").exists():
                (target / "reference").symlink_to(scene.reference.resolve(), target_is_directory=True)
            partial = copy.with_name(copy.name + ".partial")
            shutil.rmtree(partial, ignore_errors=True)
            add_twin(meta.directory, partial, photo, zoom)
            partial.rename(copy)
            if console:
                console.print(f"{scene.name}/{meta.directory.name}: twin of {photo} ({counts[photo]} correspondences)")


class TwinSceneRunner(SceneRunner):
    """`SceneRunner` with the keypoint anchors of each twin and its photo only (module docstring, step 2)."""

    def keypoints(self, subject, settings) -> list[PhotoKeypoints]:
        twins = {photo.name for photo in subject.photos if photo.name.startswith(TWIN_PREFIX)}
        kept = twins | {name[len(TWIN_PREFIX):] for name in twins}
        return [k for k in super().keypoints(subject, settings) if k.name in kept]
