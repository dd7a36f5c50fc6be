"""Command-line interface: parse options, load the scenario, call one function, write results.

Heavy imports live inside the commands so `stitchplan --help` stays instant. Every error a
user can cause ends as one line on stderr and exit code 2, with no output file written.
"""

from __future__ import annotations

import functools
import logging
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Optional

import typer

# the numerics are sparse and small-dense; BLAS threads only compete with each other on a
# busy machine (set the variable yourself to override)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="Simulate curved suture needle insertion into deformable tissue and plan the "
    "needle-centre trajectory that compensates the deformation.",
)
calibrate_app = typer.Typer(no_args_is_help=True, help="Fit model parameters to measurements.")
app.add_typer(calibrate_app, name="calibrate")

EXIT_USER_ERROR = 2

ScenarioArgument = typer.Argument(..., help="Scenario YAML file (see README: Scenario format).")
SpacingOption = typer.Option(None, "--spacing", help="Particle spacing in mm (overrides the scenario).")
DilationOption = typer.Option(None, "--dilation", help="Kernel support / spacing (overrides the scenario).")
SummaryOption = typer.Option(None, "--summary", help="Write a JSON summary here.")


def user_errors(command: Callable) -> Callable:
    """Turn the project's user-facing exceptions into one line on stderr and exit code 2."""

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        from .config import ScenarioError
        from .needle.insertion import InsertionFailure
        from .tissue.solver import SolverDivergence

        try:
            return command(*args, **kwargs)
        except (ScenarioError, SolverDivergence, InsertionFailure) as error:
            typer.echo(f"error: {error}", err=True)
            raise typer.Exit(EXIT_USER_ERROR) from None
        except ValueError as error:  # domain checks raised by the numerics
            typer.echo(f"error: {error}", err=True)
            raise typer.Exit(EXIT_USER_ERROR) from None

    return wrapper


def _setup_logging(verbose: bool) -> None:
    # warnings of the numerics also come back as events, printed once as `note:` lines
    logging.basicConfig(level=logging.INFO if verbose else logging.ERROR,
                        format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)


def _load(scenario_path: Path, spacing: Optional[float], dilation: Optional[float]):
    from .config import load_scenario, parse_discretization, with_discretization

    scenario = load_scenario(scenario_path)
    if spacing is not None:
        parse_discretization({"spacing": spacing}, "--spacing")
    if dilation is not None:
        parse_discretization({"dilation": dilation}, "--dilation")
    return with_discretization(scenario, spacing=spacing, dilation=dilation)


def _check_outputs(*paths: Optional[Path]) -> None:
    """Fail before any work if an output folder cannot exist (a file stands in its place)."""
    from .config import ScenarioError

    for path in paths:
        if path is None:
            continue
        for parent in Path(path).resolve().parents:
            if parent.exists():
                if not parent.is_dir():
                    raise ScenarioError(f"{path}: cannot write, {parent} is not a folder")
                break
        if Path(path).is_dir():
            raise ScenarioError(f"{path}: is a folder, expected a file name")


@app.command()
@user_errors
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
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log solver progress."),
) -> None:
    """Static large-deformation solve of the slab under the scenario's `loads`."""
    _setup_logging(verbose)
    _check_outputs(probes_out, reactions_out, summary, out, plot)
    scenario = _load(scenario_path, spacing, dilation)
    from .io import reports
    from .tissue.deform import run_deform
    from .io.progress import progress_bar

    with progress_bar("load steps", scenario.load_steps) as advance:
        result = run_deform(scenario, on_step=lambda step, record: advance())
    reports.write_deform_outputs(result, probes_out=probes_out, reactions_out=reactions_out,
                                 summary=summary, out=out, plot=plot)
    typer.echo(
        f"deform: {result.model.n_particles} particles, {scenario.load_steps} load steps, "
        f"{result.report.iterations} Newton iterations, {result.wall_seconds:.3f} s"
    )


@calibrate_app.command("material")
@user_errors
def calibrate_material(
    calibration_path: Path = typer.Argument(..., help="Calibration YAML: tissue, experiments "
                                            "(loads + markers CSV x,y,x_def,y_def), fit ranges."),
    out: Path = typer.Option(..., "--out",
                             help="Fitted YAML: `material:` block, fit quality, diagnostics."),
    plot_dir: Optional[Path] = typer.Option(
        None, "--plot-dir", help="Folder for cost_surface.png and marker_residuals.png."),
    spacing: Optional[float] = SpacingOption,
    dilation: Optional[float] = DilationOption,
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log solver progress."),
) -> None:
    """Fit lame_lambda and lame_mu to marker displacements (grid search, then least squares)."""
    _setup_logging(verbose)
    _check_outputs(out, None if plot_dir is None else plot_dir / "cost_surface.png")
    from . import calibration
    from .io.progress import progress_bar

    result = calibration.calibrate_material(calibration_path, spacing, dilation, progress=progress_bar)
    calibration.write_material_outputs(result, out, plot_dir)
    typer.echo(calibration.material_summary_line(result))


