"""What runs cost: the constants of the resource guard (stitchplan/resources/costs.py).

Each case runs in a fresh Python process, so that its peak resident memory (ru_maxrss) is
its own: deform on configs/slab_edge_load.yaml at several spacings (and one wider kernel,
dilation 3), and the unplanned insertion (stitchplan.needle.insertion.run_insertion) on
configs/sh12_100x100.yaml at its default and half spacing, and at needle steps far below its
0.08 rad (what a run keeps of its steps, resources.costs._step_memory, then dominates its
memory). For each case the guard's own estimate of the model (resources.model_size.model_size:
particles, neighbours, quadrature points) and of the run (resources.costs.estimate: its
memory, and the part of it the needle steps keep) is printed next to the measured wall time
of the run (the result's wall_seconds) and peak memory.

Fitted (least squares in log-log over the dilation-2 cases at the scenarios' needle steps):

  seconds / step = c_kind x (particles / 1000)^p x (neighbours / 16)^2 x (points / 4)
  memory - baseline - kept steps = m x (particles / 1000)^q x (neighbours / 16) x (points / 4)

(kept steps: the guard's _step_memory, derived from the arrays the code keeps, not fitted)
and the guard's prediction is compared with each measured case (ratio), the dilation-3 and
small-step cases included (they check the neighbour scaling and the steps' memory, which the
fit did not see). From the small-step cases alone, the growth of a needle step's time with
the steps before it (STEP_TIME_DOUBLES_AT: a step k taking a + b k, a / b in steps).

Writes benchmarks/results/resource_costs.{md,csv} and prints them.
Run from the repository root:  python benchmarks/resource_costs.py
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402

import numpy as np  # noqa: E402

import _common as common  # noqa: E402

SLAB = common.REPO_ROOT / "configs" / "slab_edge_load.yaml"
NEEDLE = common.REPO_ROOT / "configs" / "sh12_100x100.yaml"
# (kind, scenario, spacing or None for the default, dilation, needle step (rad) or None for the scenario's)
CASES = (
    ("deform", SLAB, 5.0, 2.0, None),
    ("deform", SLAB, 2.5, 2.0, None),
    ("deform", SLAB, 1.5, 2.0, None),
    ("deform", SLAB, 1.0, 2.0, None),
    ("deform", SLAB, 2.5, 3.0, None),
    ("insertion", NEEDLE, None, 2.0, None),
    ("insertion", NEEDLE, 1.786, 2.0, None),
    ("insertion", NEEDLE, None, 2.0, 0.01),
    ("insertion", NEEDLE, None, 2.0, 0.0025),
)

CHILD = r"""
import json, resource, sys, time
from dataclasses import replace
from stitchplan.config import load_scenario, with_discretization
from stitchplan.resources.costs import estimate
from stitchplan.resources.model_size import model_size
kind, path, spacing, dilation, step = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4]), sys.argv[5]
scenario = with_discretization(load_scenario(path), spacing=None if spacing == "none" else float(spacing),
                               dilation=dilation)
if step != "none":
    scenario = replace(scenario, needle=replace(scenario.needle, step=float(step)))
size = model_size(scenario)
row = {"particles_estimated": size.particles, "neighbours": size.neighbours,
       "points_per_particle": size.points_per_particle}
if kind != "baseline":
    guard = estimate(scenario, kind)
    row.update(guard_memory=guard.memory_bytes, guard_seconds=guard.seconds, step_memory=guard.step_memory,
               guard_steps=guard.steps)
if kind == "baseline":
    from stitchplan.tissue.deform import run_deform
    from stitchplan.needle import insertion
    row.update(wall=0.0, steps=1, particles=0)
elif kind == "deform":
    from stitchplan.tissue.deform import run_deform
    result = run_deform(scenario)
    row.update(wall=result.wall_seconds, steps=scenario.load_steps, particles=result.model.n_particles)
