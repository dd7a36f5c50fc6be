"""The commands that run the model: deform, simulate, plan, study and schema. Each parses
its options, loads the scenario, calls one function and hands the result to a writer;
heavy imports stay inside the commands so `--help` is instant."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import typer

from .app import app
from .options import (DilationOption, LinearSolver, LinearSolverOption, QuietOption, ScenarioArgument,
                      SpacingOption, SummaryOption, TipTracking, TipTrackingOption, VerboseOption,
                      _check_outputs, _echo_events, _expected_steps, _load, _parse_base_transform,
                      _parse_steps, _setup_logging, _value)


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
    from ..io import reports
    from ..io.progress import progress_bar
    from ..tissue.deform import run_deform

    with progress_bar("load steps", scenario.load_steps) as advance:
        result = run_deform(scenario, on_step=lambda step, record: advance())
    reports.write_deform_outputs(result, probes_out=probes_out, reactions_out=reactions_out,
                                 summary=summary, out=out, plot=plot)
    typer.echo(reports.deform_line(result))


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
    from ..io import reports
    from ..io.progress import progress_bar
    from ..io.readers import read_center_path
    from ..needle.insertion import run_insertion
    from ..study.auto import resolve_accuracy

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

    from ..errors import InputError

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
    from ..io import reports
    from ..planning.planner import run_plan
    from ..io.progress import progress_bar

    from ..study.auto import resolve_accuracy

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
    from ..errors import InputError

    _setup_logging(verbose, quiet)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out: {out} is a file, expected a folder")
    _check_outputs(out / "study.csv")
    scenario = _load(scenario_path, None, None)
    from ..io.progress import progress_bar
    from ..io.study_reports import summary_lines, write_study_outputs
    from ..study.sweep import run_study, study_size

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
    from ..config import scenario_schema

    typer.echo(json.dumps(scenario_schema(), indent=2))
