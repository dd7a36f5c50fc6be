"""What a needle step's Newton tolerances (`solver.needle_residual_tolerance`, the force
residual over the needle force, and `solver.needle_constraint_tolerance`, the track's
distance from the needle over the needle radius) cost and leave behind.

For every shipped needle scene: the unplanned insertion solved to REFERENCE (1e-10 of the
needle force and 1e-12 R, as good as converged) and to each pair of PAIRS; how far its exit
point lies from the reference's (mm) and how many Newton iterations it took. Then the
planned run (`plan --no-compare --no-verify`'s, in process) at each pair: Newton
iterations, planned exit error, the largest difference of the exported centres from those
at the first pair, and its wall time (median of REPEATS, the pairs alternating). Then the
plan's verification replay: the shipped trajectory (sample_runs/SCENE/trajectory.csv)
replayed on the model of half the spacing, at REFERENCE and at each pair: the verified exit
error, its distance from the reference's, Newton iterations and wall time. And `deform` on
configs/slab_edge_load.yaml at its load steps' `solver.residual_tolerance`: its probes'
largest distance from the reference's. Last, the 20 mm needle scenes' unplanned exit errors
at the default spacing h, h/sqrt(2) and h/2 (benchmarks/needle_coupling.py's levels), at the
default pair and at REFERENCE: whether the differences between the levels, a fraction of a
micrometre there, are the discretization's or the solver's.

Writes benchmarks/results/solver_tolerance.{csv,md}. About 10 minutes.
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
from stitchplan.errors import InsertionFailure  # noqa: E402
from stitchplan.needle.newton import newton_tolerances  # noqa: E402
from stitchplan.needle.insertion import run_insertion  # noqa: E402
from stitchplan.planning.planner import run_plan  # noqa: E402
from stitchplan.tissue.deform import run_deform  # noqa: E402

REFERENCE = (1e-10, 1e-12)  # (needle residual / needle force, constraint / needle radius)
PAIRS = ((5e-6, 1e-9), (1e-4, 1e-7), (1e-3, 1e-7), (1e-3, 1e-6), (1e-2, 1e-5))  # the first: the default before
STATIC_TOLERANCES = (1e-6, 5e-6)  # deform's load steps (solver.residual_tolerance)
STATIC_REFERENCE = 1e-10
REPEATS = 3
CONFIGS = common.REPO_ROOT / "configs"
SAMPLE_RUNS = common.REPO_ROOT / "sample_runs"


def label(pair: tuple[float, float]) -> str:
    return f"{pair[0]:.0e} / {pair[1]:.0e}"


def with_tolerance(scenario, pair: tuple[float, float]):
    residual, constraint = pair
    return replace(scenario, solver=replace(scenario.solver, needle_residual_tolerance=residual,
                                            needle_constraint_tolerance=constraint))


def with_static_tolerance(scenario, tolerance: float):
    # the increment test must not stop Newton before the residual one does
    return replace(scenario, solver=replace(scenario.solver, residual_tolerance=tolerance,
                                            increment_tolerance=min(scenario.solver.increment_tolerance,
                                                                    1e-2 * tolerance)))


def needle_scenes() -> list[str]:
    return [path.stem for path in sorted(CONFIGS.glob("*.yaml")) if load_scenario(path).needle is not None]


def iterations(run) -> int:
    return sum(step.newton_iterations for step in run.steps)


def unplanned(name: str) -> list[dict]:
    base = load_scenario(CONFIGS / f"{name}.yaml")
    runs = {pair: run_insertion(with_tolerance(base, pair)) for pair in (REFERENCE, *PAIRS)}
    reference = runs[REFERENCE].achieved_exit_def
    return [{"scene": name, "run": "unplanned", "tolerance": label(pair),
             "exit_error_mm": run.exit_error_mm,
             "exit_from_reference_mm": float(np.linalg.norm(run.achieved_exit_def - reference)),
             "newton_iterations": iterations(run)}
            for pair, run in runs.items()]


def planned(name: str) -> list[dict]:
    base = load_scenario(CONFIGS / f"{name}.yaml")
    scenarios = {pair: with_tolerance(base, pair) for pair in PAIRS}
    seconds, results = {pair: [] for pair in PAIRS}, {}
    for round_ in range(REPEATS):
        order = PAIRS[round_ % len(PAIRS):] + PAIRS[:round_ % len(PAIRS)]
        for pair in order:
            gc.collect()
            start = time.perf_counter()
            results[pair] = run_plan(scenarios[pair], compare=False)
            seconds[pair].append(time.perf_counter() - start)
    first = results[PAIRS[0]].exported_centers
    return [{"scene": name, "run": "planned", "tolerance": label(pair),
             "exit_error_mm": result.planned.exit_error_mm,
             "centers_from_first_mm": float(np.abs(result.exported_centers - first).max())
             if result.exported_centers.shape == first.shape else float("nan"),
             "newton_iterations": iterations(result.planned),
             "seconds": statistics.median(seconds[pair])}
            for pair, result in results.items()]


def replayed(name: str) -> list[dict]:
    """The shipped trajectory on the verification model (half the spacing)."""
    if not (SAMPLE_RUNS / name / "trajectory.csv").exists():
        return []
    base, centers = common.verification_replay(name)
    runs, seconds = {}, {}
    for pair in (REFERENCE, *PAIRS):
        gc.collect()
        start = time.perf_counter()
        runs[pair] = run_insertion(with_tolerance(base, pair), center_path=centers)
        seconds[pair] = time.perf_counter() - start
    reference = runs[REFERENCE].achieved_exit_def
    return [{"scene": name, "run": "replay h/2", "tolerance": label(pair),
             "exit_error_mm": run.exit_error_mm,
             "exit_from_reference_mm": float(np.linalg.norm(run.achieved_exit_def - reference)),
             "newton_iterations": iterations(run), "seconds": seconds[pair]}
            for pair, run in runs.items()]


COARSE_GRIDS = (4.0, 6.0)  # uniform particle spacings (mm) of the coupling comparison


def coarse_grids() -> list[dict]:
    """sh12_100x100 on uniform particles of COARSE_GRIDS with each coupling, unplanned: where
    several needle points share a particle spacing the point coupling's constraint rows become
    nearly dependent. Distances from the tightest run that finished."""
    rows = []
    for spacing in COARSE_GRIDS:
        for coupling in ("mortar", "points"):
            base = load_scenario(CONFIGS / "sh12_100x100.yaml")
            uniform = base.discretization.replaced(spacing=spacing, needle_spacing=None, needle_refinement=None,
                                                   accuracy=None)
            base = replace(base, needle=replace(base.needle, coupling=coupling), discretization=uniform)
            runs = {}
            for pair in (REFERENCE, *PAIRS):
                try:
                    runs[pair] = run_insertion(with_tolerance(base, pair))
                except InsertionFailure as failure:
                    runs[pair] = failure
            finished = [run for run in runs.values() if not isinstance(run, InsertionFailure)]
            reference = finished[0].achieved_exit_def
            scene = f"sh12_100x100 uniform {spacing:g} mm, {coupling}"
            for pair, run in runs.items():
                if isinstance(run, InsertionFailure):
                    rows.append({"scene": scene, "run": "coarse grid", "tolerance": label(pair),
                                 "failure": str(run).split(";")[0]})
                else:
                    rows.append({"scene": scene, "run": "coarse grid", "tolerance": label(pair),
                                 "exit_error_mm": run.exit_error_mm,
                                 "exit_from_reference_mm": float(np.linalg.norm(run.achieved_exit_def - reference)),
                                 "newton_iterations": iterations(run)})
    return rows


def deform_probes() -> list[dict]:
    base = load_scenario(common.SCENARIO_PATH)
    runs = {tolerance: run_deform(with_static_tolerance(base, tolerance))
            for tolerance in (STATIC_REFERENCE, *STATIC_TOLERANCES)}
    reference = runs[STATIC_REFERENCE].probe_displacements
    return [{"scene": common.SCENARIO_PATH.stem, "run": "deform", "tolerance": f"{tolerance:.0e} (load steps)",
             "probes_from_reference_mm": float(np.abs(run.probe_displacements - reference).max()),
             "newton_iterations": sum(record.iterations for record in run.report.steps)}
            for tolerance, run in runs.items()]


REFINEMENT = (1.0, 2.0 ** -0.5, 0.5)  # spacing factors, as benchmarks/needle_coupling.py's
NEEDLE20 = ("needle20_entry30", "needle20_entry25", "needle20_entry20", "needle20_entry18")


def refinement(name: str) -> list[dict]:
    base = load_scenario(CONFIGS / f"{name}.yaml")
    rows = []
    for pair in (newton_tolerances(base), REFERENCE):
        errors = [run_insertion(with_discretization(with_tolerance(base, pair),
                                                    spacing=base.discretization.spacing * factor)).exit_error_mm
                  for factor in REFINEMENT]
        rows.append({"scene": name, "tolerance": label(pair), "errors": errors})
    return rows


def refinement_markdown(rows: list[dict]) -> list[str]:
    lines = ["", "## The 20 mm needle scenes under refinement, at two tolerances", "",
             "Unplanned exit error (mm) at the default spacing h, h/sqrt(2) and h/2; the differences "
             "between consecutive levels in micrometres.", "",
             "| scene | tolerance | e(h) | e(h/sqrt(2)) | e(h/2) | e(h/sqrt(2)) - e(h) (um) | e(h/2) - e(h/sqrt(2)) (um) |",
             "|---|---|---|---|---|---|---|"]
    for row in rows:
        e = row["errors"]
        lines.append(f"| {row['scene']} | {row['tolerance']} | {e[0]:.8f} | {e[1]:.8f} | {e[2]:.8f} | "
                     f"{1e3 * (e[1] - e[0]):+.4f} | {1e3 * (e[2] - e[1]):+.4f} |")
    return lines


def summary_lines(rows: list[dict]) -> list[str]:
    """Per pair, over the scenes: the largest exit-point distance from the reference, and the
    Newton iterations and planned-run time against the first pair's."""
    lines = ["", "## Over the scenes", "",
             "| tolerance | largest exit from the reference, unplanned (mm) | largest exit from the reference, "
             "replay h/2 (mm) | Newton iterations, unplanned | planned | replay h/2 | planned runs' time |",
             "|---|---|---|---|---|---|---|"]

    def total(run: str, pair, key: str) -> float:
        return sum(row[key] for row in rows if row["run"] == run and row["tolerance"] == label(pair))

    for pair in PAIRS:
        def largest(run: str) -> float:
            return max((row["exit_from_reference_mm"] for row in rows
                        if row["run"] == run and row["tolerance"] == label(pair)), default=float("nan"))

        def relative(run: str, key: str) -> str:
            return f"{total(run, pair, key) / total(run, PAIRS[0], key):.2f}x"

        lines.append(f"| {label(pair)} | {largest('unplanned'):.2e} | {largest('replay h/2'):.2e} | "
                     f"{relative('unplanned', 'newton_iterations')} | {relative('planned', 'newton_iterations')} | "
                     f"{relative('replay h/2', 'newton_iterations')} | {relative('planned', 'seconds')} |")
    return lines


