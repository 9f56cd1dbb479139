"""Full-image datamanager that also serves each image's cached teacher feature map.

Extends nerfstudio's `FullImageDatamanager`: it checks that every image file exists, builds the teacher,
computes or loads from the on-disk cache the teacher map of every cached (undistorted) image, and
stores it in the image's cache entry, so every batch (`next_train`, `next_eval`, the eval loader) carries
`batch["teacher_features"]` [rows, columns, D]. In training ("val" mode) this happens at start-up, so a
missing image or an unloadable teacher fails early; for ns-viewer / ns-eval ("test") on the first batch
that needs them; never for rendering ("inference"). On a CPU device images are cached on that device rather than
in pinned memory (pinning needs CUDA).

The teacher's output width and grid size and a feature sample for the model's fixed PCA colouring go to
the model through `train_dataset.metadata` ("teacher_feature_dim", "teacher_grid_size",
"teacher_feature_sample").
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional, Type, Union

import torch

from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanager, FullImageDatamanagerConfig

from sg_nerfstudio.errors import InputError
from sg_nerfstudio.features import FeatureCache, TeacherConfig, build_teacher, extract_all, teacher_feature_dim, teacher_grid_size
from sg_nerfstudio.geometry.meta_image import COLMAP_LAYOUTS, decoded_size, holds_colmap_model, model_below

PCA_SAMPLE_SIZE = 20000
MIN_SEED_POINTS = 4
"""Fewest SfM points the Gaussians can start from (each one's initial scale comes from its 3 nearest neighbours)."""


class DatasetInputError(InputError):
    """A dataset the datamanager cannot train on."""


def check_colmap_model(config: "FeatureDatamanagerConfig") -> None:
    """Stop with one sentence when the COLMAP model that nerfstudio's colmap dataparser reads (`data / colmap_path`) is
    missing, naming the models the folder does hold and the flag that picks one (the dataparser's own assertion
    otherwise ends `ns-train` in a traceback)."""
    parser = config.dataparser
    if not hasattr(parser, "colmap_path"):
        return
    data = Path(config.data) if config.data is not None else Path(parser.data)  # as FullImageDatamanager resolves it
    model = data / parser.colmap_path
    if holds_colmap_model(model):
        return
    found = model_below(data)
    hint = (f"this folder has one in {found}: add `--colmap-path {found.relative_to(data)}` after `colmap`" if found
            else f"expected cameras, images and points3D (.bin or .txt) there, or a folder whose model is in {' or '.join(str(layout) for layout in COLMAP_LAYOUTS[:2])}")
    raise DatasetInputError(f"No COLMAP model in {model}; {hint}.")


def check_dataset(config: "FeatureDatamanagerConfig") -> None:
    """The COLMAP model exists, has points to seed the Gaussians, and every image of it that is on disk decodes. Run
    by the trainer config before nerfstudio writes anything (`method.FeatureSplatTrainerConfig.save_config`) and
    again by the datamanager (for callers that build it directly)."""
    check_colmap_model(config)
    check_seed_points(config)
    check_images_decode(config)


def check_images_decode(config: "FeatureDatamanagerConfig") -> None:
    """Stop with one sentence when images the COLMAP model lists are missing (or their folder is), or on the first one
    that cannot be decoded whole (a truncated JPEG or PNG): nerfstudio's datamanager otherwise fails on them with a
    traceback, after `ns-train` has written the run's config.yml."""
    parser = config.dataparser
    if not hasattr(parser, "colmap_path") or not hasattr(parser, "images_path"):
        return
    data = Path(config.data) if config.data is not None else Path(parser.data)  # as FullImageDatamanager resolves it
    model, folder = data / parser.colmap_path, data / parser.images_path
    names = colmap_image_names(model)
    if names and not folder.is_dir():
        raise DatasetInputError(f"The image folder {folder} does not exist; expected the {len(names)} images the COLMAP model {model} lists there.")
    missing = [name for name in names if not (folder / name).is_file()]
    if missing:
        shown = ", ".join(missing[:3]) + (" ..." if len(missing) > 3 else "")
        raise DatasetInputError(
            f"{len(missing)} of the {len(names)} images the COLMAP model {model} lists are missing from {folder} ({shown}); "
            "expected every image the model lists."
        )
    for name in names:
        path = folder / name
        try:
            decoded_size(path)
        except Exception as error:
            raise DatasetInputError(
                f"Image {path} of the COLMAP model {model} could not be read as an image ({error}); expected a complete JPEG "
                "or PNG (replace the file, or remove the image from the model)."
            ) from None


def colmap_image_names(model: Path) -> list[str]:
    """Names of the images a COLMAP model lists (images.bin or images.txt, read with nerfstudio's own parser, without
    the points); [] when neither file exists."""
    from nerfstudio.data.utils.colmap_parsing_utils import read_images_binary, read_images_text

    if (model / "images.bin").is_file():
        return [image.name for image in read_images_binary(model / "images.bin").values()]
    if (model / "images.txt").is_file():
        return [image.name for image in read_images_text(model / "images.txt").values()]
    return []


def check_seed_points(config: "FeatureDatamanagerConfig") -> None:
    """Stop with one sentence when the COLMAP model the Gaussians start from has (almost) no 3D points
    (nerfstudio's colmap dataparser otherwise fails deep inside with a tensor-shape error)."""
    parser = config.dataparser
    if not getattr(parser, "load_3D_points", False) or not hasattr(parser, "colmap_path"):
        return
    data = Path(config.data) if config.data is not None else Path(parser.data)  # as FullImageDatamanager resolves it
    count = count_points3D(data / parser.colmap_path)
    if count is None:
        return  # no points file: the dataparser names the missing file itself
    if count < MIN_SEED_POINTS:
        raise DatasetInputError(
            f"The COLMAP model {data / parser.colmap_path} has {count} 3D points; sg-feature-splat starts its Gaussians from them and needs "
            f"at least {MIN_SEED_POINTS} (triangulate the images with known poses, e.g. COLMAP's point_triangulator)."
        )


def count_points3D(model: Path) -> Optional[int]:
    """Number of 3D points of a COLMAP model from its points3D file alone (the binary header, or the data lines
    of the text file), without loading the model; None when neither file exists."""
    binary, text = model / "points3D.bin", model / "points3D.txt"
    if binary.is_file():
        with binary.open("rb") as handle:
            header = handle.read(8)
        return int.from_bytes(header, "little") if len(header) == 8 else 0
    if text.is_file():
        with text.open() as handle:
            return sum(1 for line in handle if line.strip() and not line.startswith("#"))
    return None


@dataclass
class FeatureDatamanagerConfig(FullImageDatamanagerConfig):
    _target: Type = field(default_factory=lambda: FeatureDatamanager)
    teacher: TeacherConfig = field(default_factory=TeacherConfig)
    """The 2D feature extractor distilled into the splat."""
    cache_images_type: Literal["uint8", "float32"] = "uint8"


class FeatureDatamanager(FullImageDatamanager):
    config: FeatureDatamanagerConfig

    def __init__(
        self,
        config: FeatureDatamanagerConfig,
        device: Union[torch.device, str] = "cpu",
        test_mode: Literal["test", "val", "inference"] = "val",
        world_size: int = 1,
        local_rank: int = 0,
        **kwargs,
    ):
        check_dataset(config)
        super().__init__(config, device=device, test_mode=test_mode, world_size=world_size, local_rank=local_rank, **kwargs)
        if torch.device(device).type == "cpu":
            self.config.cache_images = "gpu"  # i.e. "on the training device": no pinned memory without CUDA
        self.train_dataset.metadata["teacher_feature_dim"] = teacher_feature_dim(config.teacher)
        self.train_dataset.metadata["teacher_grid_size"] = teacher_grid_size(config.teacher)
        self._features_ready = False
        if test_mode == "val":  # training: fail early on missing images or an unloadable teacher
            self._ensure_teacher_features()
            self.train_dataset.metadata["teacher_feature_sample"] = self._feature_sample()
        # "test" (ns-viewer, ns-eval) computes them on the first batch; "inference" (rendering) never

    def _ensure_teacher_features(self) -> None:
        if self._features_ready:
            return
        self._check_images_exist()
        teacher = build_teacher(self.config.teacher)
        cache = FeatureCache(self.config.teacher.cache_dir)
        for split, cached in (("train", self.cached_train), ("eval", self.cached_eval)):
            maps = extract_all(lambda i, c=cached: c[i]["image"], len(cached), teacher, cache, f"Teacher features ({split})")
            for entry, features in zip(cached, maps):
                entry["teacher_features"] = features
        self._features_ready = True

    def next_train(self, step: int):
        self._ensure_teacher_features()
        return super().next_train(step)

    def next_eval_image(self, step: int):
        self._ensure_teacher_features()
        return super().next_eval_image(step)

    @property
    def fixed_indices_eval_dataloader(self):
        self._ensure_teacher_features()
        return super().fixed_indices_eval_dataloader

    def _check_images_exist(self) -> None:
        for split, dataset in (("train", self.train_dataset), ("eval", self.eval_dataset)):
            missing = [Path(p) for p in dataset.image_filenames if not Path(p).is_file()]
            if missing:
                shown = ", ".join(p.name for p in missing[:3]) + (" ..." if len(missing) > 3 else "")
                raise DatasetInputError(
                    f"{len(missing)} of the {len(dataset.image_filenames)} {split} images listed by the COLMAP model "
                    f"are missing from {missing[0].parent} ({shown}); expected every image the model lists."
                )

    def _feature_sample(self) -> torch.Tensor:
        """[<= PCA_SAMPLE_SIZE, D] teacher vectors drawn evenly from the training maps."""
        vectors = torch.cat([entry["teacher_features"].reshape(-1, entry["teacher_features"].shape[-1]) for entry in self.cached_train])
        step = max(1, vectors.shape[0] // PCA_SAMPLE_SIZE)
        return vectors[::step][:PCA_SAMPLE_SIZE].clone()
