"""Command-line interface (typer): `stitchplan` and `python -m stitchplan`.

Start-up is instant: `stitchplan --version` imports nothing but the version, the app
(typer and the commands) loads on first use, and numpy, scipy, h5py, matplotlib and rich
are imported inside the commands that use them, never for `--help` or `--version`.

Standard output is an output like the files: if it cannot be written (`> /dev/full`, a full
disk) the command ends with one `error:` line and exit code 2; a reader that stops early
(`stitchplan schema | head`) ends it quietly (see `stdout_failure`).
"""

from __future__ import annotations

import os
import signal
import sys

# what `from stitchplan.cli import ...` finds, and the module that defines it
_LAZY = {"app": "group", "EXIT_CODES": "group", "exit_code": "group", "usage_message": "group",
         "LinearSolver": "options", "TipTracking": "options"}

# Run again as the main module of a child process the command started (multiprocessing's spawn
# imports the parent's main module as __mp_main__ first: a local Dask cluster's worker
# processes), the process ignores Ctrl-C from here on: the terminal sends SIGINT to the whole
# process group, the command stops its cluster on the way out, and each worker would print a
# traceback of its own
if "__mp_main__" in sys.modules:
    signal.signal(signal.SIGINT, signal.SIG_IGN)


_OWN_PROCESS = False  # main() runs the command: it ends the process


def own_process() -> bool:
    """The command runs as its process's own (main()), not within another program (a test's
    CliRunner): once its outputs are final, interrupts are ignored until the process exits."""
    return _OWN_PROCESS


def main() -> None:
    """Console entry point of `stitchplan` and `python -m stitchplan`."""
    global _OWN_PROCESS
    _OWN_PROCESS = True
    for name in ("stdout", "stderr"):  # a closed stream (`2>&-`) is None in Python: write nowhere
        if getattr(sys, name) is None:
            setattr(sys, name, open(os.devnull, "w"))
    # SIGTERM and SIGHUP end the command like Ctrl-C does: the outputs' temporaries are
    # removed on the way out (the default action would leave them beside the targets)
    for signal_name in ("SIGTERM", "SIGHUP"):
        if hasattr(signal, signal_name):
            signal.signal(getattr(signal, signal_name), _terminated)
    sys.unraisablehook = _unraisable  # an interrupt a callback swallowed is sent again
    if sys.argv[1:] == ["--version"]:  # answered before typer is imported
        from .. import __version__

        try:
            print(f"stitchplan {__version__}", flush=True)
        except OSError as error:
            _exit(stdout_failure(error))
        return
    from ..allocator import pause_collection, reuse_freed_memory

    pause_collection(command_start=True)  # for the commands' imports, which resume it (stitchplan/allocator.py)
    reuse_freed_memory()  # before the commands' imports allocate
    from ..early_helper import start_for

    # the replay helper, before the command's imports (stitchplan/early_helper.py)
    start_for(sys.argv[1:], server="stitchplan.planning.replays:serve")
    try:
        __getattr__("app")()
    except SystemExit as done:  # the command has ended (a bug's traceback is not caught here)
        if isinstance(done.code, int):
            _exit(done.code)
        raise
    except BaseException as error:
        code = interrupt_code(error)
        if code is None:  # a bug: its traceback
            raise
        _exit(code)


class _Terminated(SystemExit):
    """SIGTERM's or SIGHUP's exit (128 + the signal), raised where the command was."""

    def __init__(self, number: int):
        super().__init__(128 + number)
        self.signal_number = number


def _terminated(number: int, frame) -> None:
    """Unwind the command (context managers and `finally` clean up) and exit 128 + signal."""
    raise _Terminated(number)


def interrupt_code(error: BaseException | None) -> int | None:
    """128 + the signal of the interrupt (Ctrl-C's KeyboardInterrupt, SIGTERM's or SIGHUP's
    exit) that `error` is or was raised from, None if it is none. A signal's handler raises
    where the command happens to be, and Python turns what is raised there into another error
    in places: an exception in a class body's `__set_name__` into a RuntimeError (SIGTERM
    while matplotlib's axes were imported ended in that traceback, exit 1), one in a C
    extension's module initialisation into an ImportError (`initialization failed`, then a
    fatal error as the interpreter finalised the half-made module)."""
    seen = set()
    while error is not None and id(error) not in seen:
        seen.add(id(error))
        if isinstance(error, KeyboardInterrupt):
            return 128 + signal.SIGINT
        if isinstance(error, _Terminated):
            return error.code
        error = error.__cause__ or error.__context__
    return None


def _unraisable(unraisable) -> None:
    """sys.unraisablehook: an interrupt raised within a callback whose exceptions Python only
    reports (a weak reference's, an object's __del__) is sent to the process again, to be
    raised where the command goes on (it was lost: the command ran to its end and wrote its
    outputs, after printing `Exception ignored in ...` and the interrupt's traceback); any
    other is reported as Python does."""
    error = unraisable.exc_value
    if isinstance(error, (KeyboardInterrupt, _Terminated)):
        import threading

        # from another thread, a moment later: sent from here, its handler would raise within
        # this hook, where the interrupt would be lost again
        number = signal.SIGINT if isinstance(error, KeyboardInterrupt) else error.signal_number
        resend = threading.Timer(0.01, os.kill, (os.getpid(), number))
        resend.daemon = True
        resend.start()
    else:
        sys.__unraisablehook__(unraisable)


def _exit(code: int) -> None:
    """End the process with `code` once the command is done: the exit functions run (log
    handlers flushed and closed, child processes joined) and the streams are flushed, but
    the interpreter's teardown of every imported module is skipped: 0.02 s of a `simulate`
    on sh12_100x100 (benchmarks/plan_speed.py, start-up and end table; 0.13 s before the
    imports' objects were frozen out of the collector's passes, stitchplan/allocator.py,
    which the teardown's collections made too)."""
    import atexit

    dask_logs = sys.modules.get("stitchplan.parallel.dask_logs")
    if dask_logs is not None:  # a cluster closed by the exit functions (after Ctrl-C) logs as it goes
        dask_logs.dask_logs_to_package_until_exit()
    run_exit_functions = getattr(atexit, "_run_exitfuncs", None)
    if run_exit_functions is None:  # not CPython's atexit: the ordinary exit
        sys.exit(code)
    run_exit_functions()
    try:
        sys.stdout.flush()
    except OSError as error:  # what the command printed last has not arrived
        code = code or stdout_failure(error)
    except ValueError:  # closed
        pass
    try:
        sys.stderr.flush()
    except (OSError, ValueError):  # a closed or broken pipe: nothing left to write to
        pass
    os._exit(code)


def stdout_failure(error: OSError) -> int:
    """The exit code of a command whose standard output could not be written. A reader that
    closed the pipe ends it quietly with 1, as Python's and click's own tools do; any other
    failure (a full disk, /dev/full) is one `error:` line and exit code 2, like a file that
    cannot be written. What is left in the buffer then goes to the null device, so that the
    flush at exit does not fail again."""
    try:
        descriptor = sys.stdout.fileno()
    except (OSError, ValueError):  # a stream without a file descriptor (a test's capture)
        descriptor = None
    if descriptor is not None:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, descriptor)
        os.close(devnull)
    if isinstance(error, BrokenPipeError):
        return 1
    print(f"error: cannot write standard output: {error.strerror or error}", file=sys.stderr)
    return 2


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
