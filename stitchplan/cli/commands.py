"""The commands that run the model: deform, simulate, plan, study and schema. Each parses
its options, loads the scenario, calls one function and hands the result to a writer;
heavy imports stay inside the commands so `--help` is instant."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..allocator import pause_collection, resume_collection
from .group import app
from .options import (DilationOption, LinearSolver, LinearSolverOption, QuietOption, ScenarioArgument,
                      SpacingOption, SummaryOption, TipTracking, TipTrackingOption, VerboseOption,
                      MaxParticlesOption, NoResourceCheckOption, SchedulerOption, WorkersOption,
                      _check_angular_speed, _check_outputs, _check_plot_scale, _check_plot_steps, _echo_events,
                      _echo_notes, _estimate_run, _executor, _expected_steps, _guard, _limits, _load,
                      _naming_files, _needle_geometry, _option_names, _parse_base_transform, _parse_steps,
                      _plot_steps_note, _provenance, _setup_logging, _value)


@app.command()
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
    _setup_logging(verbose, quiet)
    _check_plot_scale(plot_scale, plot)
    _check_outputs({"--probes-out": probes_out, "--reactions-out": reactions_out, "--summary": summary,
                    "--out": out, "--plot": plot}, {"SCENARIO": scenario_path})
    scenario = _load(scenario_path, spacing, dilation)
    from ..config.scenario import require_loads

    require_loads(scenario, scenario_path)
    _guard(scenario_path, _limits(max_particles, no_resource_check), ("deform", scenario, "deform", 1),
           names=_option_names(spacing, dilation))
    provenance = _provenance(scenario_path, scenario)
    from ..io import reports
    from ..io.progress import progress_bar
    from ..needle.geometry import needle_zone
    from ..tissue.deform import run_deform

    resume_collection()
    # a needle scene's default particles are graded toward the needle: deform keeps them
    with _naming_files(scenario_path), progress_bar("load steps", scenario.load_steps) as advance:
        result = run_deform(scenario, on_step=lambda step, record: advance(), needle_zone=needle_zone(scenario))
    reports.write_deform_outputs(result, probes_out=probes_out, reactions_out=reactions_out,
                                 summary=summary, out=out, plot=plot, provenance=provenance,
                                 plot_scale=plot_scale)
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
    from ..errors import InputError

    _setup_logging(verbose, quiet)
    _check_outputs({"--out": out, "--summary": summary, "--plot": plot},
                   {"SCENARIO": scenario_path, "--center-path": center_path})
    if plot_steps is not None and plot is None:
        raise InputError(f"--plot-steps: got {plot_steps}, expected it only with --plot PNG")
    steps_to_plot = _parse_steps(plot_steps)
    scenario = _load(scenario_path, spacing, dilation)
    accuracy = scenario.discretization.accuracy  # asked for; resolve_accuracy clears it
    provenance = _provenance(scenario_path, scenario)
    from ..io import reports
    from ..io.progress import progress_bar
    from ..io.readers import read_center_path
    from ..needle.geometry import entry_lean, scenario_needle
    from ..planning.verification import estimate_replays, simulate_with_estimate
    from ..study.auto import resolve_accuracy

    resume_collection()
    linear_solver, tip_tracking = _value(linear_solver), _value(tip_tracking)
    geometry = _needle_geometry(scenario_path, scenario)

    def needle_for(first_center):
        """The needle a path starting about `first_center` replays: a path planned with the
        needle leaning at entry leans it (run_insertion does the same)."""
        with _naming_files(scenario_path, center_path):
            return scenario_needle(entry_lean(scenario, first_center))

    path = read_center_path(center_path, geometry, needle_for) if center_path is not None else None
    _check_plot_steps(steps_to_plot, scenario)
    limits = _limits(max_particles, no_resource_check)
    if scenario.discretization.accuracy is None:
        names = _option_names(spacing, dilation)
        _guard(scenario_path, limits, ("insertion", scenario, "simulate", 1), names=names, linear_solver=linear_solver,
               alongside=[_estimate_run(scenario, "exit error estimate", "pass --no-estimate to skip the estimate",
                                        names)] if estimate else [])
    with _naming_files(scenario_path):  # an accuracy the discretizations cannot reach names the file
        scenario, auto_note = resolve_accuracy(scenario, tip_tracking, linear_solver,
                                               max_particles=None if limits is None else limits.max_particles)
    # the estimate's run at 2h goes on in a helper process alongside (planning/replays.py)
    with (_naming_files(scenario_path, center_path),
          estimate_replays(scenario, estimate=estimate, linear_solver=linear_solver, tip_tracking=tip_tracking)
          as replays, progress_bar("needle steps", _expected_steps(scenario)) as advance):
        result, error_estimate = simulate_with_estimate(
            scenario, center_path=path, estimate=estimate, linear_solver=linear_solver,
            tip_tracking=tip_tracking, condition_numbers=condition_numbers, on_step=lambda record: advance(),
            replays=replays)
    if auto_note is not None:
        result.events[:0] = [auto_note, *_accuracy_events(accuracy, error_estimate)]
    reports.write_insertion_outputs(result, "simulate", out=out, summary=summary, plot=plot,
                                    plot_steps=steps_to_plot, provenance=provenance,
                                    extra_summary=reports.exit_estimate_summary(error_estimate))
    typer.echo(reports.insertion_line(result, "simulate", error_estimate))
    _plot_steps_note(steps_to_plot, result, quiet)
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
    strict: bool = typer.Option(False, "--strict", help="Fail when a step's centre does not settle "
                                "within planner.max_iterations moves."),
    compare: bool = typer.Option(
        True, "--compare/--no-compare",
        help="Also run the unplanned insertion (fixed centre) and report its exit error."),
    verify: bool = typer.Option(
        True, "--verify/--no-verify",
        help="Replay the trajectory on a model of half the spacing, re-aiming if it misses there."),
    uncertainty_path: Optional[Path] = typer.Option(
        None, "--uncertainty",
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
    from dataclasses import replace

    from ..errors import InputError

    _setup_logging(verbose, quiet)
    if uncertainty_path is None:
        for option, value in (("--uncertainty-plot", uncertainty_plot), ("--workers", workers),
                              ("--scheduler", scheduler)):
            if value is not None:
                raise InputError(f"{option}: got {value}, expected it only with --uncertainty FILE")
    elif not compare:
        raise InputError("--no-compare: got it with --uncertainty FILE, whose report compares the unplanned, nominal "
                         "and robust exits over the samples; expected it without --uncertainty")
    executor = _executor(workers, scheduler)
    _check_outputs({"--export": export, "--out": out, "--summary": summary, "--plot": plot,
                    "--uncertainty-plot": uncertainty_plot},
                   {"SCENARIO": scenario_path, "--uncertainty": uncertainty_path})
    linear_solver, tip_tracking = _value(linear_solver), _value(tip_tracking)
    _check_angular_speed(angular_speed)
    transform = _parse_base_transform(base_transform)
    scenario = _load(scenario_path, spacing, dilation)
    accuracy = scenario.discretization.accuracy  # asked for; resolve_accuracy clears it
    provenance = _provenance(scenario_path, scenario)
    robot = scenario.robot
    if transform is not None:
        robot = replace(robot, rotation_deg=transform[0], translation=transform[1], given=True)
    if angular_speed is not None:
        robot = replace(robot, angular_speed=angular_speed)
    scenario = replace(scenario, robot=robot,
                       planner=replace(scenario.planner, strict=scenario.planner.strict or strict))
    from .. import early_helper
    from ..planning.replay_models import predicts_aim, replay_options, replay_scenario
    from ..resources import PLAN_RUNS, VERIFICATION_RUNS, verification_origin

    limits = _limits(max_particles, no_resource_check)
    names = _option_names(spacing, dilation)

    def guard(scenario) -> None:
        # a replay at twice the spacing goes on as well: the predicted aim's (in this process),
        # or without the verification the exit error estimate's (in a helper)
        at_2h = [] if verify and not predicts_aim(scenario, verify) else [_estimate_run(
            scenario, "plan's replay at twice the spacing",
            "set planner.predicted_aim: false to skip the predicted aim" if verify else "", names)]
        _guard(scenario_path, limits, ("insertion", scenario, "plan", PLAN_RUNS + compare),
               *([("insertion", replay_scenario(scenario, verify=True), "plan verification", VERIFICATION_RUNS,
                   verification_origin(scenario, names))] if verify else []), names=names,
               linear_solver=linear_solver, alongside=at_2h)

    _needle_geometry(scenario_path, scenario)  # a needle that cannot enter or exit, with the file named
    options = {"linear_solver": linear_solver, "tip_tracking": tip_tracking}
    if scenario.discretization.accuracy is None:
        guard(scenario)
        if uncertainty_path is None:  # its model settled and guarded: the helper builds it while this imports
            early_helper.hand(replay_scenario(scenario, verify), replay_options(options))
    from ..io import reports
    from ..io.progress import progress_bar
    from ..planning.verification import plan_replays, plan_verified, prediction_replays
    from ..study.auto import resolve_accuracy

    resume_collection()
    with _naming_files(scenario_path):  # an accuracy the discretizations cannot reach names the file
        scenario, auto_note = resolve_accuracy(scenario, tip_tracking, linear_solver,
                                               max_particles=None if limits is None else limits.max_particles)
    if auto_note is not None:
        guard(scenario)  # the verification model of the chosen discretization
    if uncertainty_path is not None:
        _plan_under_uncertainty(scenario_path, scenario, uncertainty_path, executor, auto_note, limits,
                                verify=verify, names=names, export=export, out=out, summary=summary, plot=plot,
                                uncertainty_plot=uncertainty_plot, provenance=provenance, quiet=quiet, **options)
        return
    expected = _expected_steps(scenario)
    # the trajectory's replays go on in a helper process alongside (planning/replays.py); the
    # predicted aim's at 2h here, after the first pass (planning/verification.py)
    with (_naming_files(scenario_path),
          plan_replays(scenario, verify, while_waiting=lambda: reports.prepare_plan_outputs(out, plot),
                       **options) as replays,
          prediction_replays(scenario, verify, **options) as predictions,
          progress_bar("planned steps", (2 if compare else 1) * expected) as advance):
        result = plan_verified(scenario, compare=compare, verify=verify, on_step=lambda record: advance(),
                               replays=replays, predictions=predictions, **options)
    if auto_note is not None:
        result.planned.events[:0] = [auto_note, *_accuracy_events(accuracy, result.estimate)]
    reports.write_plan_outputs(result, export=export, out=out, summary=summary, plot=plot,
                               provenance=provenance)
    typer.echo(reports.plan_line(result, export))
    _echo_events(result.planned.events, quiet)


def _plan_under_uncertainty(scenario_path: Path, scenario, uncertainty_path: Path, executor, auto_note, limits,
                            verify: bool, names: dict, export: Path, out, summary, plot, uncertainty_plot,
                            provenance: dict, quiet: bool, **options) -> None:
    """plan --uncertainty: the robust plan over the file's parameter distributions, its
    sampled runs on the executor (stitchplan.uncertainty.robust); with `verify` the plans aimed
    for the refined model and the exported one replayed on it at the scenario's values."""
    pause_collection()  # again, for the imports of the uncertainty's modules (stitchplan/allocator.py)
    from ..config.uncertainty import check_against_scenario, load_uncertainty
    from ..io import reports
    from ..io.progress import progress_bar
    from ..io.uncertainty_reports import uncertainty_lines
    from ..planning.replay_models import replay_scenario
    from ..planning.verification import estimate_exit_error, verify_exported
    from ..resources import PLAN_RUNS, VERIFICATION_RUNS, Origin, verification_origin
    from ..uncertainty.robust import check_target, plan_under_uncertainty, planned_tasks
    from ..uncertainty.sampling import draw

    resume_collection()
    uncertainty = load_uncertainty(uncertainty_path)
    _check_outputs({"--export": export, "--out": out, "--summary": summary, "--plot": plot,
                    "--uncertainty-plot": uncertainty_plot},
                   {"--uncertainty": uncertainty_path, "from_calibration": uncertainty.calibration})
    check_against_scenario(uncertainty, scenario, scenario_path)
    check_target(scenario, str(scenario_path))
    draw(uncertainty, scenario)  # a distribution mostly below zero is refused before the runs
    tasks = planned_tasks(uncertainty)
    # a local cluster's workers each hold a sampled plan's runs while this process holds its own
    workers = executor.workers or 0
    on_workers = Origin(dict(names), skip="pass --workers with fewer workers" if workers > 1 else "")
    _guard(scenario_path, limits, ("insertion", scenario, "plan --uncertainty", 2 * PLAN_RUNS + 1 + tasks),
           *([("insertion", replay_scenario(scenario, verify=True), "plan verification", VERIFICATION_RUNS + 1,
               verification_origin(scenario, names))] if verify else []), names=names,
           linear_solver=options.get("linear_solver"),
           alongside=[("insertion", scenario, f"worker {k + 1} of {workers}: sampled plans", PLAN_RUNS, on_workers)
                      for k in range(workers)], forked=False)
    with executor, progress_bar("plans and sampled runs", tasks + 2) as advance:
        result = plan_under_uncertainty(scenario, uncertainty, executor, verify=verify,
                                        on_run=lambda description: advance(description=description), **options)
    plan = result.exported_plan
    if verify:
        if plan.verification is None:  # the re-aimed robust plan; the nominal one was verified as `plan` verifies
            verify_exported(scenario, plan, **options)
        offset = result.refined_offset
        if offset is None:
            note = ("verification: the nominal plan's trajectory could not be replayed on the refined model: no "
                    "refined offset is added to the plans' statistics, and a re-aimed robust plan aims by the mean "
                    "shift alone")
        else:
            note = (f"verification: the plans aim for the refined model (its exit offset for the nominal plan's path, "
                    f"({offset[0]:.3g}, {offset[1]:.3g}) mm), the exported plan replayed on it at the scenario's "
                    "values; the sampled runs replay on the planning model, the plans' exit errors are reported "
                    "with that offset added")
    else:
        note = "the plans under uncertainty are not verified on a refined model (--no-verify)"
        # as plan --no-verify: the exported plan's estimate from its path replayed at twice the spacing
        plan.estimate = estimate_exit_error(scenario, plan.planned, plan.exported_centers, **options)
    plan.planned.events.insert(0, _note_event(note))
    if auto_note is not None:
        plan.planned.events.insert(0, auto_note)
    reports.write_plan_outputs(plan, export=export, out=out, summary=summary, plot=plot, provenance=provenance,
                               uncertainty=result, uncertainty_plot=uncertainty_plot)
    typer.echo(reports.plan_line(plan, export))
    for line in uncertainty_lines(result):
        typer.echo(line)
    _echo_notes(result.notes, quiet)
    _echo_events(plan.planned.events, quiet)


