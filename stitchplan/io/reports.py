"""Turn result records into the files users and robots read (CSV, JSON, HDF5, PNG)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .files import OutputSet, rounded_point, write_csv, write_hdf5, write_json
from .files import provenance as make_provenance

# units of the HDF5 run logs' datasets, by "group/name" or by name ("1": a pure number or a
# count; "text": strings)
HDF5_UNITS = {
    "text": "text", "reference": "mm", "displacement": "mm", "coefficients": "mm", "support": "mm",
    "force": "N", "load_fraction": "1", "newton_iterations": "1", "residual": "N", "increment": "mm",
    "step_cuts": "1", "center_at_entry": "mm", "entry": "mm", "radius": "mm", "arc": "rad",
    "step": "rad", "turn_sense": "1", "desired_exit": "mm", "desired_exit_def": "mm",
    "achieved_exit": "mm", "achieved_exit_def": "mm", "exit_rotation": "rad",
    "trajectory_reference": "mm", "steps/step": "1", "rotation": "rad", "center": "mm",
    "needle_tip": "mm", "tip_reference": "mm", "tip_spatial": "mm", "needle_points": "1",
    "insertion_force": "N", "friction_force": "N", "cutting_force": "N", "minres_iterations": "1",
    "constraint_violation": "mm", "tracking": "text", "exit_displacement": "mm",
    "planner_iterations": "1", "condition_saddle": "1", "condition_preconditioned": "1",
    "events/kind": "text", "events/step": "1", "angle_rad": "rad", "message": "text",
    "center_trajectory": "mm", "trajectory_columns": "text", "exit_error_mm": "mm",
    "final_displacement": "mm", "equilibrium_solves": "1", "wall_seconds": "s", "eq42_ratio": "1",
}


def column_units(columns: list[str]) -> str:
    """Units of a table's columns, comma-separated, from their names (`_mm`, `_rad`, `_s`)."""
    suffixes = {"mm": "mm", "rad": "rad", "s": "s", "N": "N"}
    return ",".join(suffixes.get(name.rsplit("_", 1)[-1], "1") for name in columns)


def run_attributes(command: str, scenario, provenance: dict | None = None) -> dict:
    """The run log's root attributes: the command's name and the provenance of the run."""
    record = provenance or make_provenance()
    return {
        "stitchplan_version": record["stitchplan_version"],
        "stitchplan_source_sha256": record["stitchplan_source_sha256"],
        "command": command,
        "command_line": record["command"],
        "scenario_name": scenario.name,
        "scenario": record["scenario"],
        "scenario_sha256": record["scenario_sha256"],
        "created_utc": record["created_utc"],
        "working_directory": record.get("working_directory") or "",
        # a replay's centre path (simulate --center-path), a plan's uncertainty file and the
        # calibration it reads (plan --uncertainty), as the summary gives them
        **{key: record[key] for key in ("center_path", "center_path_sha256", "uncertainty_file",
                                        "uncertainty_file_sha256", "calibration_file", "calibration_file_sha256")
           if key in record},
    }


def discretization_summary(model) -> dict:
    """Of a TissueModel or its ModelOutline (a replay from the helper process)."""
    outline = model.outline()
    d = outline.discretization
    return {
        "particles": outline.n_particles,
        "spacing_mm": outline.coarsest_spacing,  # the coarsest, for graded particles
        # the scenario's spacing (or --spacing's), before the particles are fitted to the tissue
        "requested_spacing_mm": d.spacing,
        "needle_spacing_mm": outline.needle_spacing if d.needle_spacing is not None else None,
        "needle_zone_radii": d.needle_zone if d.needle_spacing is not None else None,
        "needle_grading": d.needle_grading if d.needle_spacing is not None else None,
        "dilation": d.dilation,
        "quadrature_order": d.quadrature_order,
        "basis_order": d.basis_order,
        "integration": d.integration,
        "quadrature_points": outline.quadrature_points,
    }


