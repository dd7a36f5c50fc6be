"""Outputs that wait for the command: within `deferred_commits` (cli.group.exit_code), the
sets OutputSet.staged() has written (io/files.py) are renamed into place when the command
has finished, and kept only once its lines have reached standard output; a command that fails
after writing them (standard output full) leaves no file, and a replaced file comes back.
Light on imports: the command group enters it before every command, `--help` included."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator
from contextvars import ContextVar
from typing import Any

from ..parallel.signals import DEFERRED_SIGNALS, signals_deferred


DEFERRED: ContextVar[DeferredOutputs | None] = ContextVar("stitchplan_deferred_outputs", default=None)


class DeferredOutputs:
    """The staged sets of a command: `commit()` renames them all into place (all or none),
    `keep()` makes that final; anything else is undone when the block is left."""

    def __init__(self):
        self.pending: list[Any] = []  # io.files._Staged
        self.renamed = None  # io.files.Renamed, committed but not yet kept
        self._commit_all: Callable[..., Any] | None = None
        self._lock_all: Callable[[list[Any]], Any] | None = None
        self.ignored: dict[int, Any] = {}  # the interrupts' handlers before keep() ignored them

    def add(self, staged: Any, commit_all: Callable[..., Any], lock_all: Callable[[list[Any]], Any]) -> None:
        """Hold a staged set until `commit()`, which locks the held sets' folders by
        `lock_all` and renames them by `commit_all` (io.files.lock_staged, commit_staged:
        this module stays free of the writers' imports)."""
        self.pending.append(staged)
        self._commit_all, self._lock_all = commit_all, lock_all

    def commit(self) -> None:
        if self.pending:
            locks = self._lock_all(self.pending)  # before the interrupts wait: another command may hold them
            # an interrupt waits for the renames and their record, then undoes them all: between
            # two renames it left one output replaced, the others not, and backups beside them
            try:
                with signals_deferred():
                    self.renamed = self._commit_all(self.pending, locks)
            except BaseException:
                locks.release()
                raise

    def keep(self) -> None:
        """Make the renames final. An interrupt from here on, until the process exits, is
        ignored: it can no longer undo them, and its exit code would say none was written."""
        if self.renamed is not None:
            if threading.current_thread() is threading.main_thread():
                self.ignored = {number: signal.signal(number, signal.SIG_IGN)
                                for number in (getattr(signal, name) for name in DEFERRED_SIGNALS
                                               if hasattr(signal, name))}
            self.renamed.keep()
            self.renamed = None

    def restore_interrupts(self) -> None:
        for number, handler in self.ignored.items():
            signal.signal(number, handler)
        self.ignored = {}


@contextlib.contextmanager
def deferred_commits(ignore_interrupts_until_exit: bool = False) -> Iterator[DeferredOutputs]:
    """Within the block, OutputSet.staged() leaves its written temporaries staged (see
    DeferredOutputs); leaving it undoes a commit not kept and removes what was not committed.
    Interrupts ignored once the outputs are kept are handled again when it ends, unless
    `ignore_interrupts_until_exit` (the command is its process's: cli.main)."""
    outputs = DeferredOutputs()
    token = DEFERRED.set(outputs)
    try:
        yield outputs
    finally:
        DEFERRED.reset(token)
        with signals_deferred():  # an undo cut short would leave some files replaced
            if outputs.renamed is not None:
                outputs.renamed.undo()
            for staged in outputs.pending:
                staged.discard()
        if not ignore_interrupts_until_exit:
            outputs.restore_interrupts()
