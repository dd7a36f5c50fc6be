"""Outputs that wait for the command: within `deferred_commits` (cli.group.exit_code), the
sets OutputSet.staged() has written (io/files.py) are renamed into place when the command
has finished, and kept only once its lines have reached standard output; a command that fails
after writing them (standard output full) leaves no file, and a replaced file comes back.
Light on imports: the command group enters it before every command, `--help` included."""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from contextvars import ContextVar
from typing import Any


DEFERRED: ContextVar[DeferredOutputs | None] = ContextVar("stitchplan_deferred_outputs", default=None)


class DeferredOutputs:
    """The staged sets of a command: `commit()` renames them all into place (all or none),
    `keep()` makes that final; anything else is undone when the block is left."""

    def __init__(self):
        self.pending: list[Any] = []  # io.files._Staged
        self.renamed = None  # io.files.Renamed, committed but not yet kept
        self._commit_all: Callable[[list[Any]], Any] | None = None

    def add(self, staged: Any, commit_all: Callable[[list[Any]], Any]) -> None:
        """Hold a staged set until `commit()`, which renames the held sets by `commit_all`
        (io.files.commit_staged: this module stays free of the writers' imports)."""
        self.pending.append(staged)
        self._commit_all = commit_all

    def commit(self) -> None:
        if self.pending:
            self.renamed = self._commit_all(self.pending)

    def keep(self) -> None:
        if self.renamed is not None:
            self.renamed.keep()
            self.renamed = None


@contextlib.contextmanager
def deferred_commits() -> Iterator[DeferredOutputs]:
    """Within the block, OutputSet.staged() leaves its written temporaries staged (see
    DeferredOutputs); leaving it undoes a commit not kept and removes what was not committed."""
    outputs = DeferredOutputs()
    token = DEFERRED.set(outputs)
    try:
        yield outputs
    finally:
        DEFERRED.reset(token)
        if outputs.renamed is not None:
            outputs.renamed.undo()
        for staged in outputs.pending:
            staged.discard()
