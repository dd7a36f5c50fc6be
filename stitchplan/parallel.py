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
the tasks of a worker that dies are run again on another one. A cluster without a worker
holds its tasks forever, so the wait for results is watched: while no task completes the
scheduler is asked every few seconds for its workers, and when it has had none for
`worker_wait_seconds()` (WORKER_WAIT_S, or the STITCHPLAN_WORKER_WAIT environment variable)
the run ends as a ClusterFailure saying whether no worker ever came or the cluster lost its
workers, and how many tasks were done. The wait is logged at INFO (-v) as it goes. A task's own failure is the
task's business: the functions mapped here record the failures a run may end with
(RUN_FAILURES) in their result instead of raising them, so a failed sample is a recorded
failure, not a lost run; anything else escaping a task is a bug and is raised here.

Worker processes of a local cluster run with BLAS at one thread (OMP/OpenBLAS/MKL
variables), so N workers use N cores, and the sparse solves give the same numbers in every
process.

What the user gives is checked before any work (`check_workers`): a worker count from 0 to
MAX_WORKERS_PER_CORE x the cores this process may use (more only queue for the same cores and
each costs a process), and a scheduler address SCHEME://HOST:PORT with a scheme of
distributed's comm layer that reaches another process (tcp, tls, ws, wss). Reaching the
scheduler is bounded by CONNECT_TIMEOUT_S: an address where nothing listens, a server that
never answers and one that answers something else than Dask's protocol each end as one
InputError naming --scheduler, never as a hang or a traceback.

Dask's log records stay off the console: in this process, while an executor runs, they go
to this module's logger at DEBUG (shown with -vv); the worker processes of a local cluster
drop them (`dask_setup`, run in each worker as a preload), so the heartbeat errors of a
normal shutdown never reach the user. Those workers ignore Ctrl-C (SIGINT, which a terminal
sends to the whole process group): the command stops them when it closes the cluster, so an
interrupt ends with the command's own exit and no traceback of theirs. What fails for real
ends as the package's own error:
InputError when the cluster cannot be reached or started, ClusterFailure when it loses tasks.
"""

from __future__ import annotations

import contextlib
import ipaddress
import logging
import math
import os
import re
import signal
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
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
MAX_WORKERS_PER_CORE = 4  # --workers at most this many times the cores this process may use
CONNECT_TIMEOUT_S = 5.0  # reaching a --scheduler and hearing its answer, at most this long
# how long tasks wait on a cluster without a worker (none came, or all were lost) before the run
# ends: time for `dask worker` processes to be started, or for a lost one to be replaced
WORKER_WAIT_S = 60.0
WORKER_WAIT_VARIABLE = "STITCHPLAN_WORKER_WAIT"  # overrides WORKER_WAIT_S (seconds)
WORKER_POLL_S = 2.0  # while no task completes, the scheduler is asked for its workers this often
WAIT_NOTE_S = 10.0  # a wait for workers is logged at its start and then this often
MIN_OPEN_FILES = 64  # a 2-worker local cluster ran at 64; at 16 its scheduler looped on "too many open files"
# distributed's comm schemes that reach a scheduler in another process (inproc:// is in-process
# only; ucx:// has left distributed for distributed-ucxx)
SCHEDULER_SCHEMES = ("tcp", "tls", "ws", "wss")
SCHEDULER_EXPECTED = ("a Dask scheduler address SCHEME://HOST:PORT with SCHEME tcp, tls, ws or wss and PORT "
                      "from 1 to 65535, such as tcp://127.0.0.1:8786")
_HOST_NAME = re.compile(r"[A-Za-z0-9_]([A-Za-z0-9_.-]*[A-Za-z0-9_])?")  # a host name or an IPv4 address


class ClusterFailure(StitchplanError):
    """The Dask cluster lost tasks (a worker killed again and again, the scheduler gone)."""

    exit_code = 1


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


def check_scheduler_address(address: str) -> tuple[str, int]:
    """SCHEME://HOST:PORT as distributed's comm layer reads it (distributed.comm.addressing:
    parse_address, parse_host_port), checked here so that a malformed address is an InputError
    before any work: a scheme of SCHEDULER_SCHEMES, a host name, IPv4 address or bracketed IPv6
    address, a port from 1 to 65535, nothing else. Returns (host, port)."""
    try:
        return _host_port(address)
    except ValueError as problem:
        raise InputError(f"--scheduler: got {address!r}, expected {SCHEDULER_EXPECTED} ({problem})") from None


def _host_port(address: str) -> tuple[str, int]:
    """(host, port) of SCHEME://HOST:PORT; a ValueError saying what is wrong otherwise."""
    scheme, sep, location = address.partition("://")
    if not sep:
        raise ValueError("no scheme")
    if scheme not in SCHEDULER_SCHEMES:
        raise ValueError(f"unknown scheme {scheme!r}")
    if location.startswith("["):  # IPv6: [addr]:port
        host, bracket, tail = location[1:].partition("]")
        if not bracket:
            raise ValueError("no ']' after the IPv6 host")
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            raise ValueError(f"{host!r} is not an IPv6 address") from None
        if not tail:
            raise ValueError("no port")
        if not tail.startswith(":"):
            raise ValueError(f"{tail!r} after the host, expected :PORT")
        port = tail[1:]
    else:
        host, colon, port = location.rpartition(":")
        if not colon:
            raise ValueError("no port" if location else "no host")
        if ":" in host:
            raise ValueError("an IPv6 host needs brackets, such as tcp://[::1]:8786")
        if not host:
            raise ValueError("no host")
        if not _HOST_NAME.fullmatch(host):
            raise ValueError(f"host {host!r} is not a host name or an IP address")
    if not (port.isascii() and port.isdigit()):
        raise ValueError(f"port {port!r} is not a number" if port else "no port")
    if not 1 <= int(port) <= 65535:
        raise ValueError(f"port {int(port)} is out of range")
    return host, int(port)


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
            raise InputError(f"--scheduler: cannot connect to {self.scheduler} ({_brief(error)}); expected "
                             "the address of a running `dask scheduler`") from None
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
        preload = [*([configured] if isinstance(configured, str) else configured), __name__]  # its dask_setup
        try:
            # no dashboard; the scheduler's HTTP routes (health, metrics) on a free local port, not
            # on 8787, where another cluster would make distributed warn on stderr
            with signals_deferred():  # a cluster interrupted half-started cannot be closed
                cluster = self._stack.enter_context(LocalCluster(
                    n_workers=self.workers, threads_per_worker=1, processes=True, dashboard_address=None,
                    scheduler_kwargs={"dashboard_address": "127.0.0.1:0"}, silence_logs=logging.ERROR,
                    env=SINGLE_THREAD, preload=preload))
            self.had_workers = True  # LocalCluster returns once its workers have started
            return self._stack.enter_context(Client(cluster))
        except Exception as error:  # noqa: BLE001 -- a machine that cannot start them (memory, file limits)
            raise InputError(f"--workers: cannot start a local Dask cluster of {self.workers} worker "
                             f"processes ({_brief(error)}); expected fewer --workers, or --workers 0 "
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
            raise ClusterFailure(f"{self.where} lost a task: {_brief(error)}") from None


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
                                 f"({_brief(error)})") from None
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