def _accuracy_events(accuracy: float | None, estimate) -> list:
    """An accuracy-check event where the run's own exit error estimate (from a run at twice
    its spacing) is above the `accuracy` the auto discretization chose the run for by its
    estimate (from runs at h and h/2): both stand in the summary, so the difference is said."""
    if accuracy is None or estimate is None or estimate.estimate_mm <= accuracy:
        return []
    return [_note_event(f"accuracy: the run's own exit error estimate, {estimate.estimate_mm:.3g} mm (from "
                        f"the run at {estimate.other_spacing_mm:.3g} mm), is above the {accuracy:g} mm "
                        "asked for, which the auto discretization met by its estimate from two finer "
                        "runs (first note); the two estimate the same error from different pairs of "
                        "runs: for a firmer bound ask for a smaller accuracy")]


def _note_event(message: str):
    from ..events import Event, EventKind

    return Event(EventKind.ACCURACY_CHECK, message)


@app.command()
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
    from ..errors import InputError

    _setup_logging(verbose, quiet)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out: {out} is a file, expected a folder")
    from ..io.study_reports import study_outputs, summary_lines, write_study_outputs

    executor = _executor(workers, scheduler)
    _check_outputs(study_outputs(out), {"SCENARIO": scenario_path})
    scenario = _load(scenario_path, None, None)
    _needle_geometry(scenario_path, scenario)  # the sweep needs a needle that enters and exits
    from ..io.progress import progress_bar
    from ..study.sweep import plan_runs, run_study, study_size

    resume_collection()

    with _naming_files(scenario_path):
        runs, reference, repeats = plan_runs(scenario, quick)
    from ..resources import Origin

    def origin(run) -> Origin:  # a refusal names the study field that set the run's spacing
        return Origin({"spacing": run.source, "needle_spacing": run.source},
                      {"spacing": run.spacing, "needle_spacing": run.spacing})

    # on a local cluster its workers run as many at once, each in a process of its own (None:
    # a scheduler's workers, elsewhere; 0: one after another here)
    workers = executor.workers
    _guard(scenario_path, _limits(max_particles, no_resource_check),
           *[("insertion", run.scenario, f"study run {run.label!r}", repeats, origin(run))
             for run in [*runs, reference]],
           alongside=[] if workers else None, forked=False, workers=workers or None)
    with executor, progress_bar("study runs", study_size(scenario, quick)) as advance:
        result = run_study(scenario, quick=quick, on_run=lambda run: advance(description=run.label),
                           executor=executor)
    csv_path, png_path, json_path = write_study_outputs(result, out, _provenance(scenario_path, scenario))
    for line in summary_lines(result):
        typer.echo(line)
    typer.echo(f"study: wrote {csv_path}, {png_path} and {json_path}")
    _echo_notes(result.notes, quiet)


@app.command()
def schema(verbose: int = VerboseOption, quiet: bool = QuietOption) -> None:
    """Print the JSON Schema of scenario files, for editors and validators.

    For example: stitchplan schema > scenario.schema.json
    """
    import json

    _setup_logging(verbose, quiet)
    from ..config import scenario_schema

    resume_collection()
    typer.echo(json.dumps(scenario_schema(), indent=2))
