"""Options and helpers shared by the commands: the enumerated choices, discretization
overrides, logging switches, and the small parsers of option values."""

from __future__ import annotations

import math
from enum import Enum
from pathlib import Path
from typing import Optional

import typer


class LinearSolver(str, Enum):
    """--linear-solver; the values of config.LINEAR_SOLVERS (written here, not imported:
    the config imports numpy, and --help must not)."""

    direct = "direct"
    minres = "minres"


class TipTracking(str, Enum):
    """--tip-tracking; the values of config.TIP_TRACKING (see LinearSolver)."""

    auto = "auto"
    inverse_gradient = "inverse-gradient"
    levenberg_marquardt = "levenberg-marquardt"


def _positive_spacing(value: Optional[float]) -> Optional[float]:
    if value is not None and not 0 < value < math.inf:  # also refuses nan
        raise typer.BadParameter(f"got {value!r}, expected a positive number (mm)")
    return value


def _dilation_above_one(value: Optional[float]) -> Optional[float]:
    if value is not None and not 1 < value < math.inf:
        raise typer.BadParameter(f"got {value!r}, expected a number > 1 (kernel support / spacing)")
    return value


ScenarioArgument = typer.Argument(..., metavar="SCENARIO",
                                  help="Scenario YAML file (see README: Scenario format).")
SpacingOption = typer.Option(None, "--spacing", callback=_positive_spacing,
                             help="Particle spacing in mm (overrides the scenario).")
DilationOption = typer.Option(None, "--dilation", callback=_dilation_above_one,
                              help="Kernel support / spacing (overrides the scenario).")
SummaryOption = typer.Option(None, "--summary", help="Write a JSON summary here.")
VerboseOption = typer.Option(
    0, "--verbose", "-v", count=True, show_default=False, metavar="",
    help="Log progress on stderr: load steps with their Newton iterations, needle steps; "
    "-vv also every Newton iteration.")
QuietOption = typer.Option(False, "--quiet", "-q",
                           help="Errors only: no warnings, notes or progress bar.")


def _setup_logging(verbose: int, quiet: bool = False) -> None:
    """-q: errors only; default: warnings; -v: progress (INFO); -vv: every iteration (DEBUG)."""
    from ..errors import InputError
    from ..io.progress import configure_terminal

    if verbose and quiet:
        raise InputError("-v/--verbose and -q/--quiet: got both, expected at most one")
    configure_terminal(verbose=int(verbose), quiet=quiet)


def _load(scenario_path: Path, spacing: Optional[float], dilation: Optional[float]):
    from ..config import load_scenario, with_discretization

    return with_discretization(load_scenario(scenario_path), spacing=spacing, dilation=dilation)


def _check_outputs(*paths: Optional[Path]) -> None:
    """Fail before any work if an output cannot be written."""
    from ..io.files import check_output_paths

    check_output_paths(*paths)


def _value(choice: Optional[Enum]) -> Optional[str]:
    return None if choice is None else choice.value



def _parse_steps(text: Optional[str]) -> Optional[list[int]]:
    from ..errors import InputError

    if not text:
        return None
    try:
        return [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise InputError(f"--plot-steps: got {text!r}, expected comma-separated step numbers") from None


LinearSolverOption = typer.Option(None, "--linear-solver",
                                  help="Saddle-point solver (overrides the scenario).")
TipTrackingOption = typer.Option(
    None, "--tip-tracking",
    help="How the tip's next material point is found; auto: inverse gradient, falling back to "
    "Levenberg-Marquardt (overrides the scenario).")


def _expected_steps(scenario) -> int:
    from ..needle.geometry import scenario_needle

    return scenario_needle(scenario).expected_steps


def _echo_events(events, quiet: bool, shown: int = 3) -> None:
    """The first `shown` events of a run as `note:` lines on stderr (none with -q)."""
    if quiet:
        return
    for event in events[:shown]:
        typer.echo(f"note: {event.message}", err=True)
    if len(events) > shown:
        typer.echo(f"note: {len(events) - shown} more notes in the summary and run log", err=True)


def _parse_base_transform(text: Optional[str]):
    from ..errors import InputError

    if text is None:
        return None
    try:
        rotation, tx, ty = (float(part) for part in text.split(","))
        if not all(abs(value) < float("inf") for value in (rotation, tx, ty)):  # nan, inf
            raise ValueError
    except ValueError:
        raise InputError(f"--base-transform: got {text!r}, expected ROTATION_DEG,TX_MM,TY_MM") from None
    return rotation, (tx, ty)


