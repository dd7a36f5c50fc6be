"""Turn result records into the files users and robots read (CSV, JSON, HDF5, PNG)."""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

import numpy as np

from . import __version__
from .io import write_csv, write_hdf5, write_json


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
        "spacing_mm": model.spacing,
        "dilation": d.dilation,
        "quadrature_order": d.quadrature_order,
        "basis_order": d.basis_order,
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
