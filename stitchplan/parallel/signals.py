"""Ctrl-C, SIGTERM and SIGHUP held back while a local cluster starts (signals_deferred)."""

from __future__ import annotations

import contextlib
import os
import signal
from collections.abc import Iterator

DEFERRED_SIGNALS = ("SIGINT", "SIGTERM", "SIGHUP")  # the ones that end a command (stitchplan.cli)


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """While it is open, Ctrl-C (and SIGTERM, SIGHUP) only are noted; on closing, the first
    one noted is handled as it would have been (KeyboardInterrupt, the command's exit), also
    when the block raised (the interrupt then raised from its error). For the
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
        # also when the block failed: a group's Ctrl-C stops a cluster's workers as they start
        # too, and the interrupt, not the start that failed of it, is how the command ended
        if noted:
            handler = previous[noted[0]]
            if callable(handler):
                handler(noted[0], None)
            elif handler == signal.SIG_DFL:
                os.kill(os.getpid(), noted[0])
