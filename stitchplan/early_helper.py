"""The replay helper process, started as a command starts (planning/replays.py runs it).

A helper forked once the command has imported numpy, scipy and the package shares those
pages with it, copy-on-write: every page either process then writes (CPython's reference
counts and its specializing interpreter's bytecode caches write to most of the objects a
run touches) is first copied, a page fault each, within the command's planned run. Forked
here instead, before either has imported them, each process imports its own on
its own core and the helper waits for its scenario (planning/replays.py
`BackgroundReplays`); it is ready about when the command reaches it, as the two imports
take about as long (benchmarks/results/replay_helper.md: the commands' own runs 0.99-1.09x
as long with the helper forked late, the whole commands within the noise).

A command that has settled the helper's model and passed the resource guard before its own
imports of the numerics hands it the scenario then (`hand`): the helper, its imports done
first, builds that model while the command still imports (`plan`: its verification's refined
model, cli.commands.plan). Otherwise the replays send it when they start.

This module imports nothing beyond the standard library's process tools, and the helper
imports what it serves (`server`, named by the command line interface: planning/replays.py's
`serve`) only after the fork. A helper no command asks for (the input was refused, the run
ended early) reads the end of its pipe and exits.
"""

from __future__ import annotations

import os
import sys
import threading

HELPER_VARIABLE = "STITCHPLAN_REPLAY_HELPER"  # 0: replays run in the command's process
COMMANDS = ("plan", "simulate")  # the commands whose replays a helper runs

_started: tuple[int, object] | None = None  # the helper forked here: (pid, the command's end of its pipe)
_handed: tuple | None = None  # what `hand` sent it: (scenario, options)
_parent = os.getpid()  # the process that may take it (not a process forked from it later)


HELPER_VALUES = ("0", "1")  # replays in the command's process; in a helper where one can run (the default)


def helper_variable_problem() -> str | None:
    """The line refusing a STITCHPLAN_REPLAY_HELPER other than 0 or 1 (a typo read as "on"
    before), or None."""
    given = os.environ.get(HELPER_VARIABLE)
    if given is None or given in HELPER_VALUES:
        return None
    return (f"{HELPER_VARIABLE}: got {given!r}, expected 0 (the replays in the command's own process) or 1 "
            "(in a helper process where one can run, the default)")


def helper_available() -> bool:
    """Whether a forked helper process can run the replays: Linux (fork is its own way of
    starting a process; macOS's system libraries are not fork-safe), two or more cores, one
    thread in this process (forking a threaded process can deadlock the child), and
    STITCHPLAN_REPLAY_HELPER not 0."""
    if os.environ.get(HELPER_VARIABLE, "") == "0" or not sys.platform.startswith("linux"):
        return False
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return cores >= 2 and threading.active_count() == 1


def start_for(arguments: list[str], server: str) -> None:
    """Fork the helper (`fork_helper`) when `arguments` (the command line after the program)
    run a command whose replays it would run, for the first replays that ask (`take`)."""
    global _started
    if _started is not None or not arguments or arguments[0] not in COMMANDS or helper_variable_problem() \
            or not helper_available():
        return
    # no replays to run: the help, a plan under uncertainty (its sampled runs go to a cluster;
    # `--uncertainty FILE` or `--uncertainty=FILE`), a simulate without its estimate
    if any(argument.split("=", 1)[0] in ("--help", "--uncertainty", "--no-estimate") for argument in arguments):
        return
    try:
        _started = fork_helper(server)
    except OSError:  # no process to be had: the command forks one later, or replays itself
        pass


def fork_helper(server: str) -> tuple[int, object]:
    """A helper process, (pid, this process's end of its pipe): it imports `server`
    ("module:function") and calls it with (its pipe end, the scenario, the options, the
    command's pid) as this process sends them, and never returns from the fork. Raises
    OSError where no process is to be had."""
    from multiprocessing.connection import Pipe

    ours, theirs = Pipe()
    pid = os.fork()
    if pid == 0:
        ours.close()
        _helper(theirs, server)  # never returns
    theirs.close()
    return pid, ours


def hand(scenario, options: dict) -> None:
    """Send the helper forked here its scenario and replay options now (`send_scenario`), as
    the replays would, for it to build its model meanwhile.
    Call it only once the inputs are checked and the resource guard has passed: the helper
    builds whatever it is handed. Does nothing without a helper, or once handed."""
    global _handed
    if _started is None or _handed is not None or os.getpid() != _parent:
        return
    try:
        send_scenario(_started[1], scenario, options)
    except (OSError, ValueError):  # the helper is gone: the replays find out and replay themselves
        return
    _handed = (scenario, options)


def send_scenario(connection, scenario, options: dict) -> None:
    """Send a helper the scenario and replay options it serves (`_helper` reads them)."""
    connection.send(("serve", scenario, options, os.getpid()))


def take() -> tuple[int, object, tuple | None] | None:
    """The helper forked here, for the first replays that ask: (pid, pipe end, what `hand`
    sent it or None), or None."""
    global _started, _handed
    started, handed = _started, _handed
    _started = _handed = None
    if started is not None and os.getpid() == _parent:
        return started[0], started[1], handed
    return None


def _helper(connection, server: str) -> None:
    """The helper's life: import `server`, wait for the scenario, serve it; exit without
    returning to the forking process's code (nor running its exit functions)."""
    code = 0
    try:
        # the helper reports through its pipe only: its standard streams are the null device, so
        # that a caller reading the command's output does not wait for a helper that outlives it
        # (one the command never asked for ends once its imports are done)
        null = os.open(os.devnull, os.O_RDWR)
        for descriptor in (0, 1, 2):
            os.dup2(null, descriptor)
        import importlib

        from .allocator import resume_collection

        module, function = server.split(":")
        serve = getattr(importlib.import_module(module), function)
        resume_collection()  # paused as the command started, before the fork (stitchplan/allocator.py)
        try:
            message = connection.recv()
        except (EOFError, OSError):  # the command ended without replays
            os._exit(0)
        _, scenario, options, parent = message
        serve(connection, scenario, options, parent)
    except BaseException:  # noqa: BLE001 -- the command sees the pipe close and replays itself
        code = 1
    finally:
        os._exit(code)
