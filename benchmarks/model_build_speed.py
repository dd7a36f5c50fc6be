"""Shape functions, neighbour search and start-up, before and after: model builds,
single-point evaluations, whole unplanned runs and the commands' start-up.

Every command builds a model: RK shape functions and their gradients at every quadrature
point (rk_shape_pairs), and on a tissue with holes or notches the visibility test of each
(point, particle) pair (PolygonDomain.blocked). Needle steps evaluate the shape functions at
single points (tip tracking, each new needle point). On graded particles the neighbour
search of many points looks within each support group's own support (ParticleSearch), not
the largest. This script times, for SCENES (the
shipped configs at their default spacing or at `--spacing` S, the verification model of
`plan` being half the default):

- the model build (a fresh PreparedTissue's model: particles, quadrature, shape functions,
  essential boundary);
- the shape functions and gradients at one point near the needle's entry (median of
  POINT_CALLS calls, as tip tracking asks for them);
- for the cases marked so, the whole unplanned run (`run_insertion` on a fresh
  PreparedTissue: build, K0's factor and every needle step) and its exit error, which both
  codes must give alike (to round-off);

at BASELINE (the code before the change, extracted with `git archive`) and now, each in a
fresh process with PYTHONPATH at the code, alternating REPEATS times; medians over the
processes. Then the start-up, alternating STARTUP_REPEATS times, medians: a process that
imports what `simulate` and `plan` import before their run (IMPORTS, with the bytecode
cache on), and which of scipy.spatial and scipy.optimize it loaded; and the whole commands
of COMMANDS. Writes benchmarks/results/model_build_speed.md and prints the tables. About 6
minutes. Run from the repository root:  python benchmarks/model_build_speed.py [BASELINE]
"""

from __future__ import annotations

import os

# single-threaded BLAS, as the `stitchplan` command sets it
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import json  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import _common as common  # noqa: E402

BASELINE = "89f6881"
# (config, --spacing or None for the default, whether to time the whole unplanned run)
SCENES = (("sh12_100x100", None, True), ("sh12_100x100", 1.776, False), ("needle20_entry18", None, True),
          ("hole_near_stitch", None, True), ("wound_closure", None, True), ("wound_closure", 0.75, False))
REPEATS = int(os.environ.get("MODEL_BUILD_REPEATS", 3))  # processes per code and case
POINT_CALLS = 200
SOLVES = 20
STARTUP_REPEATS = 9
IMPORTS = "import stitchplan.cli.commands, stitchplan.planning.verification, stitchplan.needle.insertion"
COMMANDS = (("simulate", "sh12_100x100", ("--no-estimate",)),
            ("plan", "sh12_100x100", ("--no-compare", "--no-verify")),
            ("plan", "needle20_entry30", ("--no-compare", "--no-verify")))


def worker(scene: str, spacing: float | None, run: bool) -> dict:
    """One process's measurements of the code on sys.path (run as `--worker`)."""
    import logging
    import time

    import numpy as np

    from stitchplan.config import load_scenario, with_discretization
    PreparedTissue = common.prepared_tissue_class()
    from stitchplan.needle.geometry import scenario_needle
    from stitchplan.needle.insertion import run_insertion

    logging.disable(logging.WARNING)
    scenario = with_discretization(load_scenario(common.REPO_ROOT / "configs" / f"{scene}.yaml"), spacing=spacing)
    PreparedTissue(scenario).model  # imports and caches warm
    start = time.perf_counter()
    model = PreparedTissue(scenario).model
    build = time.perf_counter() - start
    geometry = scenario_needle(scenario)
    inward = geometry.center - geometry.entry
    point = (geometry.entry + 0.05 * inward)[None, :]  # a tip point just inside the entry
    coefficients = np.zeros((model.n_particles, 2))
    times = []
    for _ in range(POINT_CALLS):
        start = time.perf_counter()
        model.field_at(point, coefficients, gradients=True)
        times.append(time.perf_counter() - start)
    record = {"particles": model.n_particles, "quadrature_points": len(model.quadrature_points),
              "build_s": build, "point_ms": 1e3 * statistics.median(times)}
    record.update(factor_record(scenario))
    if run:
        start = time.perf_counter()
        result = run_insertion(scenario)
        record.update(run_s=time.perf_counter() - start, exit_error_mm=result.exit_error_mm)
    return record


