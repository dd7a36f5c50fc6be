"""What the Newton residual tolerance (`solver.residual_tolerance`) costs and leaves behind.

For every shipped needle scene: the unplanned insertion solved to a relative residual of
REFERENCE (1e-10 of the needle force, as good as converged) and to each tolerance of
TOLERANCES; how far its exit point lies from the reference's (mm) and how many Newton
iterations it took. Then the planned run (`plan --no-compare --no-verify`'s, in process) at
each tolerance: Newton iterations, planned exit error, the largest difference of the
exported centres from those at the first tolerance, and its wall time (median of REPEATS,
the tolerances alternating). And `deform` on configs/slab_edge_load.yaml: its probes'
largest distance from the reference's. Last, the 20 mm needle scenes' unplanned exit errors
at the default spacing h, h/sqrt(2) and h/2 (benchmarks/needle_coupling.py's levels), at the
default tolerance and at REFERENCE: whether the differences between the levels, a fraction
of a micrometre there, are the discretization's or the solver's.

Writes benchmarks/results/solver_tolerance.{csv,md}. About 5 minutes.
Run from the repository root:  python benchmarks/solver_tolerance.py
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import gc  # noqa: E402
import logging  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402

import _common as common  # noqa: E402
import numpy as np  # noqa: E402

from stitchplan.config.scenario import load_scenario, with_discretization  # noqa: E402
from stitchplan.needle.insertion import run_insertion  # noqa: E402
from stitchplan.planning.planner import run_plan  # noqa: E402
from stitchplan.tissue.deform import run_deform  # noqa: E402

REFERENCE = 1e-10
TOLERANCES = (1e-6, 5e-6)  # the former default and the default
REPEATS = 3
CONFIGS = common.REPO_ROOT / "configs"


def with_tolerance(scenario, tolerance: float):
    # the increment test must not stop Newton before the residual one does
    return replace(scenario, solver=replace(scenario.solver, residual_tolerance=tolerance,
                                            increment_tolerance=min(scenario.solver.increment_tolerance,
                                                                    1e-2 * tolerance)))


def needle_scenes() -> list[str]:
    return [path.stem for path in sorted(CONFIGS.glob("*.yaml")) if load_scenario(path).needle is not None]


def unplanned(name: str) -> list[dict]:
    base = load_scenario(CONFIGS / f"{name}.yaml")
    runs = {tolerance: run_insertion(with_tolerance(base, tolerance)) for tolerance in (REFERENCE, *TOLERANCES)}
    reference = runs[REFERENCE].achieved_exit_def
    return [{"scene": name, "run": "unplanned", "tolerance": tolerance,
             "exit_error_mm": run.exit_error_mm,
             "exit_from_reference_mm": float(np.linalg.norm(run.achieved_exit_def - reference)),
             "newton_iterations": sum(step.newton_iterations for step in run.steps)}
            for tolerance, run in runs.items()]


def planned(name: str) -> list[dict]:
    base = load_scenario(CONFIGS / f"{name}.yaml")
    scenarios = {tolerance: with_tolerance(base, tolerance) for tolerance in TOLERANCES}
    seconds, results = {tolerance: [] for tolerance in TOLERANCES}, {}
    for round_ in range(REPEATS):
        order = TOLERANCES[round_ % len(TOLERANCES):] + TOLERANCES[:round_ % len(TOLERANCES)]
        for tolerance in order:
            gc.collect()
            start = time.perf_counter()
            results[tolerance] = run_plan(scenarios[tolerance], compare=False)
            seconds[tolerance].append(time.perf_counter() - start)
    first = results[TOLERANCES[0]].exported_centers
    return [{"scene": name, "run": "planned", "tolerance": tolerance,
             "exit_error_mm": result.planned.exit_error_mm,
             "centers_from_first_mm": float(np.abs(result.exported_centers - first).max())
             if result.exported_centers.shape == first.shape else float("nan"),
             "newton_iterations": sum(step.newton_iterations for step in result.planned.steps),
             "seconds": statistics.median(seconds[tolerance])}
            for tolerance, result in results.items()]


def deform_probes() -> list[dict]:
    base = load_scenario(common.SCENARIO_PATH)
    runs = {tolerance: run_deform(with_tolerance(base, tolerance)) for tolerance in (REFERENCE, *TOLERANCES)}
    reference = runs[REFERENCE].probe_displacements
    return [{"scene": common.SCENARIO_PATH.stem, "run": "deform", "tolerance": tolerance,
             "probes_from_reference_mm": float(np.abs(run.probe_displacements - reference).max()),
             "newton_iterations": sum(record.iterations for record in run.report.steps)}
            for tolerance, run in runs.items()]


REFINEMENT = (1.0, 2.0 ** -0.5, 0.5)  # spacing factors, as benchmarks/needle_coupling.py's
NEEDLE20 = ("needle20_entry30", "needle20_entry25", "needle20_entry20", "needle20_entry18")


def refinement(name: str) -> list[dict]:
    base = load_scenario(CONFIGS / f"{name}.yaml")
    rows = []
    for tolerance in (base.solver.residual_tolerance, REFERENCE):
        errors = [run_insertion(with_discretization(with_tolerance(base, tolerance),
                                                    spacing=base.discretization.spacing * factor)).exit_error_mm
                  for factor in REFINEMENT]
        rows.append({"scene": name, "tolerance": tolerance, "errors": errors})
    return rows


def refinement_markdown(rows: list[dict]) -> list[str]:
    lines = ["", "## The 20 mm needle scenes under refinement, at two tolerances", "",
             "Unplanned exit error (mm) at the default spacing h, h/sqrt(2) and h/2; the differences "
             "between consecutive levels in micrometres.", "",
             "| scene | tolerance | e(h) | e(h/sqrt(2)) | e(h/2) | e(h/sqrt(2)) - e(h) (um) | e(h/2) - e(h/sqrt(2)) (um) |",
             "|---|---|---|---|---|---|---|"]
    for row in rows:
        e = row["errors"]
        lines.append(f"| {row['scene']} | {row['tolerance']:.0e} | {e[0]:.8f} | {e[1]:.8f} | {e[2]:.8f} | "
                     f"{1e3 * (e[1] - e[0]):+.4f} | {1e3 * (e[2] - e[1]):+.4f} |")
    return lines


def markdown(rows: list[dict]) -> str:
    def value(row, key, digits=".2e"):
        return "" if key not in row or row[key] != row[key] else format(row[key], digits)

    lines = ["# Newton residual tolerance: cost and what it leaves", "",
             f"Generated by `python benchmarks/solver_tolerance.py` ({common.machine_note()}).", "",
             f"Tolerance: the relative residual |r| / |f_needle| at which a needle step's Newton stops "
             f"(`solver.residual_tolerance`); {REFERENCE:.0e} is the reference, as good as converged. "
             "Unplanned: the insertion with the centre fixed; its exit point's distance from the "
             "reference's. Planned: `plan --no-compare --no-verify`'s planned run in process, its "
             f"exported centres' largest difference from those at {TOLERANCES[0]:.0e}, wall time median of "
             f"{REPEATS} (tolerances alternating). Deform: the probes' largest displacement difference "
             "from the reference's.", "",
             "| scene | run | tolerance | exit error (mm) | exit from the reference (mm) | centres from the first (mm) "
             "| Newton iterations | seconds |", "|---|---|---|---|---|---|---|---|"]
    for row in rows:
        distance = row.get("exit_from_reference_mm", row.get("probes_from_reference_mm"))
        lines.append(f"| {row['scene']} | {row['run']} | {row['tolerance']:.0e} | {value(row, 'exit_error_mm', '.6g')} | "
                     f"{'' if distance is None else format(distance, '.2e')} | {value(row, 'centers_from_first_mm')} | "
                     f"{row['newton_iterations']} | {value(row, 'seconds', '.3f')} |")
    unplanned_rows = [row for row in rows if row["run"] == "unplanned" and row["tolerance"] != REFERENCE]
    lines += ["", "Largest exit-point distance from the reference over the scenes: " + ", ".join(
        f"{tolerance:.0e}: {max(row['exit_from_reference_mm'] for row in unplanned_rows if row['tolerance'] == tolerance):.2e} mm"
        for tolerance in TOLERANCES) + "."]
    return "\n".join(lines) + "\n"


def main() -> None:
    logging.getLogger("stitchplan").setLevel(logging.ERROR)
    rows = []
    for name in needle_scenes():
        rows += unplanned(name)
        rows += planned(name)
        print(rows[-1], flush=True)
    rows += deform_probes()
    levels = [row for name in NEEDLE20 for row in refinement(name)]
    header = ["scene", "run", "tolerance", "exit_error_mm", "exit_from_reference_mm", "centers_from_first_mm",
              "probes_from_reference_mm", "newton_iterations", "seconds"]
    common.write_csv(common.results_path("solver_tolerance.csv"), header,
                     [[row.get(key, "") for key in header] for row in rows])
    common.write_report("solver_tolerance.md", markdown(rows).splitlines() + refinement_markdown(levels))


if __name__ == "__main__":
    main()
