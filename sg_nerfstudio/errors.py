"""User-input errors: one sentence naming the input and what was expected.

`InputError` is an ordinary exception: library callers catch the specific subclass, and every command
catches it once, in `cli_main` below (every `sg-*` command and `python -m sg_nerfstudio.bench.*` module runs its body
through it), which prints the sentence (no traceback) and exits with status 1. `FloatingPointError`, an optimisation
that diverged, is printed the same way; anything else is a bug and keeps its traceback. Under `ns-train` (nerfstudio's
own command) `install_input_error_hook` does the same for an InputError that reaches the top, e.g. a dataset with
missing images.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Callable, Optional


class InputError(Exception):
    """An input (file, flag, dataset, checkpoint) that cannot be used as given."""

    def __init__(self, message: str):
        super().__init__(message)
        self.message = message

    def __str__(self) -> str:
        return self.message


def not_a_directory(path: Path) -> str:
    """How a path that should be a directory is not one, for an InputError's sentence: "is a file" or "does not exist"."""
    return "is a file" if Path(path).exists() else "does not exist"


def range_problem(value: object, whole: bool = False, minimum: Optional[float] = None, maximum: Optional[float] = None,
                  above: Optional[float] = None, below: Optional[float] = None) -> Optional[str]:
    """What a numeric setting should be, as the end of a sentence ("a finite number above 0"), when `value` is not a finite
    number (a whole one with `whole`) within the bounds; None when it is. NaN and infinities fail every bound."""
    kind = "a whole number" if whole else "a finite number"
    if minimum is not None and maximum is not None:
        bounds = [f"from {minimum:g} to {maximum:g}"]
    else:
        bounds = [f"of {minimum:g} or more" if minimum is not None else "", f"of at most {maximum:g}" if maximum is not None else ""]
    bounds += [f"above {above:g}" if above is not None else "", f"below {below:g}" if below is not None else ""]
    expected = " ".join([kind, " and ".join(b for b in bounds if b)]).strip()
    is_number = isinstance(value, int) if whole else isinstance(value, (int, float))
    if isinstance(value, bool) or not is_number or not math.isfinite(value):
        return expected
    if (minimum is not None and value < minimum) or (maximum is not None and value > maximum):
        return expected
    if (above is not None and value <= above) or (below is not None and value >= below):
        return expected
    return None


def install_input_error_hook() -> None:
    """Print an uncaught InputError as its sentence on stderr (exit status 1); anything else as before."""
    previous = sys.excepthook
    if getattr(previous, "prints_input_errors", False):
        return

    def hook(kind, error, traceback) -> None:
        if isinstance(error, InputError):
            print(str(error), file=sys.stderr)
            return
        previous(kind, error, traceback)

    hook.prints_input_errors = True
    sys.excepthook = hook


def cli_main(body: Callable[[], int]) -> int:
    """Run a command's body; its exit status, or 1 after printing an InputError's (or FloatingPointError's) sentence,
    or 130 (the shell's status for SIGINT) after one line where the user pressed Ctrl+C (an output directory being
    written is removed on the way out by `atomic.atomic_directory`; a reference being trained keeps nerfstudio's run)."""
    from rich.console import Console
    from rich.text import Text

    try:
        return body()
    except (InputError, FloatingPointError) as error:
        Console(stderr=True).print(Text(str(error), style="red"), soft_wrap=True)
        return 1
    except KeyboardInterrupt:
        Console(stderr=True).print(Text("Interrupted (Ctrl+C).", style="red"), soft_wrap=True)
        return 130
