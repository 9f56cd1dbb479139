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

if "OMP_WAIT_POLICY" not in os.environ:
    os.environ.setdefault("GOMP_SPINCOUNT", "1000")  # GNU OpenMP: torch's and numba's pools on Linux
    os.environ.setdefault("KMP_BLOCKTIME", "0")  # Intel / LLVM OpenMP (macOS, some conda builds): sleep at once, as before
"""An idle OpenMP thread spins 1000 times before it sleeps, unless the user chose a wait policy or a spin count
(docs/measurements.md "Threads that spin a little"). torch's and numba's pools are both GNU OpenMP, whose idle
threads otherwise spin 300,000 times: two jobs on a 2-core machine collapsed (one registration 18.8 s alone, 185 s
and 208 s side by side). Sleeping at once (`OMP_WAIT_POLICY=PASSIVE`, the setting here before) keeps a pair at 1.2x
its solo time, but a lone registration with 2 threads then ran barely faster than with 1; with 1000 spins it runs
about 25% faster than passive, and a pair takes 2x each (no collapse). Jobs meant to run side by side do best with
`OMP_WAIT_POLICY=PASSIVE` or `--threads 1` each. Intel's and LLVM's OpenMP ignore the spin count; `KMP_BLOCKTIME=0`
keeps their threads sleeping at once, as the passive policy did (not measured here: this machine's torch and numba
load GNU OpenMP only). It takes effect when this package is imported before torch starts its OpenMP runtime: every
sg-* command and `python -m sg_nerfstudio...`, not `ns-train`, which imports torch first."""

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