def markdown(rows: list[dict]) -> list[str]:
    lines = ["# A needle step's Newton tolerances: cost and what they leave", "",
             f"Generated by `python benchmarks/solver_tolerance.py` ({common.machine_note()}).", "",
             "Tolerance: the force residual over the needle force |r| / |f_needle| and the track's largest "
             "distance from the needle over the needle radius |g| / R at which a needle step's Newton stops "
             f"(`solver.needle_residual_tolerance` / `solver.needle_constraint_tolerance`); {label(REFERENCE)} "
             "is the reference, as good as converged. Unplanned: the insertion with the centre fixed; its exit "
             "point's distance from the reference's. Planned: `plan --no-compare --no-verify`'s planned run in "
             f"process, its exported centres' largest difference from those at {label(PAIRS[0])}, wall time "
             f"median of {REPEATS} (pairs alternating). Replay h/2: the shipped trajectory "
             "(sample_runs/SCENE/trajectory.csv) on the plan's verification model; its exit error is the "
             "verified exit error. Deform: the load steps' `solver.residual_tolerance` (full Newton, unchanged "
             "by the needle's tolerances); the probes' largest displacement difference from the reference's.", "",
             "| scene | run | tolerance | exit error (mm) | exit from the reference (mm) | centres from the first (mm) "
             "| Newton iterations | seconds |", "|---|---|---|---|---|---|---|---|"]
    for row in rows:
        if row["run"] == "coarse grid":
            continue
        lines.append(table_row(row))
    return lines + summary_lines(rows) + coarse_markdown([row for row in rows if row["run"] == "coarse grid"])


