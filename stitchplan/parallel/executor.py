"""The Executor: a function mapped over argument lists, in this process, on a local Dask cluster or at a scheduler."""

from __future__ import annotations

import contextlib
import logging
import os
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any

from ..errors import InputError
from .dask_logs import dask_logs_to_package, dask_setup
from .failures import ClusterFailure
from .scheduler import CONNECT_TIMEOUT_S, brief_error, probe_scheduler
from .signals import signals_deferred
from .workers import WORKER_WAIT_S, check_workers, default_workers, worker_wait_seconds

log = logging.getLogger(__package__)  # "stitchplan.parallel", the name its records carry

SINGLE_THREAD = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
RETRIES = 2  # a lost worker's tasks run again elsewhere, at most this many times
WORKER_POLL_S = 2.0  # while no task completes, the scheduler is asked for its workers this often
WAIT_NOTE_S = 10.0  # a wait for workers is logged at its start and then this often
MIN_OPEN_FILES = 64  # a 2-worker local cluster ran at 64; at 16 its scheduler looped on "too many open files"


class Executor:
    """A context manager: `with Executor(workers, scheduler) as executor: executor.map(...)`."""

    def __init__(self, workers: int | None = None, scheduler: str | None = None):
        check_workers(workers, scheduler)
        self.worker_wait = worker_wait_seconds() if workers != 0 else WORKER_WAIT_S
        self.scheduler = scheduler
        self.workers = default_workers() if workers is None and scheduler is None else workers
        self.client = None
        self.had_workers = False  # whether its cluster was seen with a worker (ran a task)
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
        try:
            import distributed  # noqa: F401
        except ImportError as error:  # pragma: no cover - a dependency of the package
            raise InputError(f"--workers: Dask is not installed ({error}); expected "
                             "`pip install 'dask[distributed]'` or --workers 0") from None
        self._stack.enter_context(dask_logs_to_package())  # closed last: after the cluster
        try:
            self.client = self._connect() if self.scheduler is not None else self._start_local_cluster()
        except BaseException:
            self._stack.close()
            raise
        return self

    def _connect(self):
        """A client of the cluster at --scheduler, once it has answered as a Dask scheduler."""
        from dask.distributed import Client

        probe_scheduler(self.scheduler)
        try:
            client = self._stack.enter_context(Client(self.scheduler, timeout=CONNECT_TIMEOUT_S))
        except Exception as error:  # noqa: BLE001 -- it answered the probe, then failed: gone, or not ours
            raise InputError(f"--scheduler: cannot connect to {self.scheduler} ({brief_error(error)}); expected "
                             "the address of a running `dask scheduler`") from None
        check_package_on_workers(client, self.scheduler)
        workers = len(client.nthreads())
        self.had_workers = workers > 0
        if workers:
            log.info("Dask scheduler %s has %d worker%s", self.scheduler, workers, "s" if workers > 1 else "")
        else:  # said now, without -v too: the tasks only wait for one after the nominal plan
            log.warning("Dask scheduler %s has no workers yet; its tasks will wait up to %g s for one", self.scheduler,
                     self.worker_wait)
        return client

    def _start_local_cluster(self):
        import dask
        from dask.distributed import Client, LocalCluster

        from ..allocator import worker_environment

        try:
            os.getcwd()
        except FileNotFoundError:  # the workers start in it, and fail with a message about nannies
            raise InputError("--workers: the working directory no longer exists, and a local Dask cluster's "
                             "workers start in it; expected an existing working directory, or --workers 0 to "
                             "run in this process") from None
        open_files = _open_file_limit()
        if open_files is not None and open_files < MIN_OPEN_FILES:  # below it tornado loops on EMFILE
            raise InputError(f"--workers: a local Dask cluster needs at least {MIN_OPEN_FILES} open files, "
                             f"got a limit of {open_files} (ulimit -n); expected a higher limit, or --workers 0 "
                             "to run in this process")

        configured = dask.config.get("distributed.worker.preload", default=None) or []
        preload = [*([configured] if isinstance(configured, str) else configured),
                   dask_setup.__module__]  # its dask_setup
        # set before each worker process starts (a nanny's pre-spawn environment), where glibc reads them
        spawned = {**(dask.config.get("distributed.nanny.pre-spawn-environ", default=None) or {}),
                   **worker_environment()}
        try:
            # no dashboard; the scheduler's HTTP routes (health, metrics) on a free local port, not
            # on 8787, where another cluster would make distributed warn on stderr
            with signals_deferred(), dask.config.set({"distributed.nanny.pre-spawn-environ": spawned}), \
                    _workers_deaf_to_ctrl_c():
                _start_resource_tracker_deaf_to_hangups()
                # a cluster interrupted half-started cannot be closed (signals_deferred)
                cluster = self._stack.enter_context(LocalCluster(
                    n_workers=self.workers, threads_per_worker=1, processes=True, dashboard_address=None,
                    scheduler_kwargs={"dashboard_address": "127.0.0.1:0"}, silence_logs=logging.ERROR,
                    env=SINGLE_THREAD, preload=preload))
            self.had_workers = True  # LocalCluster returns once its workers have started
            return self._stack.enter_context(Client(cluster))
        except Exception as error:  # noqa: BLE001 -- a machine that cannot start them (memory, file limits)
            raise InputError(f"--workers: cannot start a local Dask cluster of {self.workers} worker "
                             f"processes ({brief_error(error)}); expected fewer --workers, or --workers 0 "
                             "to run in this process") from None

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
        import queue
        from concurrent.futures import CancelledError

        from distributed.scheduler import KilledWorker

        if self.scheduler is not None:  # workers may have joined since _connect
            check_package_on_workers(self.client, self.scheduler)
        futures = self.client.map(function, *[list(column) for column in zip(*calls)],
                                  pure=False, retries=RETRIES)
        index_of = {future.key: index for index, future in enumerate(futures)}
        watch = _WorkerWatch(self, len(futures))
        # each task reports itself once finished (done, failed or cancelled), in completion order:
        # waiting on all pending tasks after each completion costs the client O(tasks^2)
        finished: queue.SimpleQueue = queue.SimpleQueue()
        for future in futures:
            future.add_done_callback(finished.put)
        try:
            for done in range(len(futures)):
                while True:
                    try:
                        future = finished.get(timeout=min(WORKER_POLL_S, self.worker_wait))
                        break
                    except queue.Empty:  # nothing completed meanwhile: are there workers at all?
                        watch.check(done)
                watch.progressed()
                report(index_of[future.key], future.result())  # a task's bug is raised here
            return [future.result() for future in futures]
        except (KilledWorker, CancelledError) as error:  # the cluster's failure, not the task's
            raise ClusterFailure(f"{self.where} lost a task: {brief_error(error)}") from None


