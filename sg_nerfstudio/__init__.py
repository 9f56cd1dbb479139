"""sg-nerfstudio: Scene Grounding In the Wild (CVPR 2026) as a nerfstudio plugin.

Stages (ARCHITECTURE.md): splat -> features -> render; geometry; initialisers; registration; viewer;
bench; synthetic; scripts (console entry points only).
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import os
import sys

__version__ = "0.1.0"

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
"""Idle OpenMP threads sleep instead of spinning (unless the user chose otherwise). torch's and numba's pools
are both OpenMP; spinning, two jobs on a 2-core machine collapsed (one registration 18.8 s alone, 185 s and 208 s
side by side; passive: 22.6 s alone, 31 s each side by side). It takes effect when this package is imported before
torch starts its OpenMP runtime: every sg-* command and `python -m sg_nerfstudio...`; `ns-train` imports torch
first, so run concurrent trainings as `OMP_WAIT_POLICY=PASSIVE ns-train ...` (render/threads.py)."""

MOVED_MODULES = {
    "sg_nerfstudio.method": "sg_nerfstudio.splat.method",
    "sg_nerfstudio.model": "sg_nerfstudio.splat.model",
    "sg_nerfstudio.datamanager": "sg_nerfstudio.splat.datamanager",
}
"""Modules that moved, by their old name. A trained run's config.yml names the classes it was built from
(`!!python/object:sg_nerfstudio.method.ExponentialDecaySchedulerConfig`, ...), so configs saved before the
move keep loading through these aliases (resolved lazily, on first import of the old name)."""


class _MovedModuleFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    def find_spec(self, name, path=None, target=None):
        return importlib.util.spec_from_loader(name, self) if name in MOVED_MODULES else None

    def create_module(self, spec):
        return importlib.import_module(MOVED_MODULES[spec.name])

    def exec_module(self, module) -> None:
        """The module is the moved one, already executed."""


if not any(isinstance(finder, _MovedModuleFinder) for finder in sys.meta_path):
    sys.meta_path.append(_MovedModuleFinder())
