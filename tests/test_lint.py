"""The suite's own hygiene: ruff over the package and the tests (pyproject.toml's [tool.ruff] rules), and the slow
tests tests/conftest.py names by node id still exist."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import SLOW_TESTS

ROOT = Path(__file__).resolve().parent.parent


def test_ruff_reports_nothing():
    try:
        import ruff  # noqa: F401
    except ImportError:
        pytest.fail("ruff is not installed: the dev extra brings it (pip install -e .[dev])")
    result = subprocess.run(
        [sys.executable, "-m", "ruff", "check", "--no-cache", "--output-format", "concise", "sg_nerfstudio", "tests"],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )
    if result.returncode != 0:
        pytest.fail(f"ruff check sg_nerfstudio tests:\n{result.stdout}{result.stderr}", pytrace=False)


def test_every_test_named_slow_exists():
    """A renamed or removed test left in SLOW_TESTS would let its new name into the fast subset unnoticed."""
    missing = []
    for node_id in SLOW_TESTS:
        path, name = node_id.split("::")
        source = ROOT / path
        if not source.is_file() or not re.search(rf"^def {re.escape(name.split('[')[0])}\(", source.read_text(), re.MULTILINE):
            missing.append(node_id)
    assert not missing, f"tests/conftest.py SLOW_TESTS names tests that are not there: {missing}"