def deform_summary(result) -> dict:
    report = result.report
    return {
        **discretization_summary(result.model),
        "load_steps": result.scenario.load_steps,
        "newton_iterations": report.iterations,
        "step_cuts": report.cuts,
        "factorizations": report.factorizations,
        "krylov_iterations": report.krylov_iterations,
        "solver": deform_solver_counts(report),
        "final_residual_N": report.steps[-1].residual if report.steps else 0.0,
        "wall_seconds": result.wall_seconds,
        "timings_seconds": result.timings,
        "max_displacement_mm": float(np.linalg.norm(result.particle_displacements, axis=1).max()),
        "probes": [
            {"x": p[0], "y": p[1], "ux": u[0], "uy": u[1]}
            for p, u in zip(result.probes.tolist(), result.probe_displacements.tolist())
        ],
        "reactions_N": result.reactions.tolist(),
    }


def deform_solver_counts(report) -> dict:
    """deform's `solver` block, as simulate's and plan's: the linear solves, which sparse
    factorization made the last factor (`linear_solver_backend`) and every one that ran."""
    backends = report.linear_solver_backends
    return {"factorizations": report.factorizations, "linear_solves": report.linear_solves,
            "krylov_iterations": report.krylov_iterations, "linear_solver": report.linear_solver,
            "linear_solver_backend": backends[-1] if backends else None, "linear_solver_backends": backends}


def write_deform_outputs(result, probes_out: Path | None = None, reactions_out: Path | None = None,
                         summary: Path | None = None, out: Path | None = None,
                         plot: Path | None = None, provenance: dict | None = None,
                         plot_scale: float = 1.0) -> None:
    """All of deform's outputs, or none of them (an OutputSet); the PNG draws the
    displacements `plot_scale` times enlarged."""
    provenance = provenance or make_provenance()
    outputs = OutputSet({"--probes-out": probes_out, "--reactions-out": reactions_out,
                         "--summary": summary, "--out": out, "--plot": plot})
    with outputs.staged() as files:
        _write_deform_files(result, files, provenance, plot_scale)


def _write_deform_files(result, files: dict[str, Path], provenance: dict, plot_scale: float = 1.0) -> None:
    """Writes to the temporaries `files` of an OutputSet."""
    probes_out, reactions_out, summary, out, plot = (
        files.get(label) for label in ("--probes-out", "--reactions-out", "--summary", "--out", "--plot"))
    if probes_out is not None:
        # to 1e-12 mm as the summary's points: 0, not 2.3e-21, at a probe the clamp holds
        rows = np.hstack([result.probes, rounded_point(result.probe_displacements)])
        write_csv(probes_out, ["x", "y", "ux", "uy"], rows)
    if reactions_out is not None:
        rows = [[i, fx, fy] for i, (fx, fy) in enumerate(result.reactions.tolist())]
        write_csv(reactions_out, ["segment", "fx", "fy"], rows)
    if summary is not None:
        write_json(summary, {**provenance, **deform_summary(result)})
    if out is not None:
        report = result.report
        write_hdf5(out, {
            "scenario": {"text": result.scenario.source_text},
            "particles": {
                "reference": result.model.particles,
                "displacement": result.particle_displacements,
                "coefficients": result.coefficients,
                "support": result.model.support,
            },
            "probes": {"reference": result.probes, "displacement": result.probe_displacements},
            "reactions": {"force": result.reactions},
            "solver": {
                "load_fraction": [s.load_fraction for s in report.steps],
                "newton_iterations": [s.iterations for s in report.steps],
                "residual": [s.residual for s in report.steps],
                "increment": [s.increment for s in report.steps],
                "step_cuts": [s.cuts for s in report.steps],
            },
        }, {**run_attributes("deform", result.scenario, provenance), **{
            "wall_seconds": result.wall_seconds,
            "factorizations": report.factorizations,
            "krylov_iterations": report.krylov_iterations,
            "solver_counts": deform_solver_counts(report),
            "discretization": discretization_summary(result.model),
        }}, HDF5_UNITS)
    if plot is not None:
        from .plots import plot_deformed

        plot_deformed(plot, result, scale=plot_scale)


