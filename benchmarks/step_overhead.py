"""Fixed per-step overhead of a needle insertion on small models, before and after.

A needle step on a small model (the 20 mm needle scenes, ~600 particles; the exit-error
estimate's replay of configs/sh12_100x100.yaml at twice the spacing, 7.104 mm, ~280
particles) costs a few milliseconds, most of it fixed Python and scipy.sparse overhead
(growing the track's sparse rows, the residual's small products, shape functions at a few
points) rather than arithmetic. This script times, on a prebuilt PreparedTissue (model and
K0's factor made before the clock starts):

- the unplanned run (`run_insertion`) and
- the planned run (`run_plan(..., compare=False)`),

for SCENES, at BASELINE (the code before the overhead work, extracted with `git archive`
into a temporary folder) and now, each in a subprocess with PYTHONPATH set to the code,
alternating REPEATS times so both see the same machine load. Each process makes one untimed
run, then times RUNS_PER_PROCESS of each kind and reports their medians. Per case: median
over the processes of the run's wall time, of the median needle-step wall time
(NeedleStep.wall_seconds, tracking and solves), and the Newton iterations; and the largest
difference of the exit error over all runs of both codes (they must agree to round-off).

Writes benchmarks/results/step_overhead.md and prints the table. About 2 minutes.
Run from the repository root:  python benchmarks/step_overhead.py [BASELINE]
"""

from __future__ import annotations

import os

# single-threaded BLAS, as the `stitchplan` command sets it
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import json  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import _common as common  # noqa: E402

BASELINE = "b0ea93e"
SCENES = (("needle20_entry30", None), ("needle20_entry18", None), ("sh12_100x100", 7.104))
REPEATS = int(os.environ.get("STEP_OVERHEAD_REPEATS", 5))  # processes per code and case
RUNS_PER_PROCESS = 3  # timed runs in each process (their median is the process's sample)


def worker(scene: str, spacing: float | None) -> dict:
    """One process's measurements of the code on sys.path (run as `--worker`)."""
    import logging
    import time

    import numpy as np

    from stitchplan.config import load_scenario, with_discretization
    from stitchplan.needle.insertion import run_insertion
    from stitchplan.planning.planner import run_plan

    logging.disable(logging.WARNING)
    scenario = with_discretization(load_scenario(common.REPO_ROOT / "configs" / f"{scene}.yaml"), spacing=spacing)
    tissue = common.prepared_tissue_class()(scenario)
    tissue.model, tissue.factor_at_rest()  # built before the clock starts
    record = {"particles": int(tissue.model.n_particles)}
    run_insertion(scenario, tissue=tissue)  # first calls (imports, caches) out of the timings
    runs = {"unplanned": lambda: run_insertion(scenario, tissue=tissue),
            "planned": lambda: run_plan(scenario, compare=False, tissue=tissue).planned}
    for kind, run in runs.items():
        seconds, step_ms = [], []
        for _ in range(RUNS_PER_PROCESS):
            start = time.perf_counter()
            result = run()
            seconds.append(time.perf_counter() - start)
            step_ms.append(1e3 * float(np.median([step.wall_seconds for step in result.steps])))
        record[kind] = {
            "wall_s": float(np.median(seconds)),
            "step_ms": float(np.median(step_ms)),
            "steps": len(result.steps),
            "newton": int(sum(step.newton_iterations for step in result.steps)),
            "exit_error_mm": float(result.exit_error_mm),
            "exit_point": [float(v) for v in result.achieved_exit],
        }
    return record


def measure(source: Path, scene: str, spacing: float | None) -> dict:
    return common.worker_record(__file__, source, scene, str(spacing or ""))


def main(baseline: str) -> None:
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        before_source = common.extract_revision(baseline, Path(scratch), "stitchplan")
        for scene, spacing in SCENES:
            samples = {"before": [], "after": []}
            for _ in range(REPEATS):
                samples["before"].append(measure(before_source, scene, spacing))
                samples["after"].append(measure(common.REPO_ROOT, scene, spacing))
            for kind in ("unplanned", "planned"):
                row = {"scene": scene + (f" --spacing {spacing}" if spacing else ""), "run": kind,
                       "particles": samples["after"][0]["particles"],
                       "steps": samples["after"][0][kind]["steps"]}
                for label, records in samples.items():
                    runs = [r[kind] for r in records]
                    row[f"{label}_wall_s"] = statistics.median(r["wall_s"] for r in runs)
                    row[f"{label}_step_ms"] = statistics.median(r["step_ms"] for r in runs)
                    row[f"{label}_newton"] = statistics.median(r["newton"] for r in runs)
                row["step_change_pct"] = 100.0 * (row["after_step_ms"] / row["before_step_ms"] - 1.0)
                row["wall_change_pct"] = 100.0 * (row["after_wall_s"] / row["before_wall_s"] - 1.0)
                errors = [r[kind]["exit_error_mm"] for r in samples["before"] + samples["after"]]
                row["exit_error_mm"] = samples["after"][0][kind]["exit_error_mm"]
                row["exit_error_spread_mm"] = max(errors) - min(errors)
                rows.append(row)
    write(rows, baseline)


COLUMNS = [("scene", "scene"), ("run", "run"), ("particles", "particles"), ("steps", "steps"),
           ("before_wall_s", "wall before (s)"), ("after_wall_s", "wall after (s)"),
           ("wall_change_pct", "wall change (%)"), ("before_step_ms", "step before (ms)"),
           ("after_step_ms", "step after (ms)"), ("step_change_pct", "step change (%)"),
           ("before_newton", "Newton before"), ("after_newton", "Newton after"),
           ("exit_error_mm", "exit error (mm)"), ("exit_error_spread_mm", "exit error spread (mm)")]


def write(rows: list[dict], baseline: str) -> None:
    table = common.markdown_table([title for _, title in COLUMNS], [[row[key] for key, _ in COLUMNS] for row in rows])
    print(table)
    text = f"""# Fixed per-step overhead of a needle insertion on small models

`python benchmarks/step_overhead.py` (baseline {baseline}, extracted with `git archive`; each
case in fresh processes with PYTHONPATH at the code, before and after alternated: median of
{REPEATS} processes, each the median of {RUNS_PER_PROCESS} runs after an untimed one). The
model and K0's factor are built before the clock starts (a prebuilt `PreparedTissue`);
"wall" is the whole run (`run_insertion`, or `run_plan(..., compare=False)` with every
planner pass), "step" the median needle step's wall time (tip tracking and equilibrium
solves), "Newton" the Newton iterations over the run's steps. "exit error spread" is the
largest difference of the exit error over all runs of both codes: the change does not move
the results beyond round-off.

{table}

{common.machine_note()}
"""
    common.results_path("step_overhead.md").write_text(text)


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        print(json.dumps(worker(sys.argv[2], float(sys.argv[3]) if sys.argv[3] else None)))
    else:
        if {"-h", "--help"} & set(sys.argv[1:]):
            common.command_line(__doc__)  # prints the docstring and exits
        main(sys.argv[1] if len(sys.argv) > 1 else BASELINE)
