"""Teacher features: the 2D feature maps the feature splat distils and registration matches.

- `dinov2`: DINOv2 ViT-S/14 patch tokens (the paper's choice), weights from local files only;
- `offline`: a weight-free oriented-gradient descriptor, so everything runs without DINOv2.
Maps are cached on disk per image content and settings (`cache.py`).
"""

from sg_nerfstudio.features.base import Teacher, TeacherConfig, TeacherInputError
from sg_nerfstudio.features.cache import FeatureCache, extract_all


def build_teacher(config: TeacherConfig) -> Teacher:
    """The extractor named by `config.name` (raises TeacherInputError with one sentence if it cannot load)."""
    if config.name == "dinov2":
        from sg_nerfstudio.features.dinov2 import Dinov2Teacher

        return Dinov2Teacher(config)
    if config.name == "offline":
        from sg_nerfstudio.features.offline import OfflineTeacher

        return OfflineTeacher(config)
    raise TeacherInputError(f"Unknown teacher {config.name!r}; expected 'dinov2' or 'offline'.")


def teacher_feature_dim(config: TeacherConfig) -> int:
    """Output width of a teacher without loading it (needed to build a model for inference)."""
    from sg_nerfstudio.features.dinov2 import FEATURE_DIM
    from sg_nerfstudio.features.offline import OfflineTeacher

    return FEATURE_DIM if config.name == "dinov2" else OfflineTeacher.feature_dim


def teacher_grid_size(config: TeacherConfig) -> int:
    """Cells along the long side of the teacher's maps, without loading it (raises TeacherInputError with
    one sentence when the input size is not a multiple of the patch/cell size)."""
    from sg_nerfstudio.features import dinov2, offline
    from sg_nerfstudio.features.base import checked_grid

    if config.name == "dinov2":
        return checked_grid(config.input_size or dinov2.DEFAULT_INPUT_SIZE, dinov2.PATCH_SIZE, "DINOv2 patch size")
    return checked_grid(config.input_size or offline.DEFAULT_INPUT_SIZE, offline.CELL, "offline descriptor cell size")


__all__ = [
    "FeatureCache", "Teacher", "TeacherConfig", "TeacherInputError", "build_teacher", "extract_all", "teacher_feature_dim",
    "teacher_grid_size",
]