def deform_line(result) -> str:
    """The line `stitchplan deform` prints when it is done."""
    return (f"deform: {result.model.n_particles} particles, {result.scenario.load_steps} load steps, "
            f"{result.report.iterations} Newton iterations, {result.wall_seconds:.3f} s")


def _mm(value: float, sign: str = "") -> str:
    """A length in mm for a result line: four decimals, or two significant digits below
    0.0001 mm (a plan's exit error of 5e-11 mm is not 0.0000)."""
    return f"{value:{sign}.4f}" if value == 0.0 or abs(value) >= 5e-5 else f"{value:{sign}.2g}"


def insertion_line(result, command: str = "simulate", estimate=None) -> str:
    """The line `stitchplan simulate` prints when it is done, with the exit error's
    discretization error estimate (planning.verification.ExitEstimate) when there is one."""
    line = (f"{command}: {len(result.steps)} steps, {result.model.n_particles} particles, exit error "
            f"{_mm(result.exit_error_mm)} mm (material {_mm(result.exit_error_material_mm)} mm), "
            f"{result.wall_seconds:.2f} s")
    if estimate is not None:
        line += (f"; discretization error estimate {_mm(estimate.estimate_mm)} mm "
                 f"(from a run at spacing {estimate.other_spacing_mm:.3g} mm)")
    return line


def plan_line(result, export: Path) -> str:
    """The line `stitchplan plan` prints when it is done."""
    planned, unplanned = result.planned, result.unplanned
    versus = f" vs {_mm(unplanned.exit_error_mm)} mm unplanned" if unplanned is not None else ""
    verification = getattr(result, "verification", None)
    if verification is not None and verification.result is not None:
        versus += f", {_mm(verification.exit_error_mm)} mm verified at spacing {verification.spacing_mm:.3g} mm"
        if verification.result.bites:  # a stitch across a wound
            versus += f" (bites differ by {_mm(verification.result.bites['difference_mm'], '+')} mm there)"
    estimate = getattr(result, "estimate", None)
    if estimate is not None:
        versus += f", discretization error estimate {_mm(estimate.estimate_mm)} mm"
    return (f"plan: {len(planned.steps)} steps, exit error {_mm(planned.exit_error_mm)} mm planned{versus}, "
            f"{planned.wall_seconds:.2f} s planned run; trajectory written to {export}")


def _points(record: dict, keys: tuple[str, ...]) -> dict:
    """`record` with its points at `keys` rounded (rounded_point)."""
    return {key: rounded_point(value) if key in keys else value for key, value in record.items()}


CROSSING_POINTS = ("desired", "desired_def", "achieved_def")
BITE_POINTS = ("entry_wound_edge", "exit_wound_edge", "entry_wound_edge_def", "exit_wound_edge_def")


def insertion_summary(result) -> dict:
    steps = result.steps
    tip_at_exit = needle_tip_at_exit(result)
    return {
        "desired_exit": rounded_point(result.desired_exit),
        "desired_exit_def": rounded_point(result.desired_exit_def),
        "achieved_exit_def": rounded_point(result.achieved_exit_def),
        "achieved_exit": rounded_point(result.achieved_exit),
        "exit_error_mm": result.exit_error_mm,
        "exit_error_material_mm": result.exit_error_material_mm,
        "steps": len(steps),
        "particles": result.model.n_particles,
        "wall_seconds": result.wall_seconds,
        "exit_rotation_rad": result.exit_rotation,
        # the rigid needle's tip as the track reaches the boundary: the tissue at the cut's end,
        # carried along the needle by friction and the cutting force, is ahead of it on the arc
        "needle_tip_at_exit": rounded_point(tip_at_exit),
        "exit_to_needle_tip_mm": float(np.linalg.norm(result.achieved_exit_def - tip_at_exit)),
        "needle_center_at_entry": rounded_point(result.center_after(0)),
        # rad the needle leaned from the orthogonal entry (needle.entry_tilt, a plan's lean)
        "needle_entry_tilt_rad": result.geometry.tilt,
        "needle_points": len(result.needle_points),
        "newton_iterations": int(sum(s.newton_iterations for s in steps)),  # every iteration of every solve
        "equilibrium_solves": int(sum(s.equilibrium_solves for s in steps)),
        "minres_iterations": int(sum(s.minres_iterations for s in steps)),
        "max_constraint_violation_mm": max((s.constraint_violation for s in steps), default=0.0),
        "tip_tracking": sorted({s.tracking for s in steps}),
        "events": [event.as_record() for event in result.events],
        "solver": result.solver_counts,
        "timings_seconds": {**result.timings, "steps": step_time_distribution(steps)},
        "discretization": discretization_summary(result.model),
        # every crossing after the first entry, the final exit last (README, "Tissue shapes")
        "crossings": [_points({key: record[key] for key in ("kind", *CROSSING_POINTS, "error_mm")}, CROSSING_POINTS)
                      for record in getattr(result, "crossings", [])],
        **({"bites": _points(result.bites, BITE_POINTS)} if getattr(result, "bites", None) else {}),
    }


