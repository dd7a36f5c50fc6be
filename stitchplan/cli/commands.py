"""The commands that run the model: deform, simulate, plan, study and schema. Each parses
its options, loads the scenario, calls one function and hands the result to a writer;
heavy imports stay inside the commands so `--help` is instant. What the resource guard counts
for each is in cli.guards, the runs of simulate and plan in cli.runs (imported inside them),
plan --uncertainty in cli.plan_under_uncertainty."""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Optional

import typer

from ..allocator import resume_collection
from .group import app
from .guards import guard_plan, guard_simulate, guard_study
from .options import (DilationOption, LinearSolver, LinearSolverOption, QuietOption, ScenarioArgument,
                      SpacingOption, SummaryOption, TipTracking, TipTrackingOption, VerboseOption,
                      MaxParticlesOption, NoResourceCheckOption, SchedulerOption, SchemaVerboseOption, WorkersOption,
                      check_angular_speed, check_command_outputs, check_plot_scale_option, check_plot_steps,
                      check_replay_helper, checked_needle_geometry, choice_value, command_executor, echo_events, echo_notes, given_value,
                      guard_limits, guard_runs, load_with_options, named_file, naming_files, option_names,
                      parse_base_transform, parse_steps, plot_steps_note, run_provenance, setup_logging)
from .plan_under_uncertainty import check_uncertainty_options, run_plan_under_uncertainty


@app.command(short_help="Static solve of the slab under the scenario's loads.")
def deform(
    scenario_path: Path = ScenarioArgument,
    probes_out: Optional[Path] = typer.Option(None, "--probes-out", help="CSV x,y,ux,uy per probe."),
    reactions_out: Optional[Path] = typer.Option(None, "--reactions-out",
                                                 help="CSV segment,fx,fy per loaded segment."),
    summary: Optional[Path] = SummaryOption,
    out: Optional[Path] = typer.Option(None, "--out", help="HDF5 run log."),
    plot: Optional[Path] = typer.Option(None, "--plot", help="PNG of the deformed tissue."),
    plot_scale: float = typer.Option(
        1.0, "--plot-scale", help="Draw displacements K times enlarged in --plot (colours, numbers true)."),
    spacing: Optional[float] = SpacingOption,
    dilation: Optional[float] = DilationOption,
    max_particles: Optional[int] = MaxParticlesOption,
    no_resource_check: bool = NoResourceCheckOption,
    verbose: int = VerboseOption,
    quiet: bool = QuietOption,
) -> None:
    """Static large-deformation solve of the slab under the scenario's `loads`."""
    setup_logging(verbose, quiet)
    check_plot_scale_option(plot_scale, plot)
    check_command_outputs({"--probes-out": probes_out, "--reactions-out": reactions_out, "--summary": summary,
                           "--out": out, "--plot": plot}, {"SCENARIO": scenario_path}, out_format="HDF5")
    scenario = load_with_options(scenario_path, spacing, dilation)
    from ..config.scenario import require_loads

    require_loads(scenario, scenario_path)
    guard_runs(scenario_path, guard_limits(max_particles, no_resource_check), ("deform", scenario, "deform", 1),
               names=option_names(spacing, dilation))
    provenance = run_provenance(scenario_path, scenario)
    from ..io import reports
    from ..io.progress import progress_bar
    from ..needle.geometry import needle_zone
    from ..tissue.deform import run_deform

    resume_collection()
    # a needle scene's default particles are graded toward the needle: deform keeps them
    with naming_files(scenario_path), progress_bar("load steps", scenario.load_steps) as advance:
        result = run_deform(scenario, on_step=lambda step, record: advance(), needle_zone=needle_zone(scenario))
    reports.write_deform_outputs(result, probes_out=probes_out, reactions_out=reactions_out,
                                 summary=summary, out=out, plot=plot, provenance=provenance,
                                 plot_scale=plot_scale)
    typer.echo(reports.deform_line(result))
    if probes_out is not None and not scenario.probes:
        echo_notes([(f"--probes-out: {scenario_path} has no `probes` (reference points, mm); {probes_out} holds "
                     "the header alone")], quiet)


