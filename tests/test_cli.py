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
    # tyro on its own keeps the docstring's line break after "registered into", at any width (80: one column of help)
    monkeypatch.setenv("COLUMNS", "80")
    with pytest.raises(SystemExit) as stop:
        register_main(["--help"])
    assert stop.value.code == 0
    lines = capsys.readouterr().out.splitlines()
    (line,) = [line for line in lines if "'colmap' (photos registered into" in line]
    assert "the reference COLMAP model" in line
    (line,) = [line for line in lines if "the flags below override" in line]
    assert "single values" in line


@pytest.mark.parametrize("layout", ["target", "parent"])
def test_an_output_directory_where_a_file_is_is_one_sentence_and_the_file_stays(layout, tmp_path):
    from sg_nerfstudio.atomic import OutputPathError, atomic_directory

    user_file = tmp_path / "results"
    user_file.write_text("the user's notes")
    target = user_file if layout == "target" else user_file / "scene"
    expected = "is a file" if layout == "target" else f"cannot be created: {user_file} is a file"
    with pytest.raises(OutputPathError, match=f"Output directory {target} {expected}; expected a directory there"):
        with atomic_directory(target, overwrite=True):
            pass
    assert user_file.read_text() == "the user's notes" and sorted(p.name for p in tmp_path.iterdir()) == ["results"]


def test_an_output_apart_from_the_inputs_is_checked_on_resolved_paths(tmp_path):
    """An output may lie inside an input folder or beside it; it may not be an input or a folder above one, however
    the path is spelt (`..`, a symbolic link)."""
    from sg_nerfstudio.atomic import OutputPathError, check_apart_from_inputs

    photos = tmp_path / "data" / "photos"
    photos.mkdir(parents=True)
    link = tmp_path / "link"
    link.symlink_to(tmp_path / "data")
    check_apart_from_inputs(photos / "meta", [photos])
    check_apart_from_inputs(tmp_path / "data" / "metas", [photos, None])
    for output, relation in ((photos / "sub" / "..", "is"), (link, "holds"), (tmp_path, "holds")):
        with pytest.raises(OutputPathError, match=f"Output directory {output} {relation} the input {photos}"):
            check_apart_from_inputs(output, [None, photos])


@pytest.mark.parametrize("where", ["check", "atomic"])
def test_an_output_location_that_takes_no_new_entry_is_one_sentence(where, tmp_path, monkeypatch):
    """A folder the user may not write to (permissions, a read-only file system) is found when the output is checked,
    before any work, and again where the output is made; nothing is left behind."""
    from sg_nerfstudio import atomic

    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    target = tmp_path / "results" / "scene"
    monkeypatch.setattr(atomic.tempfile, "mkdtemp", refuse)
    expected = f"Output directory {target} cannot be created in {tmp_path if where == 'check' else target.parent} (Permission denied); expected a folder"
    with pytest.raises(atomic.OutputPathError, match=expected.replace("(", r"\(").replace(")", r"\)")):
        if where == "check":
            atomic.check_output_path(target)
        else:
            monkeypatch.setattr(atomic, "check_output_path", lambda path: None)
            with atomic.atomic_directory(target):
                pass
    assert not target.exists()


def test_a_full_disk_while_writing_is_one_sentence_and_leaves_nothing(tmp_path):
    import errno

    from sg_nerfstudio.atomic import OutputPathError, atomic_directory

    target = tmp_path / "scene"
    with pytest.raises(OutputPathError, match=f"Output directory {target} could not be written \\(No space left on device\\); nothing of it was kept"):
        with atomic_directory(target) as staging:
            (staging / "part").write_text("half")
            raise OSError(errno.ENOSPC, "No space left on device")
    assert list(tmp_path.iterdir()) == []


def test_ctrl_c_is_one_line_and_status_130(capsys):
    from sg_nerfstudio.errors import cli_main

    def body() -> int:
        raise KeyboardInterrupt

    assert cli_main(body) == 130
    assert capsys.readouterr().err.strip() == "Interrupted (Ctrl+C)."