def needle_tip_at_exit(result) -> np.ndarray:
    """The rigid needle's tip at the exit rotation, about the last step's centre (which the
    trajectory's exit row keeps)."""
    center = result.steps[-1].center if result.steps else result.center_after(0)
    return result.geometry.tip(result.exit_rotation, center)


def step_time_distribution(steps) -> dict:
    """Median, 90th percentile and largest wall time of the needle steps, s (tip tracking,
    equilibrium and the planner's centre iterations of each step)."""
    times = np.asarray([s.wall_seconds for s in steps], dtype=float)
    if not len(times):
        return {"median": None, "p90": None, "max": None}
    return {"median": float(np.median(times)), "p90": float(np.percentile(times, 90)), "max": float(times.max())}


def exit_estimate_summary(estimate) -> dict:
    """`exit_error_estimate_mm` and how it was made (planning.verification.ExitEstimate)."""
    return {"exit_error_estimate_mm": None if estimate is None else estimate.estimate_mm,
            "exit_error_estimate": None if estimate is None else estimate.as_record()}


def scenario_keys(scenario) -> dict:
    """A run's model and needle methods as the keys of a scenario file that give them:
    `discretization` (discretization_keys) and the needle's `tip_tracking` and
    `linear_solver` (an auto discretization chooses them too)."""
    needle = scenario.needle
    return {"discretization": discretization_keys(scenario.discretization),
            "needle": {"tip_tracking": needle.tip_tracking, "linear_solver": needle.linear_solver}}


def discretization_keys(discretization) -> dict:
    """A discretization as the keys of a scenario file's `discretization` block that give it:
    the spacing, and the needle spacing or the needle refinement it derives from, always
    (their defaults depend on the scene; a null needle spacing makes the particles uniform),
    the others where they differ from the defaults."""
    from dataclasses import fields

    values = discretization.as_input()
    keys = {"spacing": values["spacing"]}
    if values["needle_refinement"] is None:
        keys["needle_spacing"] = values["needle_spacing"]
    else:
        keys["needle_refinement"] = values["needle_refinement"]
    for field in fields(discretization):
        if field.name not in keys and values[field.name] != field.default:
            keys[field.name] = values[field.name]
    return keys