@app.command(short_help="Needle insertion with the needle centre held fixed.")
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
    condition_numbers: bool = typer.Option(
        False, "--condition-numbers",
        help="Record each needle step's condition numbers (dense eigenvalues: ~0.6 s a step at 642 particles, "
        "growing with the particles cubed, with 9 dense matrices of (2 x particles)^2 numbers; the resource "
        "guard refuses more than 10 min of them)."),
    center_path: Optional[Path] = typer.Option(
        None, "--center-path", callback=named_file,
        help="Replay needle centres from a trajectory CSV (row n = step n)."),
    estimate: bool = typer.Option(
        True, "--estimate/--no-estimate",
        help="Estimate the exit point's discretization error from a second run at twice the spacing."),
    max_particles: Optional[int] = MaxParticlesOption,
    no_resource_check: bool = NoResourceCheckOption,
    verbose: int = VerboseOption,
    quiet: bool = QuietOption,
) -> None:
    """Needle insertion without planning: the needle centre stays fixed.

    Thesis Algorithm 1. With --center-path the centre follows a trajectory instead (replay).
    """
    setup_logging(verbose, quiet)
    check_replay_helper()
    check_command_outputs({"--out": out, "--summary": summary, "--plot": plot},
                          {"SCENARIO": scenario_path, "--center-path": center_path}, out_format="HDF5")
    steps_to_plot = _steps_to_plot(plot_steps, plot)
    scenario = load_with_options(scenario_path, spacing, dilation)
    accuracy = scenario.discretization.accuracy  # asked for; resolve_accuracy clears it
    provenance = run_provenance(scenario_path, scenario)
    from ..io import reports
    from .runs import put_accuracy_notes_first, read_center_path_option, resolve_accuracy_guarded, simulate_with_replays

    resume_collection()
    options = {"linear_solver": choice_value(linear_solver), "tip_tracking": choice_value(tip_tracking)}
    geometry = checked_needle_geometry(scenario_path, scenario, "simulate")
    path_file = read_center_path_option(scenario_path, center_path, scenario, geometry) if center_path is not None else None
    path, path_text = (path_file.centers, {"center_path": {"text": path_file.text}}) if path_file else (None, None)
    if path_file is not None:  # the replay's path recorded as its scenario is: of the bytes read, a pipe's too
        provenance.update(center_path=str(center_path), center_path_sha256=path_file.sha256)
    check_plot_steps(steps_to_plot, scenario)
    limits = guard_limits(max_particles, no_resource_check)
    if accuracy is None:
        guard_simulate(scenario_path, limits, option_names(spacing, dilation), scenario, estimate,
                       options["linear_solver"], condition_numbers)
    scenario, auto_note = resolve_accuracy_guarded(scenario_path, scenario, limits, **options)
    result, error_estimate = simulate_with_replays(scenario_path, scenario, center_path, path, estimate,
                                                   condition_numbers, **options)
    put_accuracy_notes_first(result.events, auto_note, accuracy, error_estimate)
    reports.write_insertion_outputs(result, "simulate", out=out, summary=summary, plot=plot,
                                    plot_steps=steps_to_plot, provenance=provenance,
                                    extra_summary=reports.exit_estimate_summary(error_estimate),
                                    # the path's text beside the scenario's: the run log alone replays it again
                                    extra_datasets=path_text)
    typer.echo(reports.insertion_line(result, "simulate", error_estimate))
    plot_steps_note(steps_to_plot, result, quiet)
    echo_events(result.events, quiet)


def _steps_to_plot(plot_steps: Optional[str], plot: Optional[Path]) -> Optional[list[int]]:
    """--plot-steps as step numbers, refused without the --plot it draws in."""
    from ..errors import InputError

    if plot_steps is not None and plot is None:
        raise InputError(f"--plot-steps: got {plot_steps}, expected it only with --plot PNG")
    return parse_steps(plot_steps)


