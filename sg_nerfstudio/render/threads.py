"""The CPU thread pools rendering uses: torch's intra-op pool and numba's (the tile compositor).

Both default to every core of the machine. On a 2-core machine two such processes side by side oversubscribe
the cores and spin against each other (a training step measured 0.38 s alone and 5 s beside one or two other
jobs), so every command takes `--threads N` and sets both pools through `set_threads`: give concurrent jobs
a share of the cores each (e.g. `--threads 1` for two jobs on two cores).

Both pools are GNU OpenMP, whose idle threads spin 300,000 times before they sleep; importing `sg_nerfstudio` first
sets `GOMP_SPINCOUNT=1000` and, for Intel's or LLVM's OpenMP, `KMP_BLOCKTIME=0` (unless `OMP_WAIT_POLICY` or the
variable is already set): short enough that two jobs with the default threads share the cores (2x each) instead of
collapsing, long enough that a lone job's threads are awake for torch's many small parallel regions (about 25%
faster than `OMP_WAIT_POLICY=PASSIVE`; docs/measurements.md "Threads that spin a little").
"""

from __future__ import annotations

import os
from typing import Optional

import torch

from sg_nerfstudio.errors import InputError


class ThreadCountError(InputError):
    """A thread count no pool can have."""


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def check_thread_count(threads: Optional[int]) -> None:
    """ThreadCountError unless `threads` is None (the default) or at least 1."""
    if threads is not None and threads < 1:
        raise ThreadCountError(f"--threads must be 1 or more (default: the {available_cores()} cores this process may use), got {threads}.")


def set_threads(threads: Optional[int] = None) -> int:
    """Size torch's and numba's thread pools to `threads` (default: `available_cores()`); returns the count.
    ThreadCountError (one sentence) for a count under 1."""
    check_thread_count(threads)
    count = threads or available_cores()
    torch.set_num_threads(count)
    import numba

    numba.set_num_threads(min(count, numba.config.NUMBA_NUM_THREADS))
    return count