def plan_accuracy_summary(result, centers: np.ndarray) -> dict:
    """The exit error estimate, the verification on the refined model and the smoothness of
    the exported centre path `centers` (n, 2) of a PlanResult."""
    from ..planning.move_limits import path_smoothness

    verification = result.verification
    replay = verification.result if verification is not None else None
    max_step, max_second = path_smoothness(centers)
    return {
        **exit_estimate_summary(result.estimate),
        "verified_exit_error_mm": replay.exit_error_mm if replay is not None else None,
        "verification_spacing_mm": verification.spacing_mm if verification is not None else None,
        "verification": None if verification is None else {
            "spacing_mm": verification.spacing_mm,  # `--spacing` that reproduces the replay
            "discretization": discretization_summary(replay.model) if replay is not None else None,
            # the refined model and the needle's methods as a scenario file's keys: what
            # reproduces the replay where `--spacing` cannot (an auto discretization's choice)
            "scenario_keys": scenario_keys(replay.scenario) if replay is not None else None,
            "achieved_exit_def": rounded_point(replay.achieved_exit_def) if replay is not None else None,
            "desired_exit_def": rounded_point(replay.desired_exit_def) if replay is not None else None,
            "exit_error_material_mm": replay.exit_error_material_mm if replay is not None else None,
            "wall_seconds": replay.wall_seconds if replay is not None else None,
            "rounds": verification.rounds,
            # where the replays ran: a helper process times a round's replay from the start
            # of the pass it follows (planning/replays.py)
            "replayed_in": verification.replayed_in,
            # a stitch across a wound: each side's bite on the refined model too (what a
            # symmetric plan aims at)
            **({"bites": _points(replay.bites, BITE_POINTS)} if replay is not None and replay.bites else {}),
        },
        "max_center_step_mm": max_step,
        "max_center_second_difference_mm": max_second,
    }


def insertion_datasets(result) -> dict[str, dict]:
    steps = result.steps
    geometry = result.geometry

    def column(name):
        return np.asarray([getattr(s, name) for s in steps])

    return {
        "scenario": {"text": result.scenario.source_text},
        "needle": {
            "center_at_entry": result.center_after(0),
            "entry": geometry.entry,
            "radius": geometry.radius,
            "arc": geometry.arc,
            "step": geometry.step,
            "turn_sense": geometry.sense,
            "desired_exit": result.desired_exit,
            "desired_exit_def": result.desired_exit_def,
            "achieved_exit": result.achieved_exit,
            "achieved_exit_def": result.achieved_exit_def,
            "exit_rotation": result.exit_rotation,
            "trajectory_reference": result.needle_points,
        },
        "steps": {
            "step": column("step"),
            "rotation": column("rotation"),
            "center": column("center").reshape(-1, 2),
            "needle_tip": column("needle_tip").reshape(-1, 2),
            "tip_reference": column("tip_reference").reshape(-1, 2),
            "tip_spatial": column("tip_spatial").reshape(-1, 2),
            "needle_points": column("needle_points"),
            "insertion_force": np.asarray([s.insertion_force for s in steps]),
            "friction_force": column("friction_force"),
            "cutting_force": column("cutting_force"),
            "newton_iterations": column("newton_iterations"),
            "minres_iterations": column("minres_iterations"),
            "constraint_violation": column("constraint_violation"),
            "tracking": "\n".join(s.tracking for s in steps),
            "exit_displacement": column("exit_displacement").reshape(-1, 2),
            "planner_iterations": column("planner_iterations"),
            "equilibrium_solves": column("equilibrium_solves"),
            "wall_seconds": column("wall_seconds"),
            "condition_saddle": column("condition_saddle"),
            "condition_preconditioned": column("condition_preconditioned"),
        },
        "particles": {"reference": result.model.particles, "displacement": result.displacements},
        "events": {
            "kind": "\n".join(event.kind.value for event in result.events),
            "step": np.asarray([-1 if e.step is None else e.step for e in result.events], dtype=int),
            "angle_rad": np.asarray([np.nan if e.angle_rad is None else e.angle_rad for e in result.events]),
            "message": "\n".join(event.message for event in result.events),
        },
    }


def write_insertion_outputs(result, command: str, out: Path | None = None,
                            summary: Path | None = None, plot: Path | None = None,
                            plot_steps: list[int] | None = None, extra_summary: dict | None = None,
                            extra_datasets: dict | None = None, provenance: dict | None = None) -> None:
    """simulate's outputs, all or none (an OutputSet)."""
    outputs = OutputSet({"--out": out, "--summary": summary, "--plot": plot})
    with outputs.staged() as files:
        _write_insertion_files(result, command, files.get("--out"), files.get("--summary"),
                               files.get("--plot"), plot_steps, extra_summary, extra_datasets,
                               provenance)