@app.command(short_help="Plan and export the needle-centre trajectory.")
def plan(
    scenario_path: Path = ScenarioArgument,
    export: Path = typer.Option(..., "--export", help="Trajectory CSV for the manipulator."),
    out: Optional[Path] = typer.Option(None, "--out", help="HDF5 run log."),
    summary: Optional[Path] = SummaryOption,
    plot: Optional[Path] = typer.Option(None, "--plot", help="PNG: planned vs unplanned paths and O(t)."),
    base_transform: Optional[str] = typer.Option(
        None, "--base-transform", help="Tissue -> robot base frame: ROTATION_DEG,TX_MM,TY_MM (p_base = R p + t, R counter-clockwise by ROTATION_DEG degrees; adds base_* columns)."),
    angular_speed: Optional[float] = typer.Option(
        None, "--angular-speed", help="Needle rotation speed in rad/s; adds a time_s column."),
    strict: bool = typer.Option(False, "--strict", help="Fail when a step's centre does not settle "
                                "within planner.max_iterations moves."),
    compare: bool = typer.Option(
        True, "--compare/--no-compare",
        help="Also run the unplanned insertion (fixed centre) and report its exit error."),
    verify: bool = typer.Option(
        True, "--verify/--no-verify",
        help="Replay the trajectory on a model of half the spacing, re-aiming if it misses there."),
    uncertainty_path: Optional[Path] = typer.Option(
        None, "--uncertainty", callback=named_file,
        help="Uncertainty YAML (see README: Planning under uncertainty): export the robust plan, "
        "with exit-error bands over sampled parameters and sensitivities in the summary."),
    uncertainty_plot: Optional[Path] = typer.Option(
        None, "--uncertainty-plot",
        help="PNG (with --uncertainty): exit clouds of the unplanned, nominal and robust paths on the "
        "held-out samples, and the sensitivities."),
    workers: Optional[int] = WorkersOption,
    scheduler: Optional[str] = SchedulerOption,
    spacing: Optional[float] = SpacingOption,
    dilation: Optional[float] = DilationOption,
    linear_solver: Optional[LinearSolver] = LinearSolverOption,
    tip_tracking: Optional[TipTracking] = TipTrackingOption,
    max_particles: Optional[int] = MaxParticlesOption,
    no_resource_check: bool = NoResourceCheckOption,
    verbose: int = VerboseOption,
    quiet: bool = QuietOption,
) -> None:
    """Plan and export the needle-centre trajectory that brings the tip out at the desired exit.

    Thesis Algorithm 2. By default also runs the unplanned insertion for comparison, and
    replays the trajectory on a model of half the particle spacing (verified exit error).
    """
    setup_logging(verbose, quiet)
    check_uncertainty_options(uncertainty_path, compare,
                               {"--uncertainty-plot": uncertainty_plot, "--workers": workers, "--scheduler": scheduler})
    executor = command_executor(workers, scheduler)
    check_command_outputs({"--export": export, "--out": out, "--summary": summary, "--plot": plot,
                           "--uncertainty-plot": uncertainty_plot},
                          {"SCENARIO": scenario_path, "--uncertainty": uncertainty_path},
                          out_format="HDF5" if uncertainty_path is None else None)  # else with from_calibration
    options = {"linear_solver": choice_value(linear_solver), "tip_tracking": choice_value(tip_tracking)}
    check_angular_speed(angular_speed)
    check_replay_helper()
    transform = parse_base_transform(base_transform)
    scenario = load_with_options(scenario_path, spacing, dilation)
    accuracy = scenario.discretization.accuracy  # asked for; resolve_accuracy clears it
    provenance = run_provenance(scenario_path, scenario)
    from ..planning.plan_options import with_plan_options

    scenario = with_plan_options(scenario, transform, angular_speed, strict)
    limits, names = guard_limits(max_particles, no_resource_check), option_names(spacing, dilation)
    guard = partial(guard_plan, scenario_path, limits, names, verify=verify, compare=compare,
                    linear_solver=options["linear_solver"])
    # before the numerics' imports, which the replay helper spends building its model (none under uncertainty)
    _guard_and_hand_replay_model(scenario_path, scenario, guard, verify, options, hand=uncertainty_path is None)
    from ..io import reports
    from .runs import plan_with_replays, put_accuracy_notes_first, resolve_accuracy_guarded

    resume_collection()
    scenario, auto_note = resolve_accuracy_guarded(scenario_path, scenario, limits, **options)
    if auto_note is not None:
        guard(scenario)  # the verification model of the chosen discretization
    if uncertainty_path is not None:
        run_plan_under_uncertainty(scenario_path, scenario, uncertainty_path, executor, auto_note, limits,
                                   verify=verify, names=names, export=export, out=out, summary=summary, plot=plot,
                                   uncertainty_plot=uncertainty_plot, provenance=provenance, quiet=quiet,
                                   accuracy=accuracy, **options)
        return
    result = plan_with_replays(scenario_path, scenario, compare, verify, out, plot, **options)
    put_accuracy_notes_first(result.planned.events, auto_note, accuracy, result.estimate)
    reports.write_plan_outputs(result, export=export, out=out, summary=summary, plot=plot,
                               provenance=provenance)
    typer.echo(reports.plan_line(result, export))
    echo_events(result.planned.events, quiet)


