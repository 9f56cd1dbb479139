"""What every command shares: the one place an InputError becomes a sentence on stderr and exit status 1.

A library function raises `InputError` (or `FloatingPointError` for an optimisation that diverged); the
command's `main` runs its body through `cli_main`, which prints the sentence in red without a traceback and
returns 1. Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

from typing import Callable

from rich.console import Console
from rich.text import Text

from sg_nerfstudio.errors import InputError


def cli_main(body: Callable[[], int]) -> int:
    """Run a command's body; its exit status, or 1 after printing an InputError's sentence."""
    try:
        return body()
    except (InputError, FloatingPointError) as error:
        Console(stderr=True).print(Text(str(error), style="red"), soft_wrap=True)
        return 1
