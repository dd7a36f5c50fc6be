"""Shape functions and visibility, before and after: model builds, single-point evaluations
and whole unplanned runs.

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
processes. Writes benchmarks/results/model_build_speed.md and prints the table. About 4
minutes. Run from the repository root:  python benchmarks/model_build_speed.py [BASELINE]
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

BASELINE = "78828c7"
# (config, --spacing or None for the default, whether to time the whole unplanned run)
SCENES = (("sh12_100x100", None, True), ("sh12_100x100", 1.776, False), ("needle20_entry18", None, True),
          ("hole_near_stitch", None, True), ("wound_closure", None, True), ("wound_closure", 0.75, False))
REPEATS = int(os.environ.get("MODEL_BUILD_REPEATS", 3))  # processes per code and case
POINT_CALLS = 200


def worker(scene: str, spacing: float | None, run: bool) -> dict:
    """One process's measurements of the code on sys.path (run as `--worker`)."""
    import logging
    import time

    import numpy as np

    from stitchplan.config import load_scenario, with_discretization
    from stitchplan.needle.equilibrium import PreparedTissue
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
    if run:
        start = time.perf_counter()
        result = run_insertion(scenario)
        record.update(run_s=time.perf_counter() - start, exit_error_mm=result.exit_error_mm)
    return record


def measure(source: Path, scene: str, spacing: float | None, run: bool) -> dict:
    return common.worker_record(__file__, source, scene, str(spacing or ""), "1" if run else "")


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
            for key in ("build_s", "point_ms") + (("run_s",) if run else ()):
                for label, records in samples.items():
                    row[f"{label}_{key}"] = statistics.median(r[key] for r in records)
                row[f"{key}_ratio"] = row[f"before_{key}"] / row[f"after_{key}"]
            if run:
                errors = [r["exit_error_mm"] for r in samples["before"] + samples["after"]]
                row["exit_error_mm"], row["exit_error_spread_mm"] = after["exit_error_mm"], max(errors) - min(errors)
            rows.append(row)
            print(row, flush=True)
    write(rows, baseline)


COLUMNS = [("scene", "scene"), ("particles", "particles"), ("quadrature_points", "quadrature points"),
           ("before_build_s", "build before (s)"), ("after_build_s", "build after (s)"),
           ("build_s_ratio", "build speed-up"), ("before_point_ms", "one point before (ms)"),
           ("after_point_ms", "one point after (ms)"), ("point_ms_ratio", "one point speed-up"),
           ("before_run_s", "unplanned run before (s)"), ("after_run_s", "unplanned run after (s)"),
           ("run_s_ratio", "run speed-up"), ("exit_error_mm", "exit error (mm)"),
           ("exit_error_spread_mm", "exit error spread (mm)")]


def write(rows: list[dict], baseline: str) -> None:
    table = common.markdown_table([title for _, title in COLUMNS],
                                  [[row.get(key, "-") for key, _ in COLUMNS] for row in rows])
    print(table)
    text = f"""# Shape functions and visibility: model builds, single points, unplanned runs

`python benchmarks/model_build_speed.py` (baseline {baseline}, extracted with `git archive`;
each case in fresh processes with PYTHONPATH at the code, before and after alternated:
median of {REPEATS} processes). *build*: a fresh model (particles, quadrature, RK shape
functions and gradients at every quadrature point, essential boundary); *one point*: shape
functions and gradients at one point near the entry, as tip tracking evaluates them (median
of {POINT_CALLS} calls); *unplanned run*: `run_insertion` on a fresh model (build, K0's
factor, every needle step). The change: the moment matrix summed from its upper triangle,
its gradient from D M + M D^T (the basis gradient is a constant map D of the basis) plus
one new sum per direction; the visibility test of a tissue with a hole or a notch (hole_near_stitch,
wound_closure) tests every boundary edge at once and measures the boundary distance only
for pair midpoints outside the tissue; the neighbours of many points are searched per group
of similar kernel supports within the group's support (on graded particles the largest
support reaches hundreds of fine particles that do not reach back). "exit error spread": the largest difference of the
exit error over all runs of both codes (round-off).

{table}

{common.machine_note()}
"""
    common.results_path("model_build_speed.md").write_text(text)


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        print(json.dumps(worker(sys.argv[2], float(sys.argv[3]) if sys.argv[3] else None, bool(sys.argv[4]))))
    else:
        main(sys.argv[1] if len(sys.argv) > 1 else BASELINE)