def factor_record(scenario) -> dict:
    """K0 (PreparedTissue.stiffness_at_rest) and its factor by the installed backend
    (factorize) and by SuperLU: seconds to assemble and to factor, milliseconds per solve of
    one right-hand side (median of SOLVES)."""
    import numpy as np

    PreparedTissue = common.prepared_tissue_class()
    from stitchplan.tissue.factorization import SuperLUFactor, factorize

    tissue = PreparedTissue(scenario)
    tissue.model
    start = time.perf_counter()
    stiffness = tissue.stiffness_at_rest()
    record = {"k0_s": time.perf_counter() - start}
    rhs = np.ones(stiffness.shape[0])
    for key, make in (("factor", lambda: factorize(stiffness, symmetric_positive=True)),
                      ("superlu", lambda: SuperLUFactor(stiffness))):
        start = time.perf_counter()
        factor = make()
        record[f"{key}_s"] = time.perf_counter() - start
        times = []
        for _ in range(SOLVES):
            start = time.perf_counter()
            factor.solve(rhs)
            times.append(time.perf_counter() - start)
        record[f"{key}_solve_ms"] = 1e3 * statistics.median(times)
        record.setdefault("backend", factor.backend)
    return record


def measure(source: Path, scene: str, spacing: float | None, run: bool) -> dict:
    return common.worker_record(__file__, source, scene, str(spacing or ""), "1" if run else "")


def imports(source: Path) -> tuple[float, list[str]]:
    """One process of IMPORTS from the code in `source`: wall time (s), and which of
    scipy.spatial and scipy.optimize it loaded."""
    script = f"import sys; {IMPORTS}; print([m for m in ('scipy.spatial', 'scipy.optimize') if m in sys.modules])"
    start = time.perf_counter()
    output = subprocess.run([sys.executable, "-c", script], check=True, capture_output=True, text=True,
                            cwd=source, env=common.command_environment(PYTHONPATH=str(source)))
    return time.perf_counter() - start, json.loads(output.stdout.strip().replace("'", '"'))


def command(source: Path, folder: Path, name: str, scene: str, options: tuple[str, ...]) -> float:
    """One whole `stitchplan NAME configs/SCENE.yaml OPTIONS` process of the code in `source` (s)."""
    seconds, _ = common.scene_command(name, scene, [*options, "-q"], folder, source, PYTHONPATH=str(source))
    return seconds


def startup(before_source: Path, folder: Path) -> list[dict]:
    sources = {"before": before_source, "after": common.REPO_ROOT}
    samples: dict[str, dict[str, list]] = {label: {} for label in sources}
    for _ in range(STARTUP_REPEATS):
        for label, source in sources.items():
            seconds, loaded = imports(source)
            samples[label].setdefault("imports", []).append(seconds)
            samples[label]["loaded"] = loaded
            for name, scene, options in COMMANDS:
                key = " ".join([name, scene, *options])
                samples[label].setdefault(key, []).append(command(source, folder, name, scene, options))
    rows = []
    for key in samples["after"]:
        if key == "loaded":
            continue
        before, after = (statistics.median(samples[label][key]) for label in sources)
        rows.append({"what": "imports of simulate and plan" if key == "imports" else key,
                     "before_s": before, "after_s": after, "saved_s": before - after})
    rows[0]["before_loaded"] = ", ".join(samples["before"]["loaded"]) or "neither"
    rows[0]["after_loaded"] = ", ".join(samples["after"]["loaded"]) or "neither"
    return rows


def main(baseline: str) -> None:
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        before_source = common.extract_revision(baseline, Path(scratch), "stitchplan")
        for scene, spacing, run in SCENES:
            samples = {"before": [], "after": []}
            for _ in range(REPEATS):
                samples["before"].append(measure(before_source, scene, spacing, run))
                samples["after"].append(measure(common.REPO_ROOT, scene, spacing, run))
            after = samples["after"][0]
            row = {"scene": scene + (f" --spacing {spacing:g}" if spacing else ""), "particles": after["particles"],
                   "quadrature_points": after["quadrature_points"]}
            for label, records in samples.items():
                row[f"{label}_backend"] = records[0]["backend"]
            for key in ("build_s", "point_ms", "k0_s", "factor_s", "factor_solve_ms") + (("run_s",) if run else ()):
                for label, records in samples.items():
                    row[f"{label}_{key}"] = statistics.median(r[key] for r in records)
                row[f"{key}_ratio"] = row[f"before_{key}"] / row[f"after_{key}"]
            for key in ("superlu_s", "superlu_solve_ms"):
                row[key] = statistics.median(r[key] for r in samples["after"])
            if run:
                errors = [r["exit_error_mm"] for r in samples["before"] + samples["after"]]
                row["exit_error_mm"], row["exit_error_spread_mm"] = after["exit_error_mm"], max(errors) - min(errors)
            rows.append(row)
            print(row, flush=True)
        with tempfile.TemporaryDirectory() as commands:
            startup_rows = startup(before_source, Path(commands))
        for row in startup_rows:
            print(row, flush=True)
    write(rows, startup_rows, baseline)


