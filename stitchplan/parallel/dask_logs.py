"""Dask's log records kept off the console: sent to the package's logger here, dropped in a local cluster's workers."""

from __future__ import annotations

import contextlib
import logging
import signal
from collections.abc import Iterator
from typing import Any

log = logging.getLogger(__package__)  # "stitchplan.parallel", the name its records carry

DASK_LOGGERS = ("distributed", "dask", "tornado", "bokeh")


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
    and KeyboardInterrupt while the command, which closes the cluster, stops it anyway. (Until
    here, while it imports, it has SIGINT blocked from its start: executor's
    _workers_deaf_to_ctrl_c.)
    Its allocator is set as the command's before it starts, by the environment its nanny
    gives it (stitchplan/allocator.py, worker_environment)."""
    import multiprocessing
    import threading

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