def _write_insertion_files(result, command: str, out: Path | None, summary: Path | None,
                           plot: Path | None, plot_steps: list[int] | None = None,
                           extra_summary: dict | None = None, extra_datasets: dict | None = None,
                           provenance: dict | None = None, units: dict | None = None) -> None:
    """Writes to the temporaries of an OutputSet (simulate's or plan's)."""
    provenance = provenance or make_provenance()
    if summary is not None:
        write_json(summary, {**provenance, **insertion_summary(result), **(extra_summary or {})})
    if out is not None:
        datasets = insertion_datasets(result)
        for group, values in (extra_datasets or {}).items():
            datasets.setdefault(group, {}).update(values)
        write_hdf5(out, datasets, {**run_attributes(command, result.scenario, provenance), **{
            "wall_seconds": result.wall_seconds,
            "timings_seconds": {**result.timings, "steps": step_time_distribution(result.steps)},
            # a plan's: every planner pass's, summed as its summary's `solver` (planning_work)
            "solver_counts": (extra_summary or {}).get("solver", result.solver_counts),
            "discretization": discretization_summary(result.model),
        }}, {**HDF5_UNITS, **(units or {})})
    if plot is not None:
        from .needle_plots import plot_insertion

        plot_insertion(plot, result, plot_steps,
                       estimate_mm=(extra_summary or {}).get("exit_error_estimate_mm"),
                       center_path=provenance.get("center_path"))


def prepare_plan_outputs(out: Path | None = None, plot: Path | None = None) -> None:
    """Import what writing the HDF5 run log (`out`) and plan.png (`plot`) needs, ahead of
    write_plan_outputs: `plan` does it while it waits for its verification's replay
    (planning/replays.py `while_waiting`), the import of matplotlib alone about a quarter of a
    second that then no longer follows the replay."""
    if out is not None:
        import h5py  # noqa: F401
    if plot is not None:
        from .plot_elements import pyplot

        pyplot()


def write_plan_outputs(result, export: Path, out: Path | None = None, summary: Path | None = None,
                       plot: Path | None = None, provenance: dict | None = None,
                       uncertainty=None, uncertainty_plot: Path | None = None) -> None:
    """trajectory.csv, summary JSON, HDF5 run log and the planned-vs-unplanned PNG: all of
    them or none (an OutputSet), so a robot never picks up a trajectory whose run failed.
    With `uncertainty` (an uncertainty.robust.UncertaintyResult whose exported plan is
    `result`) the summary's `uncertainty` block, the log's `uncertainty` group and
    `uncertainty_plot` (uncertainty.png) too."""
    outputs = OutputSet({"--export": export, "--out": out, "--summary": summary, "--plot": plot,
                         "--uncertainty-plot": uncertainty_plot})
    with outputs.staged() as files:
        _write_plan_files(result, files, provenance or make_provenance(), uncertainty)


def _write_plan_files(result, files: dict[str, Path], provenance: dict, uncertainty=None) -> None:
    """Writes to the temporaries `files` of an OutputSet."""
    from ..planning.trajectory import trajectory_table

    export, out, summary, plot = (files.get(label) for label in ("--export", "--out", "--summary", "--plot"))
    planned = result.planned
    columns, table = trajectory_table(planned, planned.scenario.robot)
    rows = [[int(row[0])] + list(row[1:]) for row in table]
    extra = _plan_summary(result, columns, table)
    datasets = _plan_datasets(result, columns, table)
    units = {"planner/trajectory": column_units(columns)}
    if uncertainty is not None:
        from .uncertainty_reports import uncertainty_datasets, uncertainty_summary

        extra.update(uncertainty_summary(uncertainty))
        groups, group_units = uncertainty_datasets(uncertainty)
        datasets.update(groups)
        units.update(group_units)
    write_csv(export, columns, rows, precision=None)  # the doubles the verification replayed, to the last bit
    _write_insertion_files(planned, "plan", out, summary, None, extra_summary=extra,
                           extra_datasets=datasets, provenance=provenance, units=units)
    if plot is not None:
        from .needle_plots import plot_plan

        plot_plan(plot, result)
    if files.get("--uncertainty-plot") is not None:
        from .uncertainty_reports import plot_uncertainty

        plot_uncertainty(files["--uncertainty-plot"], uncertainty, planned.scenario.name)


