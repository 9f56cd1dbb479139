"""Photos -> meta-images: the paper's input, "partial 3D reconstructions produced by running structure from
motion on Internet images", written in the layout `ns-register-meta` reads.

    <output>/meta-00/images/           the working photos of the largest model (EXIF-upright, capped size)
    <output>/meta-00/sparse/0/         its COLMAP model (binary), its own frame and scale
    <output>/meta-01/ ...              every further model of at least 3 photos, largest first
    <output>/meta_images.json          models (photos, points, reprojection error), pairing, and every photo
                                       that no model holds with the reason
    <output>/sfm/database.db           the COLMAP database (features, matches) for inspection

The output directory appears whole or not at all (`atomic_directory`); the photo folder is only read.
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Optional

import pycolmap

from sg_nerfstudio.atomic import atomic_directory, check_new_output_directory
from sg_nerfstudio.photos.collection import list_photos, prepare_photos, same_pictures
from sg_nerfstudio.photos.sfm import ReconstructionError, SfmResult, SfmSettings, reconstruct


@dataclass(frozen=True)
class ModelSummary:
    name: str
    photos: int
    points: int
    reprojection_error_px: float
    mean_track_length: float


def model_summary(name: str, model: pycolmap.Reconstruction) -> ModelSummary:
    return ModelSummary(
        name, model.num_reg_images(), model.num_points3D(), float(model.compute_mean_reprojection_error()),
        float(model.compute_mean_track_length()) if model.num_points3D() else 0.0,
    )


def write_model(model: pycolmap.Reconstruction, images: Path, directory: Path) -> None:
    """`directory/images/` (copies of the model's photos) and `directory/sparse/0/` (the model, binary)."""
    (directory / "images").mkdir(parents=True)
    for image_id in model.reg_image_ids():
        name = model.images[image_id].name
        shutil.copy2(images / name, directory / "images" / name)
    (directory / "sparse" / "0").mkdir(parents=True)
    model.write_binary(str(directory / "sparse" / "0"))


def build_meta_images(
    photos: Path, output: Path, max_size: Optional[int], settings: SfmSettings, overwrite: bool = False,
    stage: Optional[Callable[[str], None]] = None, on_photo: Optional[Callable[[], None]] = None,
) -> tuple[list[ModelSummary], SfmResult]:
    """Run SfM on the photo folder `photos` and write one meta-image per model into `output` (see module doc)."""
    started = time.perf_counter()
    sources = list_photos(photos)
    check_new_output_directory(output, overwrite, inputs=[photos])
    with atomic_directory(output, overwrite=overwrite) as staging:
        working = staging / "sfm" / "images"
        prepared = prepare_photos(sources, working, max_size, on_photo)
        result = reconstruct(working, [p.name for p in prepared], staging / "sfm", settings, stage)
        if not result.models:
            copies = same_pictures(sources)
            reasons = copies or "; ".join(f"{name}: {reason}" for name, reason in result.unregistered()[:3])
            expected = "different views of one place" if copies else "overlapping photos of one place"
            raise ReconstructionError(
                f"The {len(prepared)} photos of {photos} formed no model of at least {settings.min_model_size} photos "
                f"({reasons}); expected {expected}."
            )
        summaries = []
        for index, model in enumerate(result.models):
            name = f"meta-{index:02d}"
            write_model(model, working, staging / name)
            summaries.append(model_summary(name, model))
        record = {
            "photos": str(Path(photos).resolve()),
            "max_size": max_size,
            "sfm": asdict(settings),
            "pairing": result.pairing,
            "models": [asdict(s) | {"images": sorted(result.models[i].images[j].name for j in result.models[i].reg_image_ids())}
                       for i, s in enumerate(summaries)],
            "unregistered": [{"photo": name, "reason": reason} for name, reason in result.unregistered()],
            "wall_time_s": round(time.perf_counter() - started, 2),
        }
        shutil.rmtree(staging / "sfm" / "models", ignore_errors=True)
        (staging / "meta_images.json").write_text(json.dumps(record, indent=2))
    return summaries, result