def value(row, key, digits=".2e"):
    return "" if key not in row or row[key] != row[key] else format(row[key], digits)


def table_row(row: dict) -> str:
    if "failure" in row:
        return f"| {row['scene']} | {row['run']} | {row['tolerance']} | failed: {row['failure']} | | | | |"
    distance = row.get("exit_from_reference_mm", row.get("probes_from_reference_mm"))
    return (f"| {row['scene']} | {row['run']} | {row['tolerance']} | {value(row, 'exit_error_mm', '.6g')} | "
            f"{'' if distance is None else format(distance, '.2e')} | {value(row, 'centers_from_first_mm')} | "
            f"{row['newton_iterations']} | {value(row, 'seconds', '.3f')} |")


def coarse_markdown(rows: list[dict]) -> list[str]:
    return ["", "## The couplings on coarse uniform particles", "",
            "sh12_100x100 on uniform particles (no graded needle zone), unplanned, with each coupling: "
            "where several needle points share a particle spacing the point coupling's constraint rows "
            "become nearly dependent and a residual leaves a larger error in the exit. The distance is "
            "from the tightest run that finished.", "",
            "| scene | run | tolerance | exit error (mm) | exit from the reference (mm) | centres from the first (mm) "
            "| Newton iterations | seconds |", "|---|---|---|---|---|---|---|---|"] + [table_row(row) for row in rows]


def main() -> None:
    logging.getLogger("stitchplan").setLevel(logging.ERROR)
    rows = []
    for name in needle_scenes():
        rows += unplanned(name)
        rows += planned(name)
        rows += replayed(name)
        print(name, rows[-1], flush=True)
    rows += coarse_grids()
    rows += deform_probes()
    levels = [row for name in NEEDLE20 for row in refinement(name)]
    header = ["scene", "run", "tolerance", "exit_error_mm", "exit_from_reference_mm", "centers_from_first_mm",
              "probes_from_reference_mm", "newton_iterations", "seconds", "failure"]
    common.write_csv(common.results_path("solver_tolerance.csv"), header,
                     [[row.get(key, "") for key in header] for row in rows])
    common.write_report("solver_tolerance.md", markdown(rows) + refinement_markdown(levels))


if __name__ == "__main__":
    common.command_line(__doc__)
    main()