DEFERRED_SIGNALS = ("SIGINT", "SIGTERM", "SIGHUP")  # the ones that end a command (stitchplan.cli)


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """While it is open, Ctrl-C (and SIGTERM, SIGHUP) only are noted; on closing, the first
    one noted is handled as it would have been (KeyboardInterrupt, the command's exit). For the
    start of a local cluster: distributed cannot close one interrupted half-started (its exit
    function fails on the nannies still starting, with a traceback), so the interrupt waits
    the seconds until the cluster is up and in the executor's hands. Outside the main thread
    (where signal handlers cannot be set) it does nothing."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    noted: list[int] = []
    numbers = [getattr(signal, name) for name in DEFERRED_SIGNALS if hasattr(signal, name)]
    previous = {number: signal.signal(number, lambda number, frame: noted.append(number)) for number in numbers}
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
    if noted:
        handler = previous[noted[0]]
        if callable(handler):
            handler(noted[0], None)
        elif handler == signal.SIG_DFL:
            os.kill(os.getpid(), noted[0])


# --- reaching a scheduler ---------------------------------------------------------------------


def probe_scheduler(address: str, timeout: float | None = None) -> None:
    """Connect to `address` and ask who is there (distributed's `identity` message), within
    `timeout` seconds (CONNECT_TIMEOUT_S) in all: an InputError naming --scheduler unless a
    Dask scheduler answers. distributed.Client bounds the connection itself by its `timeout`
    but not the handshake that follows, which a server that never answers holds forever."""
    import asyncio

    from distributed.comm import connect
    from distributed.security import Security

    timeout = CONNECT_TIMEOUT_S if timeout is None else timeout
    expected = "expected the address of a running `dask scheduler`"

    connecting = 0.8 * timeout  # the rest of the deadline is for the handshake and the answer

    async def identity() -> Any:
        # distributed's connect() retries for its `timeout`, then raises a plain OSError
        comm = await connect(address, timeout=connecting, **Security().get_connection_args("client"))
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            comm.abort()

    try:
        reply = asyncio.run(asyncio.wait_for(identity(), timeout))
    except TimeoutError:  # the deadline (asyncio.TimeoutError is TimeoutError)
        raise InputError(f"--scheduler: no answer from {address} within {timeout:g} s; {expected}") from None
    except Exception as error:  # noqa: BLE001 -- whatever a server that is not a scheduler makes of it
        if type(error) is OSError:  # connect() gave up: nothing listening, or the host unreachable
            why = _why_unreachable(address, timeout - connecting) or _brief(_last_cause(error))
            raise InputError(f"--scheduler: cannot connect to {address} within {timeout:g} s ({why}); "
                             f"{expected}") from None
        raise InputError(f"--scheduler: {address} does not answer as a Dask scheduler (its reply could "
                         f"not be read: {_brief(error)}); {expected}") from None
    kind = reply.get("type") if isinstance(reply, dict) else None
    if kind != "Scheduler":
        what = f"a Dask {kind}" if isinstance(kind, str) else f"a reply of type {type(reply).__name__}"
        raise InputError(f"--scheduler: {address} answers as {what}, not a scheduler; {expected}")


def _why_unreachable(address: str, timeout: float) -> str | None:
    """Why a TCP connection to the address fails (refused, unknown host, timed out), from one
    plain attempt; None if it succeeds. distributed's connect() keeps only its last attempt's
    error, often a timeout of an attempt cut short by its deadline."""
    import socket

    try:
        with socket.create_connection(check_scheduler_address(address), timeout=max(timeout, 0.1)):
            return None
    except OSError as error:
        return _brief(error)


def _last_cause(error: BaseException) -> BaseException:
    """The error at the bottom of `error`'s chain of causes (the refused connection, the
    unknown host), not distributed's wrappers of it."""
    while error.__cause__ is not None:
        error = error.__cause__
    return error


