"""A non-editable install works from any directory: the wheel carries the registration presets, and sg-demo
(here on the tiny scene) runs end to end from a folder outside the repository."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

REPOSITORY = Path(__file__).resolve().parents[1]


def build_wheel(tmp_path: Path) -> Path:
    """The project's wheel, built from a copy of its sources (the checkout is left untouched)."""
    source = tmp_path / "source"
    shutil.copytree(REPOSITORY / "sg_nerfstudio", source / "sg_nerfstudio", ignore=shutil.ignore_patterns("__pycache__", "*.nbi", "*.nbc"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPOSITORY / name, source / name)
    wheels = tmp_path / "wheels"
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--quiet", "-w", str(wheels), str(source)],
        check=True, capture_output=True, text=True,
    )
    (wheel,) = wheels.glob("sg_nerfstudio-*.whl")
    return wheel


def test_sg_demo_runs_from_a_non_editable_install_outside_the_repository(tmp_path):
    wheel = build_wheel(tmp_path)
    site = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--quiet", "--target", str(site), str(wheel)], check=True, capture_output=True)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    env = {**os.environ, "PYTHONPATH": str(site)}

    where = subprocess.run([sys.executable, "-c", "import sg_nerfstudio; print(sg_nerfstudio.__file__)"], cwd=elsewhere, env=env, capture_output=True, text=True, check=True)
    assert Path(where.stdout.strip()).is_relative_to(site)  # the installed copy, not the checkout
    demo = subprocess.run(
        [sys.executable, str(site / "bin" / "sg-demo"), "--output", "demo", "--scene", "tiny", "--train-steps", "60"],
        cwd=elsewhere, env=env, capture_output=True, text=True, timeout=900,
    )
    assert demo.returncode == 0, demo.stdout[-3000:] + demo.stderr[-3000:]
    record = json.loads((elsewhere / "demo" / "registrations" / "front" / "transform.json").read_text())
    # the shipped fast-cpu preset; the tiny scene gives SIFT nothing to match, so the dense objective runs alone: 100 main
    # steps and the 40-step dense-SIFT refine stage
    assert record["steps"] == 140 and record["settings"]["objective"]["kind"] == "teacher-on-render"
    assert record["settings"]["last_stage"]["teacher"] == "dense-sift" and not record["settings"]["last_stage"]["with_anchors"]
    assert (elsewhere / "demo" / "registrations" / "front" / "metrics.json").is_file()
