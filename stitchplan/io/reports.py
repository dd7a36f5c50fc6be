"""Turn result records into the files users and robots read (CSV, JSON, HDF5, PNG)."""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

import numpy as np

from .. import __version__
from .files import write_csv, write_hdf5, write_json


def run_attributes(command: str, scenario) -> dict:
    return {
        "stitchplan_version": __version__,
        "command": command,
        "scenario_name": scenario.name,
        "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }


def discretization_summary(model) -> dict:
    d = model.discretization
    return {
        "particles": model.n_particles,
        "spacing_mm": float(model.support.max() / d.dilation),  # the coarsest, for graded particles
        "needle_spacing_mm": model.spacing if d.needle_spacing is not None else None,
        "needle_zone_radii": d.needle_zone if d.needle_spacing is not None else None,
        "dilation": d.dilation,
        "quadrature_order": d.quadrature_order,
        "basis_order": d.basis_order,
        "integration": d.integration,
        "quadrature_points": len(model.quadrature_weights),
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


def write_deform_outputs(result, probes_out: Path | None = None, reactions_out: Path | None = None,
                         summary: Path | None = None, out: Path | None = None,
                         plot: Path | None = None) -> None:
    if probes_out is not None:
        rows = np.hstack([result.probes, result.probe_displacements])
        write_csv(probes_out, ["x", "y", "ux", "uy"], rows)
    if reactions_out is not None:
        rows = [[i, fx, fy] for i, (fx, fy) in enumerate(result.reactions.tolist())]
        write_csv(reactions_out, ["segment", "fx", "fy"], rows)
    if summary is not None:
        write_json(summary, deform_summary(result))
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
        }, {**run_attributes("deform", result.scenario), **{
            "wall_seconds": result.wall_seconds,
            "factorizations": report.factorizations,
            "krylov_iterations": report.krylov_iterations,
            "discretization": discretization_summary(result.model),
        }})
    if plot is not None:
        from .plots import plot_deformed

        plot_deformed(plot, result.model.particles, result.particle_displacements,
                      title=f"{result.scenario.name or 'deform'}: deformed particles")


def deform_line(result) -> str:
    """The line `stitchplan deform` prints when it is done."""
    return (f"deform: {result.model.n_particles} particles, {result.scenario.load_steps} load steps, "
            f"{result.report.iterations} Newton iterations, {result.wall_seconds:.3f} s")


def insertion_line(result, command: str = "simulate") -> str:
    """The line `stitchplan simulate` prints when it is done."""
    return (f"{command}: {len(result.steps)} steps, {result.model.n_particles} particles, exit error "
            f"{result.exit_error_mm:.4f} mm (material {result.exit_error_material_mm:.4f} mm), "
            f"{result.wall_seconds:.2f} s")


def plan_line(result, export: Path) -> str:
    """The line `stitchplan plan` prints when it is done."""
    planned, unplanned = result.planned, result.unplanned
    versus = f" vs {unplanned.exit_error_mm:.4f} mm unplanned" if unplanned is not None else ""
    return (f"plan: {len(planned.steps)} steps, exit error {planned.exit_error_mm:.4f} mm planned{versus}, "
            f"{planned.wall_seconds:.2f} s planned run; trajectory written to {export}")


def insertion_summary(result) -> dict:
    steps = result.steps
    return {
        "desired_exit": result.desired_exit,
        "desired_exit_def": result.desired_exit_def,
        "achieved_exit_def": result.achieved_exit_def,
        "achieved_exit": result.achieved_exit,
        "exit_error_mm": result.exit_error_mm,
        "exit_error_material_mm": result.exit_error_material_mm,
        "steps": len(steps),
        "particles": result.model.n_particles,
        "wall_seconds": result.wall_seconds,
        "exit_rotation_rad": result.exit_rotation,
        "needle_center_at_entry": result.geometry.center,
        "needle_points": len(result.needle_points),
        "newton_iterations": int(sum(s.newton_iterations for s in steps)),
        "minres_iterations": int(sum(s.minres_iterations for s in steps)),
        "max_constraint_violation_mm": max((s.constraint_violation for s in steps), default=0.0),
        "tip_tracking": sorted({s.tracking for s in steps}),
        "events": [event.as_record() for event in result.events],
        "solver": result.solver_counts,
        "timings_seconds": result.timings,
        "discretization": discretization_summary(result.model),
    }


def insertion_datasets(result) -> dict[str, dict]:
    steps = result.steps
    geometry = result.geometry

    def column(name):
        return np.asarray([getattr(s, name) for s in steps])

    return {
        "scenario": {"text": result.scenario.source_text},
        "needle": {
            "center_at_entry": geometry.center,
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
                            extra_datasets: dict | None = None) -> None:
    if summary is not None:
        write_json(summary, {**insertion_summary(result), **(extra_summary or {})})
    if out is not None:
        datasets = insertion_datasets(result)
        for group, values in (extra_datasets or {}).items():
            datasets.setdefault(group, {}).update(values)
        write_hdf5(out, datasets, {**run_attributes(command, result.scenario), **{
            "wall_seconds": result.wall_seconds,
            "timings_seconds": result.timings,
            "solver_counts": result.solver_counts,
            "discretization": discretization_summary(result.model),
        }})
    if plot is not None:
        from .plots import plot_insertion

        plot_insertion(plot, result, plot_steps)


def write_plan_outputs(result, export: Path, out: Path | None = None, summary: Path | None = None,
                       plot: Path | None = None) -> None:
    """trajectory.csv (atomic), summary JSON, HDF5 run log and the planned-vs-unplanned PNG."""
    from ..planning.trajectory import trajectory_table

    planned, unplanned = result.planned, result.unplanned
    columns, table = trajectory_table(planned, planned.scenario.robot)
    rows = [[int(row[0])] + list(row[1:]) for row in table]
    extra = {
        "unplanned_exit_error_mm": unplanned.exit_error_mm if unplanned else None,
        "unplanned_exit_error_material_mm": unplanned.exit_error_material_mm if unplanned else None,
        "unplanned_achieved_exit_def": unplanned.achieved_exit_def if unplanned else None,
        "unplanned_wall_seconds": unplanned.wall_seconds if unplanned else None,
        "error_reduction": (1.0 - planned.exit_error_mm / unplanned.exit_error_mm)
        if unplanned and unplanned.exit_error_mm > 0 else None,
        "planner_iterations": int(sum(s.planner_iterations for s in planned.steps)),
        "planner_passes": result.passes,
        "trajectory_rows": len(rows),
        "trajectory_columns": columns,
    }
    datasets = {
        "planner": {
            "center_trajectory": result.center_trajectory,
            "exit_displacement": np.asarray([s.exit_displacement for s in planned.steps]).reshape(-1, 2),
            "planner_iterations": np.asarray([s.planner_iterations for s in planned.steps]),
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
    write_csv(export, columns, rows)
    write_insertion_outputs(planned, "plan", out=out, summary=summary, extra_summary=extra,
                            extra_datasets=datasets)
    if plot is not None:
        from .plots import plot_plan

        plot_plan(plot, result)
