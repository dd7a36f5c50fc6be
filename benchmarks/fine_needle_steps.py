"""Needle runs in small steps, before and after: time, peak memory and the guard's estimate.

A needle run's constraint quadrature grows by a segment's Gauss points every step, so in
small steps its saddle-point solves grow with the steps taken: 2Q rows of E (the constraint
points' shape functions, both directions) against n unknowns of the tissue. Each step's
Schur complement S = B^T (E K^-1 E^T) B was formed from the kept E K^-1 E^T, (2Q)^2 floats,
in (2Q)^2 m operations, and each step's state kept its block and, dense, the coupling's W
and its partition of unity P, (Q, m) each. Now, once 2Q > n, S is formed from E K^-1 through
a sparse B (n operations for each of B's at most 4Q entries) and E K^-1 E^T is no longer
kept; the states keep W sparse and P not at all.

This script runs `stitchplan simulate configs/sh12_100x100.yaml` with `needle.step` set to
STEPS (a copy of the file), with the code at BASELINE (extracted with `git archive`) and
the working tree's, alternating REPEATS times, each in its own process: median wall time,
the largest peak resident memory of the command (its process's ru_maxrss), the guard's
memory and time estimate for the run (the working tree's resources.costs.estimate), and the
exit error now and its difference from the baseline's (round-off).

Writes benchmarks/results/fine_needle_steps.md and .csv and prints the table. About 5 minutes.
Run from the repository root:  python benchmarks/fine_needle_steps.py [BASELINE]
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
import yaml  # noqa: E402

BASELINE = "503d511"  # the code before: S always from E K^-1 E^T, W and P dense in every state
SCENE = "sh12_100x100"
STEPS = (0.08, 0.02, 0.01, 0.005, 0.0025)  # rad
REPEATS = 2

# `stitchplan ARGS` in a child process; prints the child's peak resident memory (kB) last
MEASURED = ("import resource, subprocess, sys; done = subprocess.run(sys.argv[1:]); "
            "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss); sys.exit(done.returncode)")


def measured_run(config: Path, code: Path, folder: Path) -> tuple[float, float, dict]:
    """`stitchplan simulate CONFIG` with the code in `code`: wall (s), peak memory (MiB), summary."""
    summary = folder / "summary.json"
    arguments = ["simulate", str(config), "--no-estimate", "--no-resource-check", "--summary", str(summary)]
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", MEASURED, *common.STITCHPLAN, *arguments], capture_output=True,
                          text=True, cwd=code, env=common.command_environment(PYTHONPATH=str(code)))
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(common.command_failure(arguments, code, done))
    return seconds, int(done.stdout.strip().splitlines()[-1]) / 1024.0, json.loads(summary.read_text())


def main() -> None:
    common.command_line(__doc__)
    baseline = sys.argv[1] if len(sys.argv) > 1 else BASELINE
    from stitchplan.config.scenario import load_scenario
    from stitchplan.resources.costs import estimate

    header = ["needle step (rad)", "steps", "before (s)", "now (s)", "ratio", "before peak (MiB)", "now peak (MiB)",
              "guard's memory (MiB)", "guard's time (s)", "exit error now (mm)", "now - before (mm)"]
    rows = []
    with tempfile.TemporaryDirectory() as extracted, tempfile.TemporaryDirectory() as scratch:
        code_before = common.extract_revision(baseline, Path(extracted))
        folder = Path(scratch)
        raw = yaml.safe_load((common.REPO_ROOT / "configs" / f"{SCENE}.yaml").read_text())
        for step in STEPS:
            raw["needle"]["step"] = step
            config = folder / f"{SCENE}_{step}.yaml"
            config.write_text(yaml.safe_dump(raw, sort_keys=False))
            before, now = [], []
            for _ in range(REPEATS):
                before.append(measured_run(config, code_before, folder))
                now.append(measured_run(config, common.REPO_ROOT, folder))
            guard = estimate(load_scenario(config), "insertion")
            wall_before, wall_now = (statistics.median(run[0] for run in runs) for runs in (before, now))
            rows.append([step, now[0][2]["steps"], wall_before, wall_now, wall_now / wall_before,
                         max(run[1] for run in before), max(run[1] for run in now), guard.memory_bytes / 2**20,
                         guard.seconds, now[0][2]["exit_error_mm"],
                         now[0][2]["exit_error_mm"] - before[0][2]["exit_error_mm"]])
            print(*(common.fmt(value) for value in rows[-1]), flush=True)
    common.write_results("fine_needle_steps", header, rows, [
        "# Needle runs in small steps: before and after the Schur complement from E K^-1",
        "",
        f"Generated by `python benchmarks/fine_needle_steps.py` ({common.machine_note()}). "
        f"`stitchplan simulate configs/{SCENE}.yaml` with `needle.step` set to each row's, the code at "
        f"{baseline} (before) and the working tree's (now), alternating {REPEATS} times, each in its own "
        "process: median wall time, the largest peak resident memory (ru_maxrss), the guard's estimate "
        "of the run (resources.costs.estimate of the working tree) and the exit error each reports. "
        "The machine is shared: wall times vary by tens of percent between runs."])


if __name__ == "__main__":
    main()
