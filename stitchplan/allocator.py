"""The process's memory allocator and Python's cyclic garbage collector, set as a command starts.

glibc's malloc serves an allocation above its mmap threshold (128 KiB at first) with fresh
pages from the system and returns them when it is freed; each time such a block is freed the
threshold rises to its size, up to 32 MiB. A command's first model build and planned run
allocate many arrays of new, growing sizes, so most of them fault in page by page before the
threshold has caught up, where a second run in the same process reuses what the first
freed (and the heap's top is returned to the system once 128 KiB is free there, to be
faulted in again).

`reuse_freed_memory` sets both thresholds where glibc's own adjustment ends: arrays up to
32 MiB come from the heap, and up to 64 MiB (glibc's rule, twice the mmap threshold) stays
at its top, so what the planner frees is reused rather than faulted in anew: a fifth fewer
page faults, the verified plan's whole command faster (1.40 -> 1.34 s on sh12_100x100 in the
latest run), the planned runs by up to 3 % in earlier runs and within 1 % either way in the
latest, and the same peak memory (benchmarks/plan_speed.py, the allocator table). Where the
process is not on glibc (musl, macOS, Windows), or the user set glibc's MALLOC_MMAP_THRESHOLD_ or MALLOC_TRIM_THRESHOLD_,
nothing changes.

A local Dask cluster's workers are processes started afresh, whose glibc reads its
thresholds from the environment as they start: `worker_environment` gives them the same
thresholds (stitchplan/parallel/executor.py), where Dask's own (MALLOC_TRIM_THRESHOLD_ of 64
KiB, which also fixes the mmap threshold at 128 KiB) had every array above 128 KiB mapped
afresh and faulted in page by page, ~28 000 page faults in each unplanned run of
configs/sh12_100x100.yaml and 1.4x its time in process (benchmarks/worker_allocator.py).

The command's imports (numpy, scipy, pydantic and the scenario's classes, typer) make some
hundred thousand objects that live as long as the process, none of them garbage, and the
cyclic collector, run every few hundred allocations, looks for garbage among them as they
accumulate: 153 collections during what `plan` imports, which take 0.279 s with it and
0.253 s without (benchmarks/results/import_collection.md). `pause_collection` turns it off
as the command starts and `resume_collection`, which each command calls once its imports are
done, moves what they made out of its reach (gc.freeze: the objects stay, freed by their
reference counts as ever, but no collection visits them, the run's included) and turns it
on again. The replay helper, forked while the collector is off, does the same once its own
imports are done. The commands take 0.92-0.98x as long (`simulate`, `deform`, `plan` with
and without its verification), their results the same to the last bit.
"""

from __future__ import annotations

import gc
import os
import sys

# glibc's mallopt parameters (malloc.h)
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024  # glibc's DEFAULT_MMAP_THRESHOLD_MAX on 64-bit systems
TRIM_THRESHOLD_BYTES = 2 * MMAP_THRESHOLD_BYTES  # as glibc sets it when it raises the mmap threshold
USER_VARIABLES = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")
# whether the user's environment set either, as this module was first imported: what this
# process's glibc read as it started (a local Dask cluster later sets them in this process's
# environment for its workers)
USER_SET = any(name in os.environ for name in USER_VARIABLES)


def reuse_freed_memory() -> bool:
    """Set glibc malloc's mmap and trim thresholds (module docstring); whether they were set."""
    if not _thresholds_are_ours():
        return False
    try:
        import ctypes

        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):  # not glibc
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    # M_MMAP_THRESHOLD first: setting it also stops glibc's own adjustment of the trim threshold
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(mallopt(M_TRIM_THRESHOLD,
                                                                                  TRIM_THRESHOLD_BYTES))


def worker_environment() -> dict[str, str]:
    """glibc's variables for the thresholds reuse_freed_memory sets, for processes started
    afresh (module docstring); empty where it sets nothing (not Linux, or the user's
    environment set either variable, USER_SET)."""
    if not _thresholds_are_ours():
        return {}
    return {"MALLOC_MMAP_THRESHOLD_": str(MMAP_THRESHOLD_BYTES), "MALLOC_TRIM_THRESHOLD_": str(TRIM_THRESHOLD_BYTES)}


def _thresholds_are_ours() -> bool:
    """On Linux, where the user's environment set neither of glibc's variables (USER_SET)."""
    return sys.platform.startswith("linux") and not USER_SET


_in_command = False  # this process runs the command line (cli.main, or a helper forked from it)
_paused = False  # collection turned off by pause_collection, not yet resumed


def pause_collection(command_start: bool = False) -> None:
    """Turn the cyclic garbage collector off for imports (module docstring): as the command
    starts (`command_start`, cli.main), and for imports a command makes later, in a process
    the command line started only (not in a test's runner, whose collector stays as it is)."""
    global _in_command, _paused
    _in_command = _in_command or command_start
    if _in_command and gc.isenabled():
        gc.disable()
        _paused = True


def resume_collection() -> None:
    """After pause_collection and the command's imports: freeze what exists now and turn the
    collector on again. Does nothing where it was not paused here (a second call, a command
    run by a test's runner)."""
    global _paused
    if _paused:
        _paused = False
        gc.freeze()
        gc.enable()