@calibrate_app.command("needle")
@user_errors
def calibrate_needle(
    air: Path = typer.Option(..., "--air", help="CSV angle_rad,force_N: needle rotated in air."),
    tissue: Path = typer.Option(..., "--tissue", help="CSV angle_rad,force_N: needle rotated into "
                                "the tissue, angle from the moment the tip touches it."),
    radius: float = typer.Option(..., "--radius", help="Needle radius, mm."),
    out: Path = typer.Option(..., "--out", help="YAML with friction, cutting_force and diagnostics."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="PNG of the recordings and the fit."),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log details."),
) -> None:
    """Fit needle friction (N/mm) and cutting force (N) to force recordings in air and tissue."""
    _setup_logging(verbose)
    _check_outputs(out, plot)
    from . import calibration

    result = calibration.calibrate_needle(air, tissue, radius)
    calibration.write_needle_outputs(result, out, plot)
    typer.echo(calibration.needle_summary_line(result))


def _parse_steps(text: Optional[str]) -> Optional[list[int]]:
    from .config import ScenarioError

    if not text:
        return None
    try:
        return [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise ScenarioError(f"--plot-steps: got {text!r}, expected comma-separated step numbers") from None


LinearSolverOption = typer.Option(None, "--linear-solver",
                                  help="Saddle-point solver: direct or minres (overrides the scenario).")
TipTrackingOption = typer.Option(
    None, "--tip-tracking",
    help="levenberg-marquardt, inverse-gradient, or auto (inverse gradient, falling back to LM).")


def _choice_option(value: Optional[str], name: str, choices: tuple[str, ...]) -> Optional[str]:
    from .config import ScenarioError

    if value is not None and value not in choices:
        raise ScenarioError(f"{name}: got {value!r}, expected one of {', '.join(choices)}")
    return value


@app.command()
@user_errors
def simulate(
    scenario_path: Path = ScenarioArgument,
    out: Optional[Path] = typer.Option(None, "--out", help="HDF5 run log."),
    summary: Optional[Path] = SummaryOption,
    plot: Optional[Path] = typer.Option(None, "--plot", help="PNG: deformed tissue, needle and tip path."),
    plot_steps: Optional[str] = typer.Option(None, "--plot-steps", help="Steps to draw, e.g. 10,20,37."),
    spacing: Optional[float] = SpacingOption,
    dilation: Optional[float] = DilationOption,
    linear_solver: Optional[str] = LinearSolverOption,
    tip_tracking: Optional[str] = TipTrackingOption,
    condition_numbers: bool = typer.Option(False, "--condition-numbers",
                                           help="Record condition numbers per step (dense; small models)."),
    center_path: Optional[Path] = typer.Option(
        None, "--center-path", help="Replay needle centres from a trajectory CSV (row n = step n)."),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log solver progress."),
) -> None:
    """Needle insertion without planning (thesis Algorithm 1): the needle centre stays fixed,
    or follows --center-path."""
    from .config import LINEAR_SOLVERS, TIP_TRACKING

    _setup_logging(verbose)
    _check_outputs(out, summary, plot)
    _choice_option(linear_solver, "--linear-solver", LINEAR_SOLVERS)
    _choice_option(tip_tracking, "--tip-tracking", TIP_TRACKING)
    steps_to_plot = _parse_steps(plot_steps)
    scenario = _load(scenario_path, spacing, dilation)
    from .io import reports
    from .io.progress import progress_bar
    from .needle.insertion import run_insertion
    from .planning.trajectory import read_center_path

    from .study.auto import resolve_accuracy

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
    typer.echo(
        f"simulate: {len(result.steps)} steps, {result.model.n_particles} particles, exit error "
        f"{result.exit_error_mm:.4f} mm (material {result.exit_error_material_mm:.4f} mm), "
        f"{result.wall_seconds:.2f} s"
    )
    _echo_events(result.events)


def _expected_steps(scenario) -> int:
    from .needle.geometry import scenario_needle

    return scenario_needle(scenario).expected_steps


def _echo_events(events, shown: int = 3) -> None:
    for event in events[:shown]:
        typer.echo(f"note: {event.message}", err=True)
    if len(events) > shown:
        typer.echo(f"note: {len(events) - shown} more notes in the summary and run log", err=True)


def _parse_base_transform(text: Optional[str]):
    from .config import ScenarioError

    if text is None:
        return None
    try:
        rotation, tx, ty = (float(part) for part in text.split(","))
        if not all(abs(value) < float("inf") for value in (rotation, tx, ty)):  # nan, inf
            raise ValueError
    except ValueError:
        raise ScenarioError(f"--base-transform: got {text!r}, expected ROTATION_DEG,TX_MM,TY_MM") from None
    return rotation, (tx, ty)


@app.command()
@user_errors
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
    linear_solver: Optional[str] = LinearSolverOption,
    tip_tracking: Optional[str] = TipTrackingOption,
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log solver progress."),
) -> None:
    """Plan the needle-centre trajectory that brings the tip out at the desired exit
    (thesis Algorithm 2) and export it; by default also runs the unplanned insertion for
    comparison."""
    from dataclasses import replace

    from .config import LINEAR_SOLVERS, TIP_TRACKING, ScenarioError

    _setup_logging(verbose)
    _check_outputs(export, out, summary, plot)
    _choice_option(linear_solver, "--linear-solver", LINEAR_SOLVERS)
    _choice_option(tip_tracking, "--tip-tracking", TIP_TRACKING)
    if angular_speed is not None and not 0 < angular_speed < float("inf"):  # also refuses nan
        raise ScenarioError(f"--angular-speed: got {angular_speed!r}, expected a positive speed in rad/s")
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
    from .planning.planner import PlannerSettings, run_plan
    from .io.progress import progress_bar

    settings = PlannerSettings(scenario.planner.tolerance, scenario.planner.max_iterations,
                               scenario.planner.strict, scenario.planner.exit_tolerance,
                               scenario.planner.max_passes)
    from .study.auto import resolve_accuracy

    scenario, auto_note = resolve_accuracy(scenario, tip_tracking, linear_solver)
    expected = _expected_steps(scenario)
    with progress_bar("planned steps", (2 if compare else 1) * expected) as advance:
        result = run_plan(scenario, settings, compare=compare, linear_solver=linear_solver,
                          tip_tracking=tip_tracking, on_step=lambda record: advance())
    if auto_note is not None:
        result.planned.events.insert(0, auto_note)
    reports.write_plan_outputs(result, export=export, out=out, summary=summary, plot=plot)
    planned, unplanned = result.planned, result.unplanned
    versus = f" vs {unplanned.exit_error_mm:.4f} mm unplanned" if unplanned is not None else ""
    typer.echo(
        f"plan: {len(planned.steps)} steps, exit error {planned.exit_error_mm:.4f} mm planned{versus}, "
        f"{planned.wall_seconds:.2f} s planned run; trajectory written to {export}"
    )
    _echo_events(planned.events)


