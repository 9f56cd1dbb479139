"""Teacher features: the 2D feature maps the feature splat distils and registration matches.

- `dinov2`: DINOv2 ViT-S/14 patch tokens (the paper's choice), weights from local files only;
- `offline`: a weight-free oriented-gradient descriptor, so everything runs without DINOv2;
- `dense-sift`: kornia's dense RootSIFT, weight-free and more discriminative than `offline` (compared in the
  docs/measurements.md, "Dense SIFT as the render teacher").
Maps are cached on disk per image content and settings (`cache.py`).
"""

from sg_nerfstudio.features.base import CellDescriptor, Teacher, TeacherConfig, TeacherInputError
from sg_nerfstudio.features.cache import FeatureCache, extract_all


def build_teacher(config: TeacherConfig) -> Teacher:
    """The extractor named by `config.name` (raises TeacherInputError with one sentence if it cannot load)."""
    if config.name == "dinov2":
        from sg_nerfstudio.features.dinov2 import Dinov2Teacher

        return Dinov2Teacher(config)
    if config.name in CELL_DESCRIPTORS:
        return _cell_descriptor(config.name)(config)
    raise TeacherInputError(f"Unknown teacher {config.name!r}; expected 'dinov2' or one of {', '.join(map(repr, CELL_DESCRIPTORS))}.")


CELL_DESCRIPTORS = ("offline", "dense-sift", "hog-layout")
"""The weight-free teachers."""


def _cell_descriptor(name: str) -> type[CellDescriptor]:
    """The class of a weight-free teacher (importing it loads no weights and no kornia)."""
    if name == "dense-sift":
        from sg_nerfstudio.features.dense_sift import DenseSiftTeacher

        return DenseSiftTeacher
    if name == "hog-layout":
        from sg_nerfstudio.features.hog_layout import HogLayoutTeacher

        return HogLayoutTeacher
    from sg_nerfstudio.features.offline import OfflineTeacher

    return OfflineTeacher


def _teacher_constants(name: str) -> tuple[int, int, int, str]:
    """(feature dim, default input size, patch/cell pixels, what the cell is called) of a teacher, without loading it."""
    if name == "dinov2":
        from sg_nerfstudio.features import dinov2

        return dinov2.FEATURE_DIM, dinov2.DEFAULT_INPUT_SIZE, dinov2.PATCH_SIZE, "DINOv2 patch size"
    kind = _cell_descriptor(name)
    return kind.feature_dim, kind.default_input_size, kind.cell, kind.cell_name


def teacher_feature_dim(config: TeacherConfig) -> int:
    """Output width of a teacher without loading it (needed to build a model for inference)."""
    return _teacher_constants(config.name)[0]


def teacher_input_size(config: TeacherConfig) -> int:
    """The long side the teacher resizes images to: `config.input_size` or the teacher's default."""
    return config.input_size or _teacher_constants(config.name)[1]


def teacher_grid_size(config: TeacherConfig) -> int:
    """Cells along the long side of the teacher's maps, without loading it (raises TeacherInputError with
    one sentence when the input size is not a multiple of the patch/cell size)."""
    from sg_nerfstudio.features.base import checked_grid

    _, _, cell, what = _teacher_constants(config.name)
    return checked_grid(teacher_input_size(config), cell, what)


__all__ = [
    "FeatureCache", "Teacher", "TeacherConfig", "TeacherInputError", "build_teacher", "extract_all", "teacher_feature_dim",
    "teacher_grid_size", "teacher_input_size",
]
