"""What `simulate --condition-numbers` costs: the resource guard's CONDITION_SECONDS and
CONDITION_MATRICES (stitchplan/resources/costs.py).

Each step of such a run forms the saddle matrix [[K + H, G], [G^T, 0]] densely, with K0^-1,
its Cholesky factor and the preconditioned matrix (needle.saddle_point.condition_numbers),
and takes the eigenvalues of two of them: time ~ unknowns^3 and memory ~ unknowns^2 with
unknowns = 2 x particles. Each case runs the unplanned insertion on configs/sh12_100x100.yaml
at a spacing, at a needle step of STEP rad (a few steps, so that the finer models finish in
minutes), in a fresh process twice: with condition numbers, timing each call, and without,
for the peak memory (ru_maxrss) the dense matrices add.

Fitted: seconds per call = c x (2 x particles / 1000)^p (least squares in log-log), and the
dense matrices' peak, (peak with - peak without) / (8 bytes x (2 x particles)^2): how many
unknowns^2 float arrays are alive at once at its peak.

Writes benchmarks/results/condition_costs.{md,csv} and prints them.
Run from the repository root:  python benchmarks/condition_costs.py
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import json
import subprocess
import sys

import _common as common
import numpy as np

NEEDLE = common.REPO_ROOT / "configs" / "sh12_100x100.yaml"
SPACINGS = (12.0, 10.0, 7.104, 5.5, 4.5)
STEP = 0.4  # rad: 8 needle steps on SH 1/2

CHILD = r"""
import json, resource, sys, time
from dataclasses import replace
from stitchplan.config import load_scenario, with_discretization
from stitchplan.needle import equilibrium
from stitchplan.needle.insertion import run_insertion
from stitchplan.resources.costs import estimate
path, spacing, step, condition = sys.argv[1], float(sys.argv[2]), float(sys.argv[3]), sys.argv[4] == "1"
scenario = with_discretization(load_scenario(path), spacing=spacing)
scenario = replace(scenario, needle=replace(scenario.needle, step=step))
calls = []
original = equilibrium.NeedleInsertion.condition_numbers

def timed(self):
    start = time.perf_counter()
    values = original(self)
    calls.append(time.perf_counter() - start)
    return values

equilibrium.NeedleInsertion.condition_numbers = timed
try:
    guard = estimate(scenario, "insertion", condition_numbers=condition)
except TypeError:  # a guard that does not count them
    guard = estimate(scenario, "insertion")
result = run_insertion(scenario, condition_numbers=condition)
print(json.dumps({"particles": result.model.n_particles, "free": result.model.n_free, "calls": calls,
                  "wall": result.wall_seconds, "steps": len(result.steps),
                  "guard_seconds": guard.seconds, "guard_memory": guard.memory_bytes,
                  "peak_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024.0}))
"""


def run_case(spacing: float, condition: bool) -> dict:
    args = [sys.executable, "-c", CHILD, str(NEEDLE), str(spacing), str(STEP), "1" if condition else "0"]
    done = subprocess.run(args, capture_output=True, text=True, cwd=common.REPO_ROOT, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    rows = []
    for spacing in SPACINGS:
        plain, dense = run_case(spacing, False), run_case(spacing, True)
        unknowns = 2.0 * dense["particles"]
        per_call = float(np.median(dense["calls"]))
        added = dense["peak_bytes"] - plain["peak_bytes"]
        rows.append({"spacing": spacing, "particles": dense["particles"], "unknowns": unknowns,
                     "free": 2 * dense["free"], "steps": dense["steps"], "per_call": per_call,
                     "wall_plain": plain["wall"], "wall_dense": dense["wall"], "added": added,
                     "matrices": added / (8.0 * unknowns ** 2), "guard_seconds": dense["guard_seconds"],
                     "guard_memory": dense["guard_memory"], "peak": dense["peak_bytes"]})
        print(rows[-1], flush=True)
    x = np.log([r["unknowns"] / 1000.0 for r in rows])
    exponent, log_c = np.polyfit(x, np.log([r["per_call"] for r in rows]), 1)
    # the constant at the cubic the dense algorithms have, from the two largest cases (the
    # smaller ones are dominated by the sparse solve and Python's overhead)
    cubic = [r["per_call"] / (r["unknowns"] / 1000.0) ** 3 for r in rows[-2:]]
    header = ["spacing (mm)", "particles", "unknowns (2 x particles)", "free unknowns", "needle steps",
              "s per call (median)", "s per call / (unknowns/1000)^3", "wall without (s)", "wall with (s)",
              "guard now: time ratio", "peak added (MB)", "unknowns^2 arrays at the peak",
              "guard now: memory ratio"]
    table = [[r["spacing"], r["particles"], r["unknowns"], r["free"], r["steps"], r["per_call"],
              r["per_call"] / (r["unknowns"] / 1000.0) ** 3, r["wall_plain"], r["wall_dense"],
              r["wall_dense"] / r["guard_seconds"], r["added"] / 1e6, r["matrices"],
              r["peak"] / r["guard_memory"]] for r in rows]
    common.write_csv(common.results_path("condition_costs.csv"), header, table)
    lines = [
        "# What --condition-numbers costs: the resource guard's dense condition-number constants",
        "",
        (f"Generated by `python benchmarks/condition_costs.py` ({common.machine_note()}). "
        f"configs/sh12_100x100.yaml at needle steps of {STEP} rad; each case runs in its own process with "
        "and without condition numbers. 'Wall with' includes the condition numbers; the guard's "
        "ratios compare each run with its estimate (resources.costs.estimate with condition_numbers)."),
        "",
        common.markdown_table(header, table),
        "",
        f"Fitted over all cases: seconds per call = {np.exp(log_c):.3g} x (unknowns / 1000)^{exponent:.3g}.",
        (f"At the cubic of the dense algorithms, from the two largest cases: {min(cubic):.3g}-{max(cubic):.3g} s "
        "x (unknowns / 1000)^3."),
        ("Peak memory added by the dense matrices: "
        f"{min(r['matrices'] for r in rows[-2:]):.3g}-{max(r['matrices'] for r in rows[-2:]):.3g} arrays of "
        "unknowns^2 floats (the two largest cases)."),
    ]
    common.write_report("condition_costs.md", lines)


if __name__ == "__main__":
    common.command_line(__doc__)
    main()
