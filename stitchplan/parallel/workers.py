"""How many worker processes: the cores this process may use, the bounds of --workers, the wait for workers."""

from __future__ import annotations

import math
import os

from ..errors import InputError
from .scheduler import check_scheduler_address

MAX_WORKERS_PER_CORE = 4  # --workers at most this many times the cores this process may use
# how long tasks wait on a cluster without a worker (none came, or all were lost) before the run
# ends: time for `dask worker` processes to be started, or for a lost one to be replaced
WORKER_WAIT_S = 60.0
WORKER_WAIT_VARIABLE = "STITCHPLAN_WORKER_WAIT"  # overrides WORKER_WAIT_S (seconds)


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity, which taskset and containers narrow)."""
    try:
        return len(os.sched_getaffinity(0)) or 1
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def default_workers() -> int:
    return usable_cores()


def max_workers() -> int:
    """The largest --workers: MAX_WORKERS_PER_CORE x the usable cores. Beyond it the workers
    only queue for the same cores while each costs a process and its memory."""
    return MAX_WORKERS_PER_CORE * usable_cores()


def worker_wait_seconds() -> float:
    """How long tasks may wait on a cluster without a worker: WORKER_WAIT_VARIABLE's seconds
    when set (an InputError unless a number > 0), WORKER_WAIT_S otherwise."""
    text = os.environ.get(WORKER_WAIT_VARIABLE, "").strip()
    if not text:
        return WORKER_WAIT_S
    try:
        seconds = float(text)
    except ValueError:
        seconds = math.nan
    if not (math.isfinite(seconds) and seconds > 0):
        raise InputError(f"{WORKER_WAIT_VARIABLE}: got {text!r}, expected the seconds tasks may wait for a "
                         f"Dask worker, a number > 0 (default {WORKER_WAIT_S:g})")
    return seconds


def check_workers(workers: int | None, scheduler: str | None) -> None:
    """--workers and --scheduler as given: a worker count from 0 to `max_workers()`, or a
    well-formed scheduler address (`check_scheduler_address`), not both."""
    if workers is not None and not 0 <= workers <= max_workers():
        cores = usable_cores()
        raise InputError(f"--workers: got {workers}, expected a number of worker processes from 0 to "
                         f"{max_workers()} (at most {MAX_WORKERS_PER_CORE} x the {cores} CPU "
                         f"core{'s' if cores > 1 else ''} this process may use; 0: run in this process)")
    if scheduler is not None:
        if workers is not None:
            raise InputError(f"--workers: got {workers} with --scheduler {scheduler}, expected one of the "
                             "two (the cluster at --scheduler has its own workers)")
        check_scheduler_address(scheduler)
