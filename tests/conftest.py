"""Shared fixtures: one tiny synthetic scene per test session."""

from __future__ import annotations

from pathlib import Path

import pytest

from sg_nerfstudio.scripts.make_scene import main as make_scene_main


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    output = tmp_path_factory.mktemp("scenes") / "tiny"
    assert make_scene_main(["--preset", "tiny", "--output", str(output), "--occluder-rate", "0.6"]) == 0
    return output
