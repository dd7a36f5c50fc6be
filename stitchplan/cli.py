"""Command-line interface: parse options, load the scenario, call one function, write results.

Start-up is instant: numpy, scipy, h5py, matplotlib and rich are imported inside the
commands that use them, never for `--help` or `--version`. Errors end as `error:` lines
with the exit codes of EXIT_CODES; anything else is a bug and shows its traceback.
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Callable
from enum import Enum
from pathlib import Path
from typing import Any, Optional

import typer
from typer.core import TyperGroup

from . import __version__

# the numerics are sparse and small-dense; BLAS threads only compete with each other on a
# busy machine (set the variable yourself to override)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

EXIT_CODES = (
    "Exit codes: 0 done; 1 a numerical method failed on an accepted input (one `error:` line "
    "says what and where); 2 unusable input: a scenario field, an option or an input file "
    "(`error:` lines name it, the value received and what was expected). A traceback is a bug "
    "in stitchplan (exit code 1): please report it."
)


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


class Commands(TyperGroup):
    """The app's command group. Run standalone (the `stitchplan` script, `python -m
    stitchplan`, typer's CliRunner) it runs the commands with click's own error handling
    off and reports the errors a user can act on as `error:` lines (see `exit_code`)."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        run = super().main
        if not standalone_mode:
            return run(args, prog_name, complete_var, standalone_mode=False, **extra)
        sys.exit(exit_code(lambda: run(args, prog_name, complete_var, standalone_mode=False, **extra)))


app = typer.Typer(
    cls=Commands,
    no_args_is_help=True,
    pretty_exceptions_enable=False,  # a bug shows Python's plain traceback
    help="Simulate curved suture needle insertion into deformable tissue and plan the "
    "needle-centre trajectory that compensates the deformation.",
    epilog=EXIT_CODES,
)
calibrate_app = typer.Typer(no_args_is_help=True, help="Fit model parameters to measurements.")
app.add_typer(calibrate_app, name="calibrate")


def main() -> None:
    """Console entry point of `stitchplan` and `python -m stitchplan`."""
    app()


# --- errors ----------------------------------------------------------------------------------


def exit_code(run: Callable[[], Any]) -> int:
    """Run the app (click's standalone mode off) and return its exit code. The project's own
    errors (stitchplan.errors) and click's usage errors become `error:` lines on stderr; any
    other exception propagates with its traceback."""
    from .errors import StitchplanError  # no imports of its own: stays instant

    click_errors = sys.modules[typer.BadParameter.__module__]  # click's, or typer's copy of it
    try:
        result = run()
    except StitchplanError as error:
        _echo_errors(getattr(error, "lines", None) or str(error).splitlines() or [type(error).__name__])
        return error.exit_code
    except click_errors.UsageError as error:
        if type(error).__name__ == "NoArgsIsHelpError":  # bare `stitchplan`: the help was the answer
            if error.format_message().strip():  # typer's rich help has already been printed
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
    return result if isinstance(result, int) else 0  # click returns typer.Exit's code


def _echo_errors(lines: list[str]) -> None:
    for line in lines:
        typer.echo(f"error: {line}", err=True)


# what typer's value checks expected, by pydantic error type
_EXPECTED = {"float_parsing": "a number", "float_type": "a number", "int_parsing": "an integer",
             "int_from_float": "an integer", "bool_parsing": "true or false",
             "finite_number": "a finite number"}


def usage_message(error, click_errors) -> str:
    """One line in the project's style: `--spacing: got 'abc', expected a number`."""
    param = getattr(error, "param", None)
    if (isinstance(error, click_errors.BadParameter) and param is not None
            and not isinstance(error, click_errors.MissingParameter)):
        name = "/".join(param.opts) if getattr(param, "opts", None) else param.human_readable_name
        return f"{name}: {_bad_value(error)}"
    message = error.format_message().strip().rstrip(".")
    message = message[:1].lower() + message[1:]
    ctx = getattr(error, "ctx", None)
    return f"{message}; see '{ctx.command_path} --help'" if ctx is not None else message


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


# --- options shared by the commands ---------------------------------------------------------


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
    from .errors import InputError
    from .io.progress import configure_terminal

    if verbose and quiet:
        raise InputError("-v/--verbose and -q/--quiet: got both, expected at most one")
    configure_terminal(verbose=int(verbose), quiet=quiet)


def _load(scenario_path: Path, spacing: Optional[float], dilation: Optional[float]):
    from .config import load_scenario, with_discretization

    return with_discretization(load_scenario(scenario_path), spacing=spacing, dilation=dilation)


def _check_outputs(*paths: Optional[Path]) -> None:
    """Fail before any work if an output cannot be written."""
    from .io.files import check_output_paths

    check_output_paths(*paths)


def _value(choice: Optional[Enum]) -> Optional[str]:
    return None if choice is None else choice.value


@app.command()
def deform(
    scenario_path: Path = ScenarioArgument,
    probes_out: Optional[Path] = typer.Option(None, "--probes-out", help="CSV x,y,ux,uy per probe."),
    reactions_out: Optional[Path] = typer.Option(None, "--reactions-out",
                                                 help="CSV segment,fx,fy per loaded segment."),
    summary: Optional[Path] = SummaryOption,
    out: Optional[Path] = typer.Option(None, "--out", help="HDF5 run log."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="PNG of the deformed tissue."),
    spacing: Optional[float] = SpacingOption,
    dilation: Optional[float] = DilationOption,
    verbose: int = VerboseOption,
    quiet: bool = QuietOption,
) -> None:
    """Static large-deformation solve of the slab under the scenario's `loads`."""
    _setup_logging(verbose, quiet)
    _check_outputs(probes_out, reactions_out, summary, out, plot)
    scenario = _load(scenario_path, spacing, dilation)
    from .io import reports
    from .io.progress import progress_bar
    from .tissue.deform import run_deform

    with progress_bar("load steps", scenario.load_steps) as advance:
        result = run_deform(scenario, on_step=lambda step, record: advance())
    reports.write_deform_outputs(result, probes_out=probes_out, reactions_out=reactions_out,
                                 summary=summary, out=out, plot=plot)
    typer.echo(reports.deform_line(result))


@calibrate_app.command("material")
def calibrate_material(
    calibration_path: Path = typer.Argument(..., help="Calibration YAML: tissue, experiments "
                                            "(loads + markers CSV x,y,x_def,y_def), fit ranges."),
    out: Path = typer.Option(..., "--out",
                             help="Fitted YAML: `material:` block, fit quality, diagnostics."),
    plot_dir: Optional[Path] = typer.Option(
        None, "--plot-dir", help="Folder for cost_surface.png and marker_residuals.png."),
    spacing: Optional[float] = SpacingOption,
    dilation: Optional[float] = DilationOption,
    verbose: int = VerboseOption,
    quiet: bool = QuietOption,
) -> None:
    """Fit lame_lambda and lame_mu to marker displacements (grid search, then least squares)."""
    _setup_logging(verbose, quiet)
    _check_outputs(out, None if plot_dir is None else plot_dir / "cost_surface.png")
    from . import calibration
    from .io.calibration_reports import material_summary_line, write_material_outputs
    from .io.progress import progress_bar

    result = calibration.calibrate_material(calibration_path, spacing, dilation, progress=progress_bar)
    write_material_outputs(result, out, plot_dir)
    typer.echo(material_summary_line(result))


@calibrate_app.command("needle")
def calibrate_needle(
    air: Path = typer.Option(..., "--air", help="CSV angle_rad,force_N: needle rotated in air."),
    tissue: Path = typer.Option(..., "--tissue", help="CSV angle_rad,force_N: needle rotated into "
                                "the tissue, angle from the moment the tip touches it."),
    radius: float = typer.Option(..., "--radius", help="Needle radius, mm."),
    out: Path = typer.Option(..., "--out", help="YAML with friction, cutting_force and diagnostics."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="PNG of the recordings and the fit."),
    verbose: int = VerboseOption,
    quiet: bool = QuietOption,
) -> None:
    """Fit needle friction (N/mm) and cutting force (N) to force recordings in air and tissue."""
    _setup_logging(verbose, quiet)
    _check_outputs(out, plot)
    from . import calibration
    from .io.calibration_reports import needle_summary_line, write_needle_outputs

    result = calibration.calibrate_needle(air, tissue, radius)
    write_needle_outputs(result, out, plot)
    typer.echo(needle_summary_line(result))


def _parse_steps(text: Optional[str]) -> Optional[list[int]]:
    from .errors import InputError

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


@app.command()
def simulate(
    scenario_path: Path = ScenarioArgument,
    out: Optional[Path] = typer.Option(None, "--out", help="HDF5 run log."),
    summary: Optional[Path] = SummaryOption,
    plot: Optional[Path] = typer.Option(None, "--plot", help="PNG: deformed tissue, needle and tip path."),
    plot_steps: Optional[str] = typer.Option(None, "--plot-steps", help="Steps to draw, e.g. 10,20,37."),
    spacing: Optional[float] = SpacingOption,
    dilation: Optional[float] = DilationOption,
    linear_solver: Optional[LinearSolver] = LinearSolverOption,
    tip_tracking: Optional[TipTracking] = TipTrackingOption,
    condition_numbers: bool = typer.Option(False, "--condition-numbers",
                                           help="Record condition numbers per step (dense; small models)."),
    center_path: Optional[Path] = typer.Option(
        None, "--center-path", help="Replay needle centres from a trajectory CSV (row n = step n)."),
    verbose: int = VerboseOption,
    quiet: bool = QuietOption,
) -> None:
    """Needle insertion without planning: the needle centre stays fixed.

    Thesis Algorithm 1. With --center-path the centre follows a trajectory instead (replay).
    """
    _setup_logging(verbose, quiet)
    _check_outputs(out, summary, plot)
    steps_to_plot = _parse_steps(plot_steps)
    scenario = _load(scenario_path, spacing, dilation)
    from .io import reports
    from .io.progress import progress_bar
    from .io.readers import read_center_path
    from .needle.insertion import run_insertion
    from .study.auto import resolve_accuracy

    linear_solver, tip_tracking = _value(linear_solver), _value(tip_tracking)
    path = read_center_path(center_path) if center_path is not None else None
    scenario, auto_note = resolve_accuracy(scenario, tip_tracking, linear_solver)
    with progress_bar("needle steps", _expected_steps(scenario)) as advance:
        result = run_insertion(scenario, linear_solver=linear_solver, tip_tracking=tip_tracking,
                               condition_numbers=condition_numbers, center_path=path,
                               on_step=lambda record: advance())
    if auto_note is not None:
        result.events.insert(0, auto_note)
    reports.write_insertion_outputs(result, "simulate", out=out, summary=summary, plot=plot,
                                    plot_steps=steps_to_plot)
    typer.echo(reports.insertion_line(result, "simulate"))
    _echo_events(result.events, quiet)


def _expected_steps(scenario) -> int:
    from .needle.geometry import scenario_needle

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
    from .errors import InputError

    if text is None:
        return None
    try:
        rotation, tx, ty = (float(part) for part in text.split(","))
        if not all(abs(value) < float("inf") for value in (rotation, tx, ty)):  # nan, inf
            raise ValueError
    except ValueError:
        raise InputError(f"--base-transform: got {text!r}, expected ROTATION_DEG,TX_MM,TY_MM") from None
    return rotation, (tx, ty)


@app.command()
def plan(
    scenario_path: Path = ScenarioArgument,
    export: Path = typer.Option(..., "--export", help="Trajectory CSV for the manipulator."),
    out: Optional[Path] = typer.Option(None, "--out", help="HDF5 run log."),
    summary: Optional[Path] = SummaryOption,
    plot: Optional[Path] = typer.Option(None, "--plot", help="PNG: planned vs unplanned paths and O(t)."),
    base_transform: Optional[str] = typer.Option(
        None, "--base-transform", help="Tissue -> robot base frame: ROTATION_DEG,TX_MM,TY_MM."),
    angular_speed: Optional[float] = typer.Option(
        None, "--angular-speed", help="Needle rotation speed in rad/s; adds a time_s column."),
    strict: bool = typer.Option(False, "--strict", help="Fail when the planner's eq. 4.2 fails."),
    compare: bool = typer.Option(
        True, "--compare/--no-compare",
        help="Also run the unplanned insertion (fixed centre) and report its exit error."),
    spacing: Optional[float] = SpacingOption,
    dilation: Optional[float] = DilationOption,
    linear_solver: Optional[LinearSolver] = LinearSolverOption,
    tip_tracking: Optional[TipTracking] = TipTrackingOption,
    verbose: int = VerboseOption,
    quiet: bool = QuietOption,
) -> None:
    """Plan and export the needle-centre trajectory that brings the tip out at the desired exit.

    Thesis Algorithm 2. By default also runs the unplanned insertion for comparison.
    """
    from dataclasses import replace

    from .errors import InputError

    _setup_logging(verbose, quiet)
    _check_outputs(export, out, summary, plot)
    linear_solver, tip_tracking = _value(linear_solver), _value(tip_tracking)
    if angular_speed is not None and not 0 < angular_speed < math.inf:  # also refuses nan
        raise InputError(f"--angular-speed: got {angular_speed!r}, expected a positive speed in rad/s")
    transform = _parse_base_transform(base_transform)
    scenario = _load(scenario_path, spacing, dilation)
    robot = scenario.robot
    if transform is not None:
        robot = replace(robot, rotation_deg=transform[0], translation=transform[1], given=True)
    if angular_speed is not None:
        robot = replace(robot, angular_speed=angular_speed)
    scenario = replace(scenario, robot=robot,
                       planner=replace(scenario.planner, strict=scenario.planner.strict or strict))
    from .io import reports
    from .planning.planner import run_plan
    from .io.progress import progress_bar

    from .study.auto import resolve_accuracy

    scenario, auto_note = resolve_accuracy(scenario, tip_tracking, linear_solver)
    expected = _expected_steps(scenario)
    with progress_bar("planned steps", (2 if compare else 1) * expected) as advance:
        result = run_plan(scenario, compare=compare, linear_solver=linear_solver,
                          tip_tracking=tip_tracking, on_step=lambda record: advance())
    if auto_note is not None:
        result.planned.events.insert(0, auto_note)
    reports.write_plan_outputs(result, export=export, out=out, summary=summary, plot=plot)
    typer.echo(reports.plan_line(result, export))
    _echo_events(result.planned.events, quiet)


@app.command()
def study(
    scenario_path: Path = ScenarioArgument,
    out: Path = typer.Option(..., "--out", help="Folder for study.csv and speed_accuracy.png."),
    quick: bool = typer.Option(False, "--quick", help="A tiny sweep: two families, two spacings."),
    verbose: int = VerboseOption,
    quiet: bool = QuietOption,
) -> None:
    """Speed against accuracy of the needle insertion over discretizations and methods.

    Runs the sweep of the scenario's `study:` block (or a default around its discretization)
    and compares each run's exit point and wall time with the finest run's.
    """
    from .errors import InputError

    _setup_logging(verbose, quiet)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out: {out} is a file, expected a folder")
    _check_outputs(out / "study.csv")
    scenario = _load(scenario_path, None, None)
    from .io.progress import progress_bar
    from .io.study_reports import summary_lines, write_study_outputs
    from .study.sweep import run_study, study_size

    with progress_bar("study runs", study_size(scenario, quick)) as advance:
        result = run_study(scenario, quick=quick, on_run=lambda run: advance(description=run.label))
    csv_path, png_path = write_study_outputs(result, out)
    for line in summary_lines(result):
        typer.echo(line)
    typer.echo(f"study: wrote {csv_path} and {png_path}")


@app.command()
def schema(verbose: int = VerboseOption, quiet: bool = QuietOption) -> None:
    """Print the JSON Schema of scenario files, for editors and validators.

    For example: stitchplan schema > scenario.schema.json
    """
    import json

    _setup_logging(verbose, quiet)
    from .config import scenario_schema

    typer.echo(json.dumps(scenario_schema(), indent=2))


if __name__ == "__main__":  # pragma: no cover
    main()
