"""The files and lines of `stitchplan study`: study.csv (one row per run), speed_accuracy.png,
study.json (the run's provenance and outcome) and the summary printed by the command. The
study itself is stitchplan.study.sweep."""

from __future__ import annotations

import math
from pathlib import Path

from ..study.sweep import StudyResult, StudyRun
from .files import OutputSet, rounded_point, write_csv, write_json
from .files import provenance as make_provenance
from .plots import plot_speed_accuracy

COLUMNS = ("family", "label", "spacing_mm", "coarse_spacing_mm", "grading", "dilation",
           "quadrature_order", "basis_order", "step_rad", "tip_tracking", "linear_solver", "linear_solver_backend", "particles",
           "wall_seconds", "cpu_seconds", "steps", "newton_iterations", "minres_iterations", "events",
           "exit_error_mm", "achieved_exit_def_x", "achieved_exit_def_y", "achieved_exit_x",
           "achieved_exit_y", "exit_deviation_mm", "material_exit_deviation_mm",
           "exit_error_deviation_mm", "deviation_mm", "pareto", "status", "reason")
DEVIATIONS = ("exit_deviation_mm", "material_exit_deviation_mm", "exit_error_deviation_mm", "deviation_mm")


def study_row(run: StudyRun) -> list:
    """The run's row of study.csv, in COLUMNS order (nan where a failed run has no value)."""
    d, needle = run.scenario.discretization, run.scenario.needle
    r = run.result
    grading = round(d.spacing / d.needle_spacing) if d.needle_spacing else 1
    steps = r.steps if r is not None else []
    nan2 = (math.nan, math.nan)
    return [
        run.family, run.label, run.spacing, d.spacing, grading, d.dilation, d.quadrature_order,
        d.basis_order, needle.step, needle.tip_tracking, needle.linear_solver,
        r.solver_counts.get("linear_solver_backend", "") if r is not None else "", run.particles,
        run.wall_seconds, run.cpu_seconds, len(steps), sum(s.newton_iterations for s in steps),
        sum(s.minres_iterations for s in steps), len(r.events) if r is not None else 0,
        r.exit_error_mm if r is not None else math.nan,
        # the exits to 1e-12 mm, as the summaries' points: 0, not 4e-16, on an exit edge at y = 0
        *(rounded_point(r.achieved_exit_def) if r is not None else nan2), *(rounded_point(r.achieved_exit) if r is not None else nan2),
        *(run.deviations.get(key, math.nan) for key in DEVIATIONS),
        str(run.pareto).lower(), run.status, run.reason,
    ]


def study_outputs(out: str | Path) -> dict[str, Path]:
    """The files `stitchplan study --out DIR` writes, by label."""
    return {f"--out's {name}": Path(out) / name for name in ("study.csv", "speed_accuracy.png", "study.json")}


def study_record(result: StudyResult, provenance: dict | None = None) -> dict:
    """study.json: the provenance of the study (version, command line, scenario and its
    SHA-256, time), its counts, the sweep as run (each family's spacings), the reference (its
    spacing and needle step), Pareto front, notes and the linear-solver backends its runs used
    (each run's choices and diagnostics are its row of study.csv) and where the runs ran
    (`executor`: their wall times depend on how many ran at once)."""
    reference = result.reference
    families: dict[str, list[float]] = {}  # the sweep as resolved: each family's spacings, in run order
    for run in result.runs:
        families.setdefault(run.family, []).append(run.spacing)
    return {
        **(provenance or make_provenance()),
        "runs": len(result.runs), "ok": sum(run.ok for run in result.runs), "failed": len(result.failed),
        "families": families,
        "reference": {"label": reference.label, "spacing_mm": reference.spacing,
                      "step_rad": reference.scenario.needle.step,
                      "particles": reference.particles, "wall_seconds": reference.wall_seconds},
        "pareto": [run.label for run in sorted(result.front, key=lambda run: run.wall_seconds)],
        "linear_solver_backends": sorted({run.result.solver_counts.get("linear_solver_backend", "")
                                          for run in result.runs if run.result is not None}),
        "executor": result.executor,
        "notes": list(result.notes),
    }


def write_study_outputs(result: StudyResult, out: str | Path, provenance: dict | None = None) -> tuple[Path, ...]:
    """out/study.csv (one row per run), out/speed_accuracy.png and out/study.json: all or none
    (an OutputSet)."""
    outputs = study_outputs(out)
    csv_label, png_label, json_label = outputs
    with OutputSet(outputs).staged() as files:
        write_csv(files[csv_label], COLUMNS, [study_row(run) for run in result.runs])
        plot_speed_accuracy(files[png_label], result)
        write_json(files[json_label], study_record(result, provenance))
    return tuple(outputs.values())


def summary_lines(result: StudyResult) -> list[str]:
    """What `stitchplan study` prints: the counts, the reference, the Pareto front (its notes go
    to stderr with the runs' notes)."""
    ok = [r for r in result.runs if r.ok]
    lines = [f"study: {len(result.runs)} runs ({len(ok)} ok, {len(result.runs) - len(ok)} failed); "
             f"{result.reference.label}: {result.reference.particles} particles, "
             f"{result.reference.wall_seconds:.2f} s"]
    front = sorted(result.front, key=lambda r: r.wall_seconds)
    width = max([32, *(len(run.label) for run in front)])  # long family names keep the columns
    for run in front:
        # three significant figures, as speed_accuracy.png: a front's deviations fall with its times
        lines.append(f"  Pareto: {run.label:{width}s} {run.particles:6d} particles {run.wall_seconds:7.2f} s  "
                     f"deviation {run.deviation_mm:.3g} mm")
    return lines
