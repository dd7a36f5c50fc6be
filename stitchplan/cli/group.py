"""The `stitchplan` command group: the app, its error handling and exit codes.

Errors end as `error:` lines with the exit codes of EXIT_CODES; anything else is a bug and
shows its traceback.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
import warnings
from collections.abc import Callable
from contextvars import ContextVar
from enum import Enum
from typing import Any

import typer
from typer.core import TyperGroup

from .. import __version__

# the numerics are sparse and small-dense; BLAS threads only compete with each other on a
# busy machine (set the variable yourself to override)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

EXIT_CODES = (
    "Exit codes: 0 done; 1 a numerical method failed on an accepted input (one `error:` line "
    "says what and where); 2 unusable input: a scenario field, an option or an input file "
    "(`error:` lines name it, the value received and what was expected), or an output that "
    "cannot be written, standard output included. A reader that closes the pipe early "
    "(`| head`) ends the command quietly with 1; an interrupt with 128 + the signal (130 for "
    "Ctrl-C, 143 for SIGTERM), no output written. A traceback is a bug in stitchplan (exit "
    "code 1): please report it."
)


COMMAND_LINE: ContextVar[list[str] | None] = ContextVar("COMMAND_LINE", default=None)


class Commands(TyperGroup):
    """The app's command group. Run standalone (the `stitchplan` script, `python -m
    stitchplan`, typer's CliRunner) it runs the commands with click's own error handling
    off and reports the errors a user can act on as `error:` lines (see `exit_code`)."""

    def make_context(self, info_name, args, parent=None, **extra):
        """Keeps the command line (argv as a list) in COMMAND_LINE for the outputs' provenance."""
        # `python -m stitchplan` is the program's name under -m: three arguments of the command line
        COMMAND_LINE.set([*(info_name or "stitchplan").split(), *args])
        return super().make_context(info_name, args, parent=parent, **extra)

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        run = super().main
        if not standalone_mode:
            return run(args, prog_name, complete_var, standalone_mode=False, **extra)
        sys.exit(exit_code(lambda: run(args, prog_name, complete_var, standalone_mode=False, **extra)))


app = typer.Typer(
    cls=Commands,
    no_args_is_help=True,
    pretty_exceptions_enable=False,  # a bug shows Python's plain traceback
    rich_markup_mode=None,  # click's plain help: typer's rich help formatting costs ~0.15 s of start-up
    help="Simulate curved suture needle insertion into deformable tissue and plan the "
    "needle-centre trajectory that compensates the deformation.",
    epilog=EXIT_CODES,
)
calibrate_app = typer.Typer(no_args_is_help=True, rich_markup_mode=None, help="Fit model parameters to measurements.")
app.add_typer(calibrate_app, name="calibrate")


# --- errors ----------------------------------------------------------------------------------


def exit_code(run: Callable[[], Any]) -> int:
    """Run the app (click's standalone mode off) and return its exit code. The project's own
    errors (stitchplan.errors), click's usage errors and a failed write to standard output
    become `error:` lines on stderr; any other exception propagates with its traceback.

    What the command prints goes to standard output when it has finished, after its output
    files have been renamed into place and before they are kept (io/commits.py): if standard
    output cannot be written, the files are undone, so a failed command leaves none."""
    from ..errors import StitchplanError  # no imports of its own: stays instant
    from ..io.commits import deferred_commits
    from . import stdout_failure, own_process

    click_errors = sys.modules[typer.BadParameter.__module__]  # click's, or typer's copy of it
    # numpy's floating-point warnings (an overflow to inf, an invalid operation to nan) in the
    # package's code are not for the user: its checks (det F, finite residuals and outputs)
    # turn what they lead to into the one `error:` line
    warnings.filterwarnings("ignore", category=RuntimeWarning, module=r"stitchplan\.")
    stdout = _HeldStream(sys.stdout)
    sys.stdout = stdout
    try:
        try:
            with deferred_commits(ignore_interrupts_until_exit=own_process()) as outputs:
                result = run()
                stdout.finished = True
                outputs.commit()
                stdout.deliver()
                outputs.keep()
        except BaseException as error:  # what it printed before failing, unless printing failed
            if error is not stdout.failure:
                stdout.deliver_quietly()
            raise
    except StitchplanError as error:
        _echo_errors(problem_lines(error))
        return error.exit_code
    except click_errors.UsageError as error:
        if type(error).__name__ == "NoArgsIsHelpError":  # bare `stitchplan`: the help was the answer
            if error.format_message().strip():  # the help has already been printed
                error.show()
            return error.exit_code
        _echo_errors([usage_message(error, click_errors)])
        return error.exit_code
    except (typer.Abort, getattr(click_errors, "Abort", typer.Abort)):
        _echo_errors(["aborted"])
        return 1
    except click_errors.ClickException as error:
        _echo_errors([error.format_message()])
        return error.exit_code
    except OSError as error:
        if error is not stdout.failure:
            raise
        return stdout_failure(error)
    except (ImportError, MemoryError) as error:
        line = address_space_failure(error)
        if line is None:  # not the limit's doing: a bug, with its traceback
            raise
        _echo_errors([line])
        return 2
    finally:
        sys.stdout = stdout.stream
    return result if isinstance(result, int) else 0  # click returns typer.Exit's code


# what the dynamic loader says when mapping a library fails for want of address space
_MAP_FAILURES = ("failed to map segment", "cannot allocate memory", "cannot map zero-fill pages")


def address_space_failure(error: BaseException) -> str | None:
    """The `error:` line for a library that could not be loaded (an ImportError from the
    loader's mmap) or memory that could not be had (MemoryError) under the process's
    address-space limit (RLIMIT_AS, `ulimit -v`); None without such a limit, or for an
    ImportError of another cause. Under `ulimit -v 150000` importing scipy's OpenBLAS fails
    before any guard can run; a library imported within a run (calibrate material's optimizer)
    may fail once the run's factors fill the limit, which the line then says."""
    import resource

    limit, _ = resource.getrlimit(resource.RLIMIT_AS)
    if limit == resource.RLIM_INFINITY:
        return None
    if isinstance(error, ImportError) and not any(text in str(error).lower() for text in _MAP_FAILURES):
        return None
    limit_text = f"the process's address-space limit (ulimit -v {limit // 1024}) of {limit / 1e6:.0f} MB"
    if isinstance(error, MemoryError):
        return f"out of memory within {limit_text}; raise the limit, or make the run smaller"
    from ..resources import machine

    peak = machine.mapped_peak()
    if peak is not None and peak > machine.IMPORTS_MAPPED_AT_MOST:  # the run's arrays had filled the limit
        return (f"a library loaded within the run could not be mapped within {limit_text}, its arrays and "
                f"factors holding the rest ({error}); raise the limit, or make the run smaller")
    return (f"the numerical libraries could not be loaded within {limit_text} ({error}); raise the limit: "
            "their imports alone map ~300 MB of address space")


class _HeldStream(io.StringIO):
    """Standard output held while the command runs: `deliver()` writes it to the real
    stream and flushes, remembering an OSError there, so that `exit_code` can tell standard
    output that cannot be written (`> /dev/full`, a closed pipe) from an OSError of a bug."""

    def __init__(self, stream):
        super().__init__()
        self.stream = stream
        self.failure: OSError | None = None
        self.finished = False  # the command returned: its lines report a success

    def fileno(self) -> int:  # child processes and faulthandler write to the real one
        return self.stream.fileno()

    def isatty(self) -> bool:
        return self.stream.isatty()

    def deliver(self) -> None:
        text = self.getvalue()
        self.seek(0)
        self.truncate()
        try:
            if text:
                self._write(text)
            self.stream.flush()
        except OSError as error:
            self.failure = error
            raise

    def _write(self, text: str) -> None:
        """`text` on the real stream; characters its encoding cannot hold (a non-ASCII path
        under PYTHONIOENCODING=ascii) escaped, as the error lines on stderr are."""
        try:
            self.stream.write(text)
        except UnicodeEncodeError:
            encoding = getattr(self.stream, "encoding", None) or "ascii"
            self.stream.write(text.encode(encoding, "backslashreplace").decode(encoding))

    def deliver_quietly(self) -> None:
        """What the command printed before it failed, if standard output takes it; nothing
        when the command had finished and its outputs then failed to land (its lines would
        report them written)."""
        if self.finished:
            return
        with contextlib.suppress(OSError, ValueError):
            self.deliver()


def _echo_errors(lines: list[str]) -> None:
    """One `error:` line per problem: a check that two models of a run make alike (an option
    out of range for the planned and the refined model, or for two experiments) says it once.
    A control character or line separator within a problem (a file name holding a line break)
    is shown escaped, as Python writes it in a string (\\n), so that the problem stays one line."""
    try:
        for line in dict.fromkeys(map(_one_line, lines)):
            typer.echo(f"error: {line}", err=True)
    except OSError:  # stderr cannot be written (a full disk): the exit code still tells
        pass


def problem_lines(error: BaseException) -> list[str]:
    """The problems of one of the project's errors: its `lines`, or its message's lines, where
    an argument of the command line holding a line break (a file name) is one problem's text,
    its line breaks shown escaped, not two problems."""
    lines = getattr(error, "lines", None)
    if lines:
        return list(lines)
    message = str(error)
    given = {text for argument in COMMAND_LINE.get() or () for text in (argument, argument.partition("=")[2])}
    for text in sorted((text for text in given if text and text.splitlines() != [text]), key=len, reverse=True):
        message = message.replace(text, _one_line(text))
    return message.splitlines() or [type(error).__name__]


def _one_line(text: str) -> str:
    """`text` with its control characters (Unicode category Cc: line breaks, tab, NUL, escape)
    and line separators escaped (`\\n`, `\\x1b`, `\\u2028`)."""
    import unicodedata

    return "".join(ch.encode("unicode_escape").decode("ascii") if unicodedata.category(ch) in ("Cc", "Zl", "Zp")
                   else ch for ch in text)


# what typer's value checks expected, by pydantic error type
_EXPECTED = {"float_parsing": "a number", "float_type": "a number", "int_parsing": "an integer",
             "int_from_float": "an integer", "bool_parsing": "true or false",
             "finite_number": "a finite number"}


def usage_message(error, click_errors) -> str:
    """One line in the project's style: `--spacing: got 'abc', expected a number`."""
    param = getattr(error, "param", None)
    if (isinstance(error, click_errors.BadParameter) and param is not None
            and not isinstance(error, click_errors.MissingParameter)):
        if getattr(param, "param_type_name", "") == "argument":  # as --help shows it: SCENARIO
            name = param.metavar or param.name.upper()
        else:
            name = "/".join(param.opts) if getattr(param, "opts", None) else param.human_readable_name
        return f"{name}: {_bad_value(error)}"
    message = error.format_message().strip().rstrip(".")
    message = message[:1].lower() + message[1:]
    ctx = getattr(error, "ctx", None)
    if ctx is None:
        return message
    # click's suggestion ends the message as a question: the pointer to --help then follows it
    return f"{message} See '{ctx.command_path} --help'." if message.endswith("?") else \
        f"{message}; see '{ctx.command_path} --help'"


def _bad_value(error) -> str:
    message = error.message.removeprefix("Value error, ")
    issues = error.__cause__.errors() if hasattr(error.__cause__, "errors") else []  # pydantic
    if not issues or "input" not in issues[0]:
        return message
    choices = _choices(error.param)
    expected = "one of " + ", ".join(choices) if choices else _EXPECTED.get(issues[0].get("type"))
    return f"got {issues[0]['input']!r}, expected {expected}" if expected else message


def _choices(param) -> list[str]:
    """The allowed values of a choice parameter (typer's descriptor, or click's Choice type)."""
    choices = (getattr(getattr(param, "type_descriptor", None), "choices", None)
               or getattr(getattr(param, "type", None), "choices", None) or ())
    return [choice.value if isinstance(choice, Enum) else str(choice) for choice in choices]




def _print_version(value: bool) -> None:
    if value:
        typer.echo(f"stitchplan {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True,
                                 help="Print the version and exit."),
) -> None:
    pass