def _guard_and_hand_replay_model(scenario_path: Path, scenario, guard, verify: bool, options: dict,
                                 hand: bool = True) -> None:
    """A needle that cannot enter or exit refused with the file named; then, when the scenario
    settles its model (no `accuracy` to resolve), the resource `guard`, and with `hand` the
    replay helper (stitchplan/early_helper.py) handed the model the plan's replays run on."""
    checked_needle_geometry(scenario_path, scenario, "plan")
    if scenario.discretization.accuracy is None:
        guard(scenario)
        if hand:
            from .. import early_helper
            from ..planning.replay_models import replay_options, replay_scenario

            early_helper.hand(replay_scenario(scenario, verify), replay_options(options))


@app.command(short_help="Speed against accuracy over discretizations and methods.")
def study(
    scenario_path: Path = ScenarioArgument,
    out: Path = typer.Option(..., "--out", help="Folder for study.csv, study.json and speed_accuracy.png."),
    quick: bool = typer.Option(False, "--quick", help="A tiny sweep: two families, two spacings."),
    workers: Optional[int] = WorkersOption,
    scheduler: Optional[str] = SchedulerOption,
    max_particles: Optional[int] = MaxParticlesOption,
    no_resource_check: bool = NoResourceCheckOption,
    verbose: int = VerboseOption,
    quiet: bool = QuietOption,
) -> None:
    """Speed against accuracy of the needle insertion over discretizations and methods.

    Runs the sweep of the scenario's `study:` block (or a default around its discretization)
    and compares each run's exit point and wall time with the finest run's. The runs are
    tasks on a Dask cluster (--workers, --scheduler); wall times compare best with one worker.
    """
    setup_logging(verbose, quiet)
    _check_study_folder(out)
    from ..io.study_reports import study_outputs, summary_lines, write_study_outputs

    executor = command_executor(workers, scheduler)
    check_command_outputs(study_outputs(out), {"SCENARIO": scenario_path})
    scenario = load_with_options(scenario_path, None, None)
    checked_needle_geometry(scenario_path, scenario, "study")  # the sweep needs a needle that enters and exits
    from ..io.progress import progress_bar
    from ..study.sweep import EveryRunFailed, plan_runs, run_study, study_size

    resume_collection()
    with naming_files(scenario_path):
        runs, reference, repeats = plan_runs(scenario, quick)
    guard_study(scenario_path, guard_limits(max_particles, no_resource_check), runs, reference, repeats,
                executor.workers)
    with executor, progress_bar("study runs", study_size(scenario, quick)) as advance, naming_files(scenario_path):
        # the runs go on at once on a cluster: the bar names the one that ended last
        try:
            result = run_study(scenario, quick=quick, executor=executor,
                               on_run=lambda run: advance(description=f"study runs, last done: {run.label}"))
        except EveryRunFailed as failure:  # no study.csv holds the reasons: the line names the scenario
            raise EveryRunFailed(f"{scenario_path}: {failure}") from None
    csv_path, png_path, json_path = write_study_outputs(result, out, run_provenance(scenario_path, scenario))
    for line in summary_lines(result):
        typer.echo(line)
    typer.echo(f"study: wrote {csv_path}, {png_path} and {json_path}")
    echo_notes(result.notes, quiet)


def _check_study_folder(out: Path) -> None:
    """--out names a folder (made if missing), not a file."""
    from ..errors import InputError

    if given_value("--out") == "":  # Path("") is ".", the working folder
        raise InputError("--out: got an empty path, expected a folder name")
    if out.exists() and not out.is_dir():
        raise InputError(f"--out: got {out}, a file; expected a folder")


@app.command(short_help="Print the JSON Schema of scenario files.")
def schema(verbose: int = SchemaVerboseOption, quiet: bool = QuietOption) -> None:
    """Print the JSON Schema of scenario files, for editors and validators.

    For example: stitchplan schema > scenario.schema.json
    """
    import json

    setup_logging(verbose, quiet)
    from ..config import scenario_schema

    resume_collection()
    typer.echo(json.dumps(scenario_schema(), indent=2))
