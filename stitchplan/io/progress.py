"""What a run shows on stderr while it works: log lines and a progress bar.

configure_terminal sets how much: -q errors only and no bar; by default warnings; -v
progress (INFO); -vv every iteration (DEBUG). On a terminal one rich console draws both,
so log lines scroll above the bar instead of through it; otherwise (a log file, a pipe)
there is no bar and each log record is one plain line.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import sys
import warnings
from collections.abc import Callable, Iterator

_settings = {"bars": True}


@functools.cache
def stderr_console():
    """One rich console on stderr (it follows sys.stderr when that is replaced)."""
    from rich.console import Console

    return Console(stderr=True)


def configure_terminal(verbose: int = 0, quiet: bool = False) -> None:
    """Route the `stitchplan` loggers to stderr at the level the options ask for: through
    rich on a terminal, as plain `LEVEL logger: message` lines otherwise (one line a record,
    for log files; a warning as `warning: message`). A second call replaces the first (tests
    run many commands in a process)."""
    level = logging.ERROR if quiet else {0: logging.WARNING, 1: logging.INFO}.get(verbose, logging.DEBUG)
    if quiet:  # errors only: matplotlib's notes (its cache folder, a glyph a font lacks) too
        logging.getLogger("matplotlib").setLevel(logging.ERROR)
        warnings.filterwarnings("ignore", category=UserWarning, module="matplotlib")
    logger = logging.getLogger("stitchplan")
    for handler in [h for h in logger.handlers if getattr(h, "stitchplan_terminal", False)]:
        logger.removeHandler(handler)
    if sys.stderr.isatty():
        from rich.logging import RichHandler

        handler = RichHandler(console=stderr_console(), show_path=False, markup=False,
                              log_time_format="[%X]")
    else:
        handler = _StderrHandler()
        handler.setFormatter(_PlainFormatter("%(levelname)s %(name)s: %(message)s"))
    handler.stitchplan_terminal = True
    logger.addHandler(handler)
    logger.setLevel(level)
    _settings["bars"] = not quiet


class _PlainFormatter(logging.Formatter):
    """A warning as the command's own `error:` and `note:` lines (`warning: ...`, what a user
    sees without -v); progress and iterations (-v, -vv) keep their level and logger."""

    def format(self, record: logging.LogRecord) -> str:
        if record.levelno >= logging.WARNING:
            return f"{record.levelname.lower()}: {record.getMessage()}"
        return super().format(record)


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever sys.stderr is at the time of the record."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


@contextlib.contextmanager
def progress_bar(label: str, total: int | None) -> Iterator[Callable[..., None]]:
    """Yields advance(n=1, description=None); draws nothing unless stderr is a terminal (and
    the run is not quiet)."""
    if not (_settings["bars"] and sys.stderr.isatty()):
        yield lambda *args, **kwargs: None
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    columns = [TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn()]
    with Progress(*columns, console=stderr_console(), transient=True) as progress:
        task = progress.add_task(label, total=total)

        def advance(n: int = 1, description: str | None = None) -> None:
            progress.update(task, advance=n, **({"description": description} if description else {}))

        yield advance
