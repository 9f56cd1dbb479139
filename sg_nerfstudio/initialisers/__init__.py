"""Initialisers of the meta -> reference Sim(3) built from SIFT and pycolmap (see pipeline.py)."""

from sg_nerfstudio.initialisers.pipeline import (
    METHODS,
    InitialiserSettings,
    Initialiser,
    InitResult,
    reference_source_from_config,
    resolve_reference_source,
    rich_progress,
    set_colmap_verbosity,
    silent_progress,
)
from sg_nerfstudio.initialisers.reference_cloud import ReferenceSource, ReferenceSourceError

__all__ = [
    "METHODS", "InitialiserSettings", "Initialiser", "InitResult", "ReferenceSource", "ReferenceSourceError",
    "reference_source_from_config", "resolve_reference_source", "rich_progress", "set_colmap_verbosity", "silent_progress",
]
