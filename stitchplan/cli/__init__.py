"""Command-line interface (typer): `stitchplan` and `python -m stitchplan`.

Start-up is instant: `stitchplan --version` imports nothing but the version, the app
(typer and the commands) loads on first use, and numpy, scipy, h5py, matplotlib and rich
are imported inside the commands that use them, never for `--help` or `--version`.
"""

from __future__ import annotations

import sys

# what `from stitchplan.cli import ...` finds, and the module that defines it
_LAZY = {"app": "group", "EXIT_CODES": "group", "exit_code": "group", "usage_message": "group",
         "LinearSolver": "options", "TipTracking": "options"}


def main() -> None:
    """Console entry point of `stitchplan` and `python -m stitchplan`."""
    if sys.argv[1:] == ["--version"]:  # answered before typer is imported
        from .. import __version__

        print(f"stitchplan {__version__}")
        return
    try:
        __getattr__("app")()
    except SystemExit as done:  # the command has ended (a bug's traceback is not caught here)
        if isinstance(done.code, int):
            _exit(done.code)
        raise


def _exit(code: int) -> None:
    """End the process with `code` once the command is done: the exit functions run (log
    handlers flushed and closed, child processes joined) and the streams are flushed, but
    the interpreter's teardown of every imported module is skipped: 0.14 s of a `simulate`
    on sh12_100x100 (benchmarks/plan_speed.py, start-up and end table)."""
    import atexit
    import os

    run_exit_functions = getattr(atexit, "_run_exitfuncs", None)
    if run_exit_functions is None:  # not CPython's atexit: the ordinary exit
        sys.exit(code)
    run_exit_functions()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed or broken pipe: nothing left to write to
            pass
    os._exit(code)


def __getattr__(name: str):
    """The app and its helpers, loaded with the commands registered on first use."""
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from importlib import import_module

    import_module(".calibrate", __name__)  # registers the commands on the app
    import_module(".commands", __name__)
    for attribute, module in _LAZY.items():
        globals()[attribute] = getattr(import_module(f".{module}", __name__), attribute)
    return globals()[name]