COLUMNS = [("scene", "scene"), ("particles", "particles"), ("quadrature_points", "quadrature points"),
           ("before_build_s", "build before (s)"), ("after_build_s", "build after (s)"),
           ("build_s_ratio", "build speed-up"), ("before_point_ms", "one point before (ms)"),
           ("after_point_ms", "one point after (ms)"), ("point_ms_ratio", "one point speed-up"),
           ("before_run_s", "unplanned run before (s)"), ("after_run_s", "unplanned run after (s)"),
           ("run_s_ratio", "run speed-up"), ("exit_error_mm", "exit error (mm)"),
           ("exit_error_spread_mm", "exit error spread (mm)")]
FACTOR_COLUMNS = [("scene", "scene"), ("before_k0_s", "K0 before (s)"), ("after_k0_s", "K0 after (s)"),
                  ("k0_s_ratio", "K0 speed-up"), ("before_backend", "backend before"),
                  ("before_factor_s", "factor before (s)"), ("before_factor_solve_ms", "solve before (ms)"),
                  ("after_backend", "backend after"), ("after_factor_s", "factor after (s)"),
                  ("after_factor_solve_ms", "solve after (ms)"), ("factor_s_ratio", "factor speed-up"),
                  ("superlu_s", "SuperLU factor (s)"), ("superlu_solve_ms", "SuperLU solve (ms)")]


STARTUP_COLUMNS = [("what", "process"), ("before_s", "before (s)"), ("after_s", "after (s)"),
                   ("saved_s", "saved (s)"), ("before_loaded", "loaded before"), ("after_loaded", "loaded after")]


def write(rows: list[dict], startup_rows: list[dict], baseline: str) -> None:
    table = common.markdown_table([title for _, title in COLUMNS],
                                  [[row.get(key, "-") for key, _ in COLUMNS] for row in rows])
    factor_table = common.markdown_table([title for _, title in FACTOR_COLUMNS],
                                         [[row.get(key, "-") for key, _ in FACTOR_COLUMNS] for row in rows])
    startup_table = common.markdown_table([title for _, title in STARTUP_COLUMNS],
                                          [[row.get(key, "") for key, _ in STARTUP_COLUMNS] for row in startup_rows])
    print(table)
    print(factor_table)
    print(startup_table)
    text = f"""# Shape functions, neighbour search and start-up: model builds, single points, unplanned runs, commands

`python benchmarks/model_build_speed.py` (baseline {baseline}, extracted with `git archive`;
each case in fresh processes with PYTHONPATH at the code, before and after alternated:
median of {REPEATS} processes). *build*: a fresh model (particles, quadrature, RK shape
functions and gradients at every quadrature point, essential boundary); *one point*: shape
functions and gradients at one point near the entry, as tip tracking evaluates them (median
of {POINT_CALLS} calls); *unplanned run*: `run_insertion` on a fresh model (build, K0's
factor, every needle step). The change: the RK shape functions of many points in about
half the time (tissue/shape_functions.py: each pair's offset computed once, the support
groups' sorted runs merged by a stable sort, the sums over a point's pairs as one sparse
product, the 3 x 3 moment matrices inverted by cofactors with a 1-norm condition estimate
and their eigenvalues computed only where that estimate is in doubt; tissue/kernel.py:
products instead of powers); K0 from the isotropic tangent at rest, one product of the
(nq x 2n) direction gradients (tissue/assembly.py stiffness_at_rest); and the `fast`
extra's CHOLMOD from cvxopt's wheel, which carries OpenBLAS, instead of cholespy's, which
carries the reference BLAS (tissue/factorization.py). Both codes ran with their own `fast`
extra installed (cholespy and cvxopt). (Earlier changes this script measured, with their
baselines: the git history of this file.) "exit error spread": the largest difference of
the exit error over all runs of both codes (round-off).

{table}

## K0 and its factor

*K0*: assembling the tangent at rest (PreparedTissue.stiffness_at_rest); *factor*: its factor
by `factorize` with the installed backend, and the median of {SOLVES} solves of one right-hand
side; *SuperLU*: the same with scipy's SuperLU (the path without the `fast` extra), now.

{factor_table}

## Start-up

Process wall times, before and after alternated, median of {STARTUP_REPEATS}, Python's
bytecode cache on. *imports of simulate and plan*: `python -c "{IMPORTS}"`, what those
commands import before their run (the interpreter's own start included). The whole
commands run with their defaults otherwise (the `plan` rows include the helper process's
estimate run at 2h).

{startup_table}

{common.machine_note()}
"""
    common.results_path("model_build_speed.md").write_text(text)


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        print(json.dumps(worker(sys.argv[2], float(sys.argv[3]) if sys.argv[3] else None, bool(sys.argv[4]))))
    else:
        if {"-h", "--help"} & set(sys.argv[1:]):
            common.command_line(__doc__)  # prints the docstring and exits
        main(sys.argv[1] if len(sys.argv) > 1 else BASELINE)
