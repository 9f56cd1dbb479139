"""The package layout of ARCHITECTURE.md: imports point one way, from scripts down to render, and the shipped
presets are package resources."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import sg_nerfstudio
from sg_nerfstudio.registration.settings import PRESETS, RegistrationSettings, load_preset

PACKAGE = Path(sg_nerfstudio.__file__).parent
ALLOWED = {
    "geometry": set(),
    "render": set(),
    "features": set(),
    "synthetic": set(),
    "splat": {"features", "render", "geometry"},
    "initialisers": {"geometry", "features", "splat"},
    "registration": {"geometry", "features", "render", "splat", "initialisers"},
    "viewer": {"geometry", "splat"},
    "photos": {"geometry", "initialisers", "synthetic", "features", "splat", "registration"},
    "bench": {"geometry", "features", "render", "splat", "initialisers", "registration", "synthetic"},
    "scripts": {"geometry", "features", "render", "splat", "initialisers", "registration", "viewer", "bench", "synthetic", "photos"},
}
"""Stage -> the stages it may import (besides itself and the root modules errors.py / atomic.py / cli.py)."""
ROOT_MODULES = {"errors", "atomic", "cli"}


def imported_stages(path: Path) -> set[str]:
    """First components below sg_nerfstudio of every sg_nerfstudio import in a module (lazy ones included)."""
    stages = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names = [node.module] if isinstance(node, ast.ImportFrom) and node.module else [a.name for a in getattr(node, "names", [])] if isinstance(node, ast.Import) else []
        if isinstance(node, ast.ImportFrom) and node.module == "sg_nerfstudio":  # from sg_nerfstudio import cli
            names = [f"sg_nerfstudio.{alias.name}" for alias in node.names]
        for name in names:
            parts = name.split(".")
            if parts[0] == "sg_nerfstudio" and len(parts) > 1:
                stages.add(parts[1])
    return stages


def test_every_stage_imports_only_the_stages_below_it():
    modules = sorted(PACKAGE.rglob("*.py"))
    assert len(modules) > 40
    seen_stages = set()
    for path in modules:
        relative = path.relative_to(PACKAGE)
        if len(relative.parts) == 1:  # root modules: errors, atomic, cli, __init__
            assert imported_stages(path) <= ROOT_MODULES, relative
            continue
        stage = relative.parts[0]
        seen_stages.add(stage)
        assert stage in ALLOWED, f"{relative}: package {stage} is not in ARCHITECTURE.md's layout"
        illegal = imported_stages(path) - ALLOWED[stage] - ROOT_MODULES - {stage}
        assert not illegal, f"{relative} imports {sorted(illegal)}, which {stage} may not depend on"
    assert seen_stages == set(ALLOWED)


@pytest.mark.parametrize("name", PRESETS)
def test_presets_ship_inside_the_package_and_load_by_name(name):
    resource = PACKAGE / "registration" / "presets" / f"{name}.yaml"
    assert resource.is_file()
    settings = load_preset(name)
    assert isinstance(settings, RegistrationSettings)
    assert load_preset(resource) == settings  # a path gives the same settings as the name


@pytest.mark.parametrize("name", PRESETS)
def test_repository_configs_are_the_shipped_presets(name):
    in_repository = Path(__file__).resolve().parents[1] / "configs" / "register" / f"{name}.yaml"
    assert in_repository.read_text() == (PACKAGE / "registration" / "presets" / f"{name}.yaml").read_text()


def test_the_anchored_start_is_entered_through_its_package_only():
    """Outside registration/anchored_start, the package's modules import it by its one entry (its __init__), never its
    inner modules: the anchored start can be read top-down from `start_from_anchors`."""
    inner = "sg_nerfstudio.registration.anchored_start."
    for path in sorted(PACKAGE.rglob("*.py")):
        if "anchored_start" in path.relative_to(PACKAGE).parts:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = [node.module or ""] if isinstance(node, ast.ImportFrom) else [a.name for a in node.names] if isinstance(node, ast.Import) else []
            assert not any(name.startswith(inner) for name in names), f"{path.relative_to(PACKAGE)} imports {names} past the entry"