def _plan_summary(result, columns: list[str], table: np.ndarray) -> dict:
    """What a plan's summary adds to its planned run's: the unplanned run's exit, the
    planner's passes, lean and work, and the trajectory's shape and accuracy."""
    from ..planning.planner import planning_work

    planned, unplanned = result.planned, result.unplanned
    return {
        "unplanned_exit_error_mm": unplanned.exit_error_mm if unplanned else None,
        "unplanned_exit_error_material_mm": unplanned.exit_error_material_mm if unplanned else None,
        "unplanned_achieved_exit_def": rounded_point(unplanned.achieved_exit_def) if unplanned else None,
        "unplanned_wall_seconds": unplanned.wall_seconds if unplanned else None,
        "error_reduction": (1.0 - planned.exit_error_mm / unplanned.exit_error_mm)
        if unplanned and unplanned.exit_error_mm > 0 else None,
        "planner_iterations": int(sum(s.planner_iterations for s in planned.steps)),
        # steps where the thesis's plain centre update would stall (eq. 4.2 fails: the exit
        # point moves with the centre at least one for one); the Newton update goes on there
        "planner_eq42_failed_steps": [s.step for s in planned.steps if s.eq42_ratio >= 1.0],
        "planner_passes": result.passes,
        # planner.aim_entry_tilt: the lean chosen and the first passes tried
        "planner_entry_lean": result.lean.as_record() if result.lean is not None else None,
        # every pass's work, the discarded passes' included (the HDF5 steps: the exported run's)
        **planning_work(result),
        "trajectory_rows": len(table),
        "trajectory_columns": columns,
        # the robot frame and speed the trajectory was written with (the file's robot block, or
        # --base-transform and --angular-speed, which take its place)
        "robot": _robot_record(planned.scenario.robot),
        **plan_accuracy_summary(result, table[:, 2:4]),
    }


def _robot_record(robot) -> dict:
    """The summary's `robot`: the base transform applied (None: the tissue frame only) and the
    angular speed (None: no time_s)."""
    transform = ({"rotation_deg": robot.rotation_deg, "translation_mm": list(robot.translation)}
                 if robot.given else None)
    return {"base_transform": transform, "angular_speed_rad_s": robot.angular_speed}


def _plan_datasets(result, columns: list[str], table: np.ndarray) -> dict[str, dict]:
    """What a plan's HDF5 run log adds to its planned run's: the planner's group (centre
    trajectory, exit displacements, iterations, trajectory table) and the unplanned run's."""
    planned, unplanned = result.planned, result.unplanned
    datasets = {
        "planner": {
            "center_trajectory": result.center_trajectory,
            "exit_displacement": np.asarray([s.exit_displacement for s in planned.steps]).reshape(-1, 2),
            "planner_iterations": np.asarray([s.planner_iterations for s in planned.steps]),
            "eq42_ratio": np.asarray([s.eq42_ratio for s in planned.steps]),
            "trajectory_columns": ",".join(columns),
            "trajectory": table,
        },
    }
    if unplanned is not None:
        datasets["unplanned"] = {
            "tip_spatial": np.asarray([s.tip_spatial for s in unplanned.steps]).reshape(-1, 2),
            "tip_reference": np.asarray([s.tip_reference for s in unplanned.steps]).reshape(-1, 2),
            "achieved_exit": unplanned.achieved_exit,
            "achieved_exit_def": unplanned.achieved_exit_def,
            "desired_exit_def": unplanned.desired_exit_def,
            "exit_error_mm": unplanned.exit_error_mm,
            "final_displacement": unplanned.displacements[-1],
        }
    return datasets