@app.command()
@user_errors
def study(
    scenario_path: Path = ScenarioArgument,
    out: Path = typer.Option(..., "--out", help="Folder for study.csv and speed_accuracy.png."),
    quick: bool = typer.Option(False, "--quick", help="A tiny sweep: two families, two spacings."),
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Log each run."),
) -> None:
    """Speed against accuracy: run the needle insertion over a sweep of discretization and
    method choices (the scenario's `study:` block, or a default around its discretization)
    and compare each run's exit point and wall time with the finest run's."""
    from .config import ScenarioError

    _setup_logging(verbose)
    if out.exists() and not out.is_dir():
        raise ScenarioError(f"--out: {out} is a file, expected a folder")
    _check_outputs(out / "study.csv")
    scenario = _load(scenario_path, None, None)
    from .io.progress import progress_bar
    from .study.sweep import run_study, study_size, summary_lines, write_study_outputs

    with progress_bar("study runs", study_size(scenario, quick)) as advance:
        result = run_study(scenario, quick=quick, on_run=lambda run: advance(description=run.label))
    csv_path, png_path = write_study_outputs(result, out)
    for line in summary_lines(result):
        typer.echo(line)
    typer.echo(f"study: wrote {csv_path} and {png_path}")


def main() -> None:  # pragma: no cover - console entry point
    app()


if __name__ == "__main__":  # pragma: no cover
    app()
