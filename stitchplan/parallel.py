"""Many independent runs on a Dask cluster: the sampled runs of `plan --uncertainty` and the
sweep of `stitchplan study`.

`Executor` maps a top-level (picklable) function over argument lists and returns the
results in submission order, so a result never depends on where or in which order its
task ran. Three ways to run:

- `workers=0`: in this process, one after another (tests, debugging, profiling);
- `workers=N` (default: the machine's cores): a `dask.distributed.LocalCluster` of N
  single-threaded worker processes started for the run and closed after it;
- `scheduler="tcp://host:port"`: an existing cluster (`dask scheduler` and `dask worker
  tcp://...` on any machines that can import stitchplan).

Tasks are submitted with `pure=False` (each is run, none deduplicated) and `retries=2`, so
the tasks of a worker that dies are run again on another one. A task's own failure is the
task's business: the functions mapped here record the failures a run may end with
(RUN_FAILURES) in their result instead of raising them, so a failed sample is a recorded
failure, not a lost run; anything else escaping a task is a bug and is raised here.

Worker processes of a local cluster run with BLAS at one thread (OMP/OpenBLAS/MKL
variables), so N workers use N cores, and the sparse solves give the same numbers in every
process. Dask's own log lines are kept off the console (errors only).
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np

from .errors import InputError, StitchplanError

log = logging.getLogger(__name__)

# what a run may end with because of its input (recorded, never raised):
RUN_FAILURES = (
    # the project's own errors: a discretization the scenario checks refuse (InputError, e.g. a
    # quadratic basis with too small a dilation, or a replayed centre path that ends before the
    # tip exits) and numerical failures of an accepted one (SolverDivergence, InvertedMaterial,
    # SingularMomentMatrix, TipTrackingJump, InsertionFailure)
    StitchplanError,
    # dense linear algebra on a degenerate model: numpy's solves and factorizations
    np.linalg.LinAlgError,
    # SuperLU (scipy.sparse.linalg.splu) raises a bare RuntimeError on an exactly singular factor
    # (too few particles or quadrature points to pin the tissue down)
    RuntimeError,
    # a model too fine for the machine: the sweep records it and goes on with the coarser runs
    MemoryError,
)

SINGLE_THREAD = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
DASK_LOGGERS = ("distributed", "dask", "tornado", "bokeh")
RETRIES = 2  # a lost worker's tasks run again elsewhere, at most this many times


def default_workers() -> int:
    return os.cpu_count() or 1


def check_workers(workers: int | None, scheduler: str | None) -> None:
    """--workers and --scheduler as given: a worker count >= 0, an address with a scheme."""
    if workers is not None and workers < 0:
        raise InputError(f"--workers: got {workers}, expected a number of worker processes >= 0 "
                         "(0: run in this process)")
    if scheduler is not None:
        if workers is not None:
            raise InputError(f"--workers: got {workers} with --scheduler {scheduler}, expected one of the "
                             "two (the cluster at --scheduler has its own workers)")
        if "://" not in scheduler or scheduler.endswith("://"):
            raise InputError(f"--scheduler: got {scheduler!r}, expected a Dask scheduler address such as "
                             "tcp://127.0.0.1:8786")


class Executor:
    """A context manager: `with Executor(workers, scheduler) as executor: executor.map(...)`."""

    def __init__(self, workers: int | None = None, scheduler: str | None = None):
        check_workers(workers, scheduler)
        self.scheduler = scheduler
        self.workers = default_workers() if workers is None and scheduler is None else workers
        self.client = None
        self._stack = contextlib.ExitStack()

    @property
    def where(self) -> str:
        """Where the tasks run, for summaries: "in-process", "local cluster of N workers" or
        the scheduler's address."""
        if self.scheduler is not None:
            return f"Dask scheduler {self.scheduler}"
        if not self.workers:
            return "in-process"
        return f"local Dask cluster of {self.workers} worker process{'es' if self.workers > 1 else ''}"

    def __enter__(self) -> Executor:
        if self.scheduler is None and not self.workers:
            return self
        _quiet_dask()
        try:
            from dask.distributed import Client, LocalCluster
        except ImportError as error:  # pragma: no cover - a dependency of the package
            raise InputError(f"--workers: Dask is not installed ({error}); expected "
                             "`pip install 'dask[distributed]'` or --workers 0") from None
        try:
            if self.scheduler is not None:
                self.client = self._stack.enter_context(Client(self.scheduler, timeout="10s"))
            else:
                cluster = self._stack.enter_context(LocalCluster(
                    n_workers=self.workers, threads_per_worker=1, processes=True, dashboard_address=None,
                    silence_logs=logging.ERROR, env=SINGLE_THREAD))
                self.client = self._stack.enter_context(Client(cluster))
        except OSError as error:  # no scheduler at the address, or it did not answer
            self._stack.close()
            raise InputError(f"--scheduler: cannot connect to {self.scheduler} ({error}); expected a "
                             "running `dask scheduler`") from None
        return self

    def __exit__(self, *exc) -> None:
        with contextlib.suppress(Exception):  # closing a cluster must not hide the run's error
            self._stack.close()
        self.client = None

    def map(self, function: Callable[..., Any], *arguments: Sequence[Any],
            on_result: Callable[[int, Any], None] | None = None) -> list[Any]:
        """[function(*args) for args in zip(*arguments)], in submission order; `on_result(index,
        result)` is called as each task completes (in completion order, for progress)."""
        calls = list(zip(*arguments))
        report = on_result or (lambda index, result: None)
        if not calls:
            return []
        if self.client is None:
            results = []
            for index, args in enumerate(calls):
                results.append(function(*args))
                report(index, results[-1])
            return results
        from dask.distributed import as_completed

        futures = self.client.map(function, *[list(column) for column in zip(*calls)],
                                  pure=False, retries=RETRIES)
        index_of = {future.key: index for index, future in enumerate(futures)}
        for future in as_completed(futures):
            report(index_of[future.key], future.result())  # a task's bug is raised here
        return [future.result() for future in futures]


def run_all(function: Callable[..., Any], *arguments: Iterable[Any], executor: Executor | None = None,
            on_result: Callable[[int, Any], None] | None = None) -> list[Any]:
    """`executor.map`, or in this process without one."""
    return (executor or Executor(workers=0)).map(function, *[list(a) for a in arguments], on_result=on_result)


def _quiet_dask() -> None:
    """Dask's log lines (cluster start, worker restarts, closing) stay off the console."""
    for name in DASK_LOGGERS:
        logging.getLogger(name).setLevel(logging.ERROR)
