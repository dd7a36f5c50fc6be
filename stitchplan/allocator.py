"""The process's memory allocator, set once as a command starts.

glibc's malloc returns the top of its heap to the system as soon as more than its trim
threshold (128 KiB at first) is free there, so every array a Newton iteration frees and the
next allocates again is faulted in page by page once more. Keeping 64 MiB at the top of the
heap (M_TOP_PAD; untouched pages cost nothing) halves a planned run's page faults: 17 000 ->
8 800 on configs/sh12_100x100.yaml, 6 000 -> 3 400 on the 20 mm needle scenes, with the
same peak memory (benchmarks/plan_speed.py, the allocator table). Elsewhere (musl, macOS,
Windows) nothing changes.
"""

from __future__ import annotations

import sys

M_TOP_PAD = -2  # glibc's mallopt parameter
TOP_PAD_BYTES = 64 * 1024 * 1024


def keep_heap_top() -> bool:
    """Ask glibc's malloc to keep TOP_PAD_BYTES at the top of its heap; whether it did."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):  # not glibc
        return False
    return bool(mallopt(M_TOP_PAD, TOP_PAD_BYTES))