def package_version() -> tuple[str, str]:
    """This package's version and the SHA-256 of its sources where it runs: on a worker,
    check_package_on_workers's probe, which also fails there where the package cannot be
    imported."""
    from .. import __version__, source_sha256

    return __version__, source_sha256()


def check_package_on_workers(client: Any, scheduler: str) -> None:
    """An InputError naming --scheduler unless every worker attached to the scheduler imports
    this package at this version from the same sources. A worker that cannot import it dies on
    its first task (the task cannot be unpickled), which the run would only see as lost
    workers; one at another version, or at this one from other sources (the version stays the
    same over many changes of the numerics), would run other code, and the results would
    depend on where they ran."""
    from .. import __version__, source_sha256

    try:
        versions = client.run(package_version, on_error="return")
    except Exception as error:  # noqa: BLE001 -- the scheduler gone meanwhile: the run's own wait says so
        log.debug("could not ask the workers of %s for their stitchplan: %s", scheduler, brief_error(error))
        return
    for worker, version in sorted(versions.items()):
        if isinstance(version, BaseException):
            raise InputError(f"--scheduler: worker {worker} of {scheduler} cannot import this "
                             f"command's stitchplan ({brief_error(version)}); expected workers that can, started where stitchplan is "
                             "installed or with it on PYTHONPATH, and restarted since it changed (`PYTHONPATH=DIR "
                             f"dask worker {scheduler}`)")
        # a worker at code from before the sources were checked answers its version alone
        version, sources = (version, None) if isinstance(version, str) else version
        if version != __version__:
            raise InputError(f"--scheduler: worker {worker} of {scheduler} runs stitchplan {version}, this command "
                             f"{__version__}; expected the same version on every worker (the runs must not depend "
                             "on where they ran)")
        if sources != source_sha256():
            theirs = f"SHA-256 {sources[:12]}..." if sources else "code that does not give its SHA-256"
            raise InputError(f"--scheduler: worker {worker} of {scheduler} runs stitchplan {version} from other "
                             f"sources ({theirs}, this command's {source_sha256()[:12]}...); "
                             "expected the same code on every worker, restarted since it changed (the runs must "
                             "not depend on where they ran)")


