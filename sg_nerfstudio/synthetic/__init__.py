"""Synthetic landmark scenes with exact ground truth (reference capture + in-the-wild meta-images)."""

from sg_nerfstudio.synthetic.generator import PRESETS, MetaImageSpec, SceneConfig, SceneGenerationError, generate_scene

__all__ = ["PRESETS", "MetaImageSpec", "SceneConfig", "SceneGenerationError", "generate_scene"]