def _open_file_limit() -> int | None:
    """The soft limit on open files of this process, None when unknown or unlimited."""
    try:
        import resource
    except ImportError:  # not a POSIX system
        return None
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    return None if soft == resource.RLIM_INFINITY else int(soft)


def _brief(error: BaseException) -> str:
    """`Type: the message on one line`, short enough for the one error line (without the
    `in <distributed.comm...>: ` that distributed puts before the message it wraps)."""
    text = re.sub(r"^in <[^>]*>: ", "", " ".join(str(error).split()))
    text = f"{type(error).__name__}: {text}" if text else type(error).__name__
    return text if len(text) <= 200 else text[:197] + "..."


# --- Dask's log records ------------------------------------------------------------------------


class _ToPackageLog(logging.Handler):
    """Hands Dask's records to this module's logger at DEBUG, named after their origin."""

    def emit(self, record: logging.LogRecord) -> None:
        if log.isEnabledFor(logging.DEBUG):
            try:
                log.debug("%s %s: %s", record.name, record.levelname, record.getMessage(),
                          exc_info=record.exc_info)
            except Exception:  # noqa: BLE001 -- a malformed record of theirs must not end the run
                self.handleError(record)


@contextlib.contextmanager
def dask_logs_to_package() -> Iterator[None]:
    """While it is open, the log records of Dask and the libraries under it in this process
    (DASK_LOGGERS and their children) go to this module's logger at DEBUG instead of the
    stderr handlers distributed installs at import; everything is put back afterwards."""
    loggers = [logging.getLogger(name) for name in _dask_logger_names()]
    saved = [(logger, list(logger.handlers), logger.propagate) for logger in loggers]
    try:
        _forward_to_package(loggers)
        yield
    finally:
        for logger, handlers, propagate in saved:
            logger.handlers = handlers
            logger.propagate = propagate


def dask_setup(worker: Any) -> None:
    """Run in each worker process of a local cluster when it starts (a Dask preload): its
    Dask records are dropped. Its stderr is the user's terminal, distributed's silence_logs
    lets ERROR through and is undone while the worker closes, when the heartbeat to a
    scheduler that has closed first fails; a task's own failure reaches the client anyway.
    A worker process (one its nanny started) ignores Ctrl-C: the terminal sends SIGINT to the
    whole process group, and the worker would end in a traceback of asyncio's CancelledError
    and KeyboardInterrupt while the command, which closes the cluster, stops it anyway.
    Its allocator reuses freed memory, as the command's does (stitchplan/allocator.py)."""
    import multiprocessing
    import threading

    from .allocator import reuse_freed_memory

    reuse_freed_memory()
    for name in _dask_logger_names():
        logging.getLogger(name).setLevel(logging.CRITICAL + 1)
    if multiprocessing.parent_process() is not None and threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def dask_logs_to_package_until_exit() -> None:
    """From now on, for the rest of the process, Dask's log records go to this module's logger
    at DEBUG (as inside `dask_logs_to_package`). For the command's end: a cluster an interrupt
    caught half-started is closed by distributed's exit functions, and its finalizers reap the
    worker processes, each saying so in INFO records that would reach the console."""
    _forward_to_package([logging.getLogger(name) for name in _dask_logger_names()])


def _forward_to_package(loggers: list[logging.Logger]) -> None:
    """Dask's top loggers (DASK_LOGGERS) hand their records to this module's logger, their
    children pass theirs up to them, and none reaches a stderr handler of its own."""
    forward = _ToPackageLog()
    for logger in loggers:
        logger.handlers = [forward] if logger.name in DASK_LOGGERS else []
        logger.propagate = logger.name not in DASK_LOGGERS  # children to their top, tops nowhere


def _dask_logger_names() -> list[str]:
    """DASK_LOGGERS and every logger made so far below them, sorted."""
    names = {name for name in list(logging.root.manager.loggerDict) if name.split(".")[0] in DASK_LOGGERS}
    return sorted(names | set(DASK_LOGGERS))
