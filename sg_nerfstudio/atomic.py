"""Write a directory so that it appears complete or not at all, apart from every input, and by one command at a time.

`atomic_directory` fills a hidden sibling and renames it into place; `check_apart_from_inputs` is the one rule that an
output never is, nor holds, anything a command reads; `output_lock` lets a second command writing the same output stop
before its work (an advisory `flock`, which the system releases when a process dies: a crash leaves no stuck lock).
"""

from __future__ import annotations

import errno
import fcntl
import os
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterable, Iterator, Optional

from sg_nerfstudio.errors import InputError


class OutputPathError(InputError):
    """An output directory that cannot be created where it was asked for."""


def check_output_path(path: Path) -> None:
    """OutputPathError when `path`, a directory to create or fill, or a folder above it exists as something other than
    a directory (a file): creating it would fail with a traceback, and replacing it would delete the user's file; or
    when the nearest folder of it that exists takes no new entry (`check_writable`)."""
    path = Path(path)
    for candidate in (path, *path.parents):
        if candidate.exists():
            if candidate.is_dir():
                check_writable(path, candidate)
                return
            where = "is a file" if candidate == path else f"cannot be created: {candidate} is a file"
            raise OutputPathError(f"Output directory {path} {where}; expected a directory there, or a path that does not exist yet.")


def check_writable(path: Path, existing: Path) -> None:
    """OutputPathError when `existing`, the nearest existing folder of the output directory `path`, takes no new entry
    (its permissions, a read-only file system, a system folder): found before the work, not when its results are
    written. Probed by making and removing an empty directory there, since `os.access` does not see every refusal
    (a root user's, /proc's)."""
    try:
        probe = tempfile.mkdtemp(prefix=".sg-write-probe-", dir=existing)
    except OSError as error:
        raise OutputPathError(unwritable(path, existing, error)) from None
    os.rmdir(probe)


def unwritable(path: Path, folder: Path, error: OSError) -> str:
    """The sentence for an output directory that cannot be made in `folder`."""
    return f"Output directory {path} cannot be created in {folder} ({error.strerror or error}); expected a folder this user may write to."


def check_apart_from_inputs(path: Path, inputs: Iterable[Optional[Path]]) -> None:
    """OutputPathError when `path`, a directory a command creates whole (and with --overwrite replaces, deleting what
    it held), is one of the command's `inputs` (files or directories; None entries are skipped) or a folder above
    one. Paths are compared resolved, so `photos/..` and a symbolic link name their target."""
    output = Path(path).resolve()
    for given in inputs:
        if given is None:
            continue
        resolved = Path(given).resolve()
        if resolved == output or output in resolved.parents:
            relation = "is" if resolved == output else "holds"
            raise OutputPathError(
                f"Output directory {path} {relation} the input {given}; expected a directory apart from the inputs "
                "(writing the output there replaces what it holds)."
            )


def check_new_output_directory(path: Path, overwrite: bool, inputs: Iterable[Optional[Path]] = ()) -> None:
    """`check_output_path`, `check_apart_from_inputs`, and OutputPathError when `path` exists and `overwrite` is not
    given (the commands that create their output directory whole)."""
    check_output_path(path)
    check_apart_from_inputs(path, inputs)
    if Path(path).exists() and not overwrite:
        raise OutputPathError(f"Output directory {path} already exists; pass --overwrite to replace it.")


_HELD: dict[Path, int] = {}
"""Outputs this process holds the lock of -> how many times (the commands nest: a job, then each result directory)."""


def lock_path(output: Path) -> Path:
    """The lock file of an output directory: a hidden sibling, so that it exists before the output does."""
    output = Path(output).resolve()
    return output.parent / f".{output.name}.sg-lock"


@contextmanager
def output_lock(output: Path) -> Iterator[None]:
    """Hold the lock of `output` for the block: OutputPathError naming the other process when a running command holds it.
    Re-entrant within one process. The lock file is removed on the way out."""
    output = Path(output).resolve()
    if output in _HELD:
        _HELD[output] += 1
        try:
            yield
        finally:
            _HELD[output] -= 1
        return
    check_output_path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    path = lock_path(output)
    while True:
        descriptor = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(descriptor, 32).decode(errors="replace").strip() or "another process"
            os.close(descriptor)
            raise OutputPathError(
                f"Output directory {output} is being written by a command still running (process {holder}); expected it to "
                "finish first, or another output directory."
            ) from None
        try:
            same = os.fstat(descriptor).st_ino == os.stat(path).st_ino  # not a lock file its last holder just removed
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(descriptor)
    os.ftruncate(descriptor, 0)
    os.write(descriptor, str(os.getpid()).encode())
    _HELD[output] = 1
    try:
        yield
    finally:
        del _HELD[output]
        try:
            os.unlink(path)
        except FileNotFoundError:
            pass
        os.close(descriptor)


@contextmanager
def atomic_directory(target: Path, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary sibling of `target` to fill; on success it replaces `target`, on any error it is
    removed and `target` is left as it was.

    Raises:
        OutputPathError: `target` or a folder above it is a file, or `target` cannot be made there.
        FileExistsError: `target` exists and `overwrite` is False (checked before and after the work).
    """
    target = Path(target)
    check_output_path(target)
    with output_lock(target):
        with _filled(target, overwrite) as staging:
            yield staging


@contextmanager
def _filled(target: Path, overwrite: bool) -> Iterator[Path]:
    """`atomic_directory`'s body, under the output's lock."""
    if target.exists() and not overwrite:
        raise FileExistsError(f"{target} already exists")
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-", dir=target.parent))
    except OSError as error:  # the location changed since `check_output_path`, or refuses only deeper down
        raise OutputPathError(unwritable(target, target.parent, error)) from None
    try:
        yield staging
        if target.exists():
            if not overwrite:
                raise FileExistsError(f"{target} already exists")
            shutil.rmtree(target)
        os.replace(staging, target)
    except BaseException as error:
        shutil.rmtree(staging, ignore_errors=True)
        if isinstance(error, OSError) and error.errno in (errno.ENOSPC, errno.EDQUOT):  # the disk, not an input
            raise OutputPathError(
                f"Output directory {target} could not be written ({error.strerror}); nothing of it was kept. Expected room for it on that disk."
            ) from None
        raise