class _WorkerWatch:
    """Watches an executor's cluster while its tasks wait: a ClusterFailure once it has had no
    worker for `executor.worker_wait` seconds, INFO records of the wait meanwhile."""

    def __init__(self, executor: Executor, tasks: int):
        self.executor = executor
        self.tasks = tasks
        self.without_since: float | None = None  # when the cluster was last seen to have no worker
        self.noted_at = 0.0

    def progressed(self) -> None:
        """A task completed: a worker ran it."""
        self.executor.had_workers = True
        self.without_since = None

    def check(self, done: int) -> None:
        """Ask the scheduler for its workers; raise a ClusterFailure if it has had none for the
        wait allowed, `done` of the tasks completed."""
        executor = self.executor
        try:
            workers = len(executor.client.nthreads())
        except Exception as error:  # noqa: BLE001 -- the scheduler gone or not answering: the cluster's failure
            raise ClusterFailure(f"{executor.where} stopped answering with {done} of {self.tasks} tasks done "
                                 f"({brief_error(error)})") from None
        now = time.monotonic()
        if workers:
            if self.without_since is not None:
                log.warning("%s has %d worker%s again", executor.where, workers, "s" if workers > 1 else "")
            executor.had_workers, self.without_since = True, None
            return
        what = "lost its workers" if executor.had_workers else "has no workers"
        if self.without_since is None:
            self.without_since = self.noted_at = now
            # a warning: a command that stalls says why without -v
            log.warning("%s %s (%d of %d tasks done); waiting up to %g s for one", executor.where, what, done,
                     self.tasks, executor.worker_wait)
        waited = now - self.without_since
        if waited >= executor.worker_wait:
            if executor.had_workers:
                raise ClusterFailure(f"{executor.where} lost its workers: {done} of {self.tasks} tasks done, then "
                                     f"no worker for {executor.worker_wait:g} s; expected workers attached to it "
                                     "that keep running" + _worker_hint(executor.scheduler))
            raise ClusterFailure(f"{executor.where} has no workers: none joined within {executor.worker_wait:g} s "
                                 f"({done} of {self.tasks} tasks done); expected workers attached to it"
                                 f"{_worker_hint(executor.scheduler)}")
        if now - self.noted_at >= WAIT_NOTE_S:
            self.noted_at = now
            log.warning("%s still %s: waited %.0f s of %g s (%d of %d tasks done)", executor.where,
                     "without workers" if executor.had_workers else "has no workers", waited, executor.worker_wait,
                     done, self.tasks)


def _worker_hint(scheduler: str | None) -> str:
    """How to attach a worker to the scheduler, for the error line."""
    return f" (`dask worker {scheduler}`)" if scheduler is not None else ""


def run_all(function: Callable[..., Any], *arguments: Iterable[Any], executor: Executor | None = None,
            on_result: Callable[[int, Any], None] | None = None) -> list[Any]:
    """`executor.map`, or in this process without one."""
    return (executor or Executor(workers=0)).map(function, *[list(a) for a in arguments], on_result=on_result)


def _open_file_limit() -> int | None:
    """The soft limit on open files of this process, None when unknown or unlimited."""
    try:
        import resource
    except ImportError:  # not a POSIX system
        return None
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    return None if soft == resource.RLIM_INFINITY else int(soft)


@contextlib.contextmanager
def _signals_blocked(*names: str):
    """The named signals blocked in this thread while the block runs: threads it starts keep
    the mask, and so do processes they start, across their exec (a handler, not the mask, is
    reset there). A signal for this thread arrives when the block ends."""
    import signal

    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {getattr(signal, name) for name in names})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


def _workers_deaf_to_ctrl_c():
    """SIGINT blocked while a local cluster starts: the threads distributed starts then (its
    event loop's, the ones that spawn the workers) keep the mask, and the worker processes too.
    A worker ignores Ctrl-C once it is up (its preload, dask_logs.dask_setup), but the
    terminal's SIGINT to the process group reached the workers still importing, each printing
    a KeyboardInterrupt traceback. This thread's interrupt is delivered when the block ends
    (into signals_deferred's hands)."""
    return _signals_blocked("SIGINT")


def _start_resource_tracker_deaf_to_hangups() -> None:
    """multiprocessing's resource tracker, which the nannies' semaphores register with, started
    with SIGHUP blocked, as it has Ctrl-C and SIGTERM ignored: a hangup of the terminal's process
    group killed it, and the one started in its place printed a warning and a traceback for every
    semaphore the closing cluster released."""
    import signal
    import threading
    from multiprocessing import resource_tracker

    if not hasattr(signal, "SIGHUP") or threading.current_thread() is not threading.main_thread():
        return
    with _signals_blocked("SIGHUP"):
        resource_tracker.ensure_running()
