"""Command-line help (sg_nerfstudio/cli.py): field docstrings read as paragraphs at any terminal width."""

from __future__ import annotations

import pytest

from sg_nerfstudio.cli import paragraphs
from sg_nerfstudio.scripts.register_meta import main as register_main


def test_a_field_docstring_becomes_paragraphs_with_its_list_items_kept():
    docstring = """First line of the help,
    (a continuation that starts with a parenthesis) and `code`
    'quoted' to the end.

    Second paragraph:
    - one item
      continued
    1. a numbered item"""
    assert paragraphs(docstring) == (
        "First line of the help, (a continuation that starts with a parenthesis) and `code` 'quoted' to the end.\n"
        "\n"
        "Second paragraph:\n"
        "- one item continued\n"
        "1. a numbered item"
    )


def test_register_meta_help_wraps_each_flag_description_as_one_paragraph(monkeypatch, capsys):
    # tyro on its own keeps the docstring's line break after "registered into", at any width
    monkeypatch.setenv("COLUMNS", "200")
    with pytest.raises(SystemExit) as stop:
        register_main(["--help"])
    assert stop.value.code == 0
    lines = capsys.readouterr().out.splitlines()
    (line,) = [line for line in lines if "'colmap' (photos registered into" in line]
    assert "the reference COLMAP model" in line
    (line,) = [line for line in lines if "the flags below override" in line]
    assert "single values" in line
