"""Command-line parsing for every `sg-*` command and benchmark module: tyro, with field help that reads as prose.

Our settings are documented the way tyro asks, by a docstring under each dataclass field, and most of those
docstrings run over several source lines. tyro (1.0.17 with docstring_parser 0.18; 0.9.35 with 0.17 alike) joins a
docstring's lines into one paragraph only where a continuation line starts with a letter, and it tests that before
removing the class body's indentation, so every continuation line keeps its line break: `ns-register-meta --help`
printed "'colmap' (photos registered into" and "the reference COLMAP model, ..." as two lines of a paragraph, at
any terminal width. `parse` hands tyro each field docstring with its lines already joined into paragraphs (blank
lines still separate paragraphs, and a line that starts a list item, "- " or "1. ", still starts a line), then calls
`tyro.cli`. It changes only how tyro reads field docstrings (`tyro._docstrings.parse_docstring_from_object`, a
private function: where a tyro version lacks it, help text stays as that version prints it).
"""

from __future__ import annotations

import functools
import inspect
import re
from typing import Any, Callable, TypeVar

import tyro

T = TypeVar("T")

LIST_ITEM = re.compile(r"^(?:[-*] |\d+[.)] )")


def parse(config_class: Callable[..., T], **tyro_arguments: Any) -> T:
    """`tyro.cli(config_class, **tyro_arguments)`, with each field's help joined into paragraphs."""
    join_field_docstring_lines()
    return tyro.cli(config_class, **tyro_arguments)


def paragraphs(docstring: str) -> str:
    """A field docstring with its indentation removed and the lines of each paragraph joined by spaces; blank lines
    and list items ("- ", "* ", "1. ", "1) ") keep their line breaks."""
    lines = inspect.cleandoc(docstring).split("\n")
    joined: list[str] = []
    for line in lines:
        continues = joined and joined[-1] and line.strip() and not LIST_ITEM.match(line.lstrip())
        if continues:
            joined[-1] = f"{joined[-1]} {line.strip()}"
        else:
            joined.append(line.strip())
    return "\n".join(joined)


def join_field_docstring_lines() -> None:
    """Make tyro read field docstrings through `paragraphs` (once per process; nothing where tyro has no such hook)."""
    try:
        from tyro import _docstrings
    except ImportError:
        return
    read = getattr(_docstrings, "parse_docstring_from_object", None)
    if read is None or getattr(read, "joins_lines", False):
        return

    @functools.wraps(read)
    def read_joined(obj: object) -> dict[str, str]:
        return {name: paragraphs(text) for name, text in read(obj).items()}

    read_joined.joins_lines = True  # type: ignore[attr-defined]
    _docstrings.parse_docstring_from_object = read_joined