else:
    from stitchplan.needle.insertion import run_insertion
    result = run_insertion(scenario)
    row.update(wall=result.wall_seconds, steps=len(result.steps) + 1, particles=result.model.n_particles)
row["peak_bytes"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024.0
print(json.dumps(row))
"""


def run_case(kind: str, path, spacing, dilation: float, step=None) -> dict:
    args = [sys.executable, "-c", CHILD, kind, str(path), "none" if spacing is None else str(spacing), str(dilation),
            "none" if step is None else str(step)]
    done = subprocess.run(args, capture_output=True, text=True, cwd=common.REPO_ROOT, check=False)
    if done.returncode != 0:
        return {"failed": done.stderr.strip().splitlines()[-1] if done.stderr.strip() else "failed"}
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    from stitchplan.resources import costs

    baseline = run_case("baseline", SLAB, 5.0, 2.0)["peak_bytes"]
    rows = []
    for kind, path, spacing, dilation, step in CASES:
        result = run_case(kind, path, spacing, dilation, step)
        result.update(kind=kind, scene=path.stem, spacing=spacing or "default", dilation=dilation,
                      needle_step=step or ("" if kind == "deform" else "scenario's"))
        rows.append(result)
        print(result, flush=True)
    ok = [r for r in rows if "failed" not in r]
    # the time and the tissue's memory are fitted at the scenarios' needle steps: at small steps a
    # step's dense products and what the run keeps of its steps grow with the steps taken
    fit = [r for r in ok if r["dilation"] == 2.0 and r["needle_step"] in ("", "scenario's")]

    def relative(r):
        return (r["particles"] / costs.REFERENCE_PARTICLES,
                min(r["neighbours"], r["particles"]) / costs.REFERENCE_NEIGHBOURS,
                r["points_per_particle"] / costs.REFERENCE_POINTS_PER_PARTICLE)

    # time: log(t / (steps n^2 q)) = log c_kind + p log P, one c per kind, a common p
    design, target = [], []
    for r in fit:
        p, n, q = relative(r)
        design.append([np.log(p), r["kind"] == "deform", r["kind"] == "insertion"])
        target.append(np.log(r["wall"] / (r["steps"] * n ** 2 * q)))
    coefficients, *_ = np.linalg.lstsq(np.asarray(design, float), np.asarray(target), rcond=None)
    time_exponent = float(coefficients[0])
    per_step = {"deform": float(np.exp(coefficients[1])) / costs.REFERENCE_PARTICLES,
                "insertion": float(np.exp(coefficients[2])) / costs.REFERENCE_PARTICLES}
    # memory above the baseline and the kept steps: log(m / (n q)) = log m0 + q log P
    x = [np.log(relative(r)[0]) for r in fit]
    y = [np.log(max(r["peak_bytes"] - baseline - r["step_memory"], 1e6) / (relative(r)[1] * relative(r)[2]))
         for r in fit]
    memory_exponent, log_m = np.polyfit(x, y, 1)
    per_particle = float(np.exp(log_m)) / costs.REFERENCE_PARTICLES
    # a needle step k taking a + b k: N steps take a N + b N^2 / 2; a / b from the small-step cases
    growing = [r for r in ok if r["kind"] == "insertion" and r["needle_step"] not in ("", "scenario's")]
    (a, b), *_ = np.linalg.lstsq(np.asarray([[r["steps"], r["steps"] ** 2 / 2.0] for r in growing], float),
                                 np.asarray([r["wall"] for r in growing]), rcond=None)
    doubles_at = float(a / b)

    header = ["kind", "scene", "spacing (mm)", "dilation", "needle step (rad)", "particles", "guard's count",
              "steps", "guard's steps", "wall (s)", "peak memory (MB)", "guard: kept steps (MB)", "fit: time (s)",
              "fit: memory (MB)", "time ratio", "memory ratio", "guard now: time ratio", "guard now: memory ratio"]
    table = []
    for r in rows:
        if "failed" in r:
            table.append([r["kind"], r["scene"], r["spacing"], r["dilation"], r["needle_step"],
                          "failed: " + r["failed"]] + [""] * (len(header) - 6))
            continue
        _, n, q = relative(r)
        p = r["particles_estimated"] / costs.REFERENCE_PARTICLES  # the guard predicts from its count
        predicted_time = per_step[r["kind"]] * costs.REFERENCE_PARTICLES * p ** time_exponent * n ** 2 * q * r["steps"]
        predicted_memory = (baseline + per_particle * costs.REFERENCE_PARTICLES * p ** memory_exponent * n * q
                            + r["step_memory"])
        # stitchplan/resources/costs.py as it is now: costs.estimate's time and memory (kept steps included)
        guard_time = r["guard_seconds"]
        table.append([r["kind"], r["scene"], r["spacing"], r["dilation"], r["needle_step"], r["particles"],
                      r["particles_estimated"], r["steps"], r["guard_steps"], r["wall"], r["peak_bytes"] / 1e6,
                      r["step_memory"] / 1e6, predicted_time, predicted_memory / 1e6, r["wall"] / predicted_time,
                      r["peak_bytes"] / predicted_memory, r["wall"] / guard_time, r["peak_bytes"] / r["guard_memory"]])
    common.write_csv(common.results_path("resource_costs.csv"), header, table)
    lines = [
        "# What runs cost: the resource guard's constants",
        "",
        f"Generated by `python benchmarks/resource_costs.py` ({common.machine_note()}). Each case "
        "runs in its own process; peak memory is its ru_maxrss. The machine is shared: wall "
        "times vary by tens of percent between runs.",
        "",
        common.markdown_table(header, table),
        "",
        f"Baseline (interpreter with stitchplan, numpy and scipy loaded): {baseline / 1e6:.0f} MB.",
        "",
        "Fitted over the dilation-2 cases at the scenarios' needle steps (time per step per reference "
        "particle, at 1000 particles, 16 neighbours, 4 quadrature points per particle; memory above the "
        "baseline and the guard's kept steps):",
        "",
        f"- SECONDS_PER_PARTICLE_STEP: deform {per_step['deform']:.3g} s, insertion {per_step['insertion']:.3g} s",
        f"- TIME_EXPONENT: {time_exponent:.3g}",
        f"- MEMORY_PER_PARTICLE: {per_particle:.3g} bytes, MEMORY_EXPONENT: {memory_exponent:.3g}",
        f"- BASE_MEMORY: {baseline:.3g} bytes",
        f"- STEP_TIME_DOUBLES_AT: {doubles_at:.3g} needle steps (a step k taking a + b k, a / b, from the "
        "cases in small needle steps: N steps take a N (1 + N / (2 a / b)))",
        "",
        "The guard's predictions use its own particle and step counts (resources.model_size.model_size and the "
        "undeformed circle's steps, made before anything is built); the fit uses the particles and "
        "steps the run had. 'Kept steps': what the guard estimates a needle run keeps of its steps "
        "until it ends (resources.costs._step_memory: the saddle-point solver's doubling buffers, the "
        "coupling's dense weights and the track's arrays of every step's state, the per-step "
        "displacements), part of both memory predictions. The ratios compare each measured case with "
        "the prediction (1 = exact); the dilation-3 case was not fitted and checks the "
        "(neighbours/16)^2 time and (neighbours/16) memory scaling, the small-step cases the kept "
        "steps (their time per step grows with the steps taken, which the fit, linear in the steps, does "
        "not follow; STEP_TIME_DOUBLES_AT is fitted on them alone). 'Guard now': the same ratios with "
        "resources.costs.estimate as it is, the growth of the steps' time included (a ratio below 1: "
        "the guard bounds the run's time or peak from above).",
    ]
    common.write_report("resource_costs.md", lines)


if __name__ == "__main__":
    common.command_line(__doc__)
    main()
