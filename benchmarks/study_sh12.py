"""Speed against accuracy on the shipped SH 1/2 scene (configs/sh12_100x100.yaml).

The study of `stitchplan study` (stitchplan.study.sweep) with the sweep below: a uniform family
over the particle spacing, a graded family (needle spacing within 1.5 needle radii of the
needle centre, 4x coarser away from it), and seven method families on the graded
particles, each differing from it in one choice (tip tracking, linear solver, dilation x2,
quadrature order, basis order, needle step), at least 8 configurations each. Every run is
compared with the finest one (graded, 0.5 mm at the needle). The auto discretization is
asked for an accuracy of 0.05 mm and its choice run and compared too; then the auto choice
and the cheapest uniform run of equal accuracy are timed twice more (medians), for the
speed-up.

Writes benchmarks/results/study_sh12/{study.csv, speed_accuracy.png, study.md} and prints
the tables. About 10 minutes. Run from the repository root:

    python benchmarks/study_sh12.py
"""

from __future__ import annotations

import os

# single-threaded BLAS, as the `stitchplan` command sets it (and for both codes compared):
# the numerics are sparse and small-dense, and BLAS threads only compete on 2 cores
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import statistics
import sys
import time
from dataclasses import replace

import _common as common
from stitchplan.config.scenario import load_scenario
from stitchplan.config.study import parse_study
from stitchplan.io.files import write_text
from stitchplan.io.study_reports import write_study_outputs
from stitchplan.needle.insertion import run_insertion
from stitchplan.study.sweep import run_study

SCENARIO = common.REPO_ROOT / "configs" / "sh12_100x100.yaml"
OUT = common.RESULTS_DIR / "study_sh12"
ACCURACY = 0.05  # mm, asked of the auto discretization
METHOD_SPACINGS = [3.0, 2.6, 2.3, 2.0, 1.75, 1.5, 1.3, 1.1]  # mm at the needle, graded x4
STUDY = {  # the scenario's `study:` block, as a user would write it
    "families": [
        {"name": "uniform", "spacing": [6.0, 5.0, 4.5, 4.0, 3.5, 3.0, 2.5, 2.0, 1.5]},
        {"name": "graded x4", "grading": 4, "spacing": [3.0, 2.5, 2.0, 1.75, 1.5, 1.25, 1.0, 0.75]},
        {"name": "graded x4, tip tracking auto", "grading": 4, "tip_tracking": "auto", "spacing": METHOD_SPACINGS},
        {"name": "graded x4, MINRES", "grading": 4, "linear_solver": "minres", "spacing": METHOD_SPACINGS},
        {"name": "graded x4, dilation 1.5", "grading": 4, "dilation": 1.5, "spacing": METHOD_SPACINGS},
        {"name": "graded x4, dilation 3", "grading": 4, "dilation": 3.0, "spacing": METHOD_SPACINGS},
        {"name": "graded x4, quadrature 3", "grading": 4, "quadrature_order": 3, "spacing": METHOD_SPACINGS},
        {"name": "graded x4, quadratic (dilation 2.5)", "grading": 4, "basis_order": 2, "dilation": 2.5,
         "spacing": METHOD_SPACINGS},
        {"name": "graded x4, step 0.04", "grading": 4, "step": 0.04, "spacing": METHOD_SPACINGS},
    ],
    "reference": {"grading": 4, "spacing": 0.5},
}


def median_wall(scenario, first: float, repeats: int = 2) -> float:
    return statistics.median([first] + [run_insertion(scenario).wall_seconds for _ in range(repeats)])


def main() -> None:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--smoke", metavar="DIR", help="two coarse runs per family, written to DIR "
                        "(checks the script in a minute; not the benchmark)")
    options = parser.parse_args()
    global OUT
    study_block = STUDY
    if options.smoke:
        OUT = common.Path(options.smoke)
        study_block = {"families": [{**f, "spacing": [4.0, 3.0] if f["name"] == "uniform" else [3.0, 2.5]}
                                    for f in STUDY["families"][:3]], "reference": {"grading": 4, "spacing": 1.5}}
    base = load_scenario(SCENARIO)
    scenario = replace(base, study=parse_study(study_block),
                       discretization=replace(base.discretization, accuracy=ACCURACY))
    start = time.perf_counter()

    def report(run):
        state = f"{run.wall_seconds:6.2f} s" if run.ok else f"FAILED: {run.reason[:90]}"
        print(f"{time.perf_counter() - start:7.1f} s  {run.label:45s} {run.particles:6d} particles  {state}",
              flush=True)

    study = run_study(scenario, on_run=report)
    OUT.mkdir(parents=True, exist_ok=True)
    write_study_outputs(study, OUT)

    runs = [r for r in study.runs if r is not study.reference]
    header = ["family", "h at needle (mm)", "particles", "wall (s)", "deviation (mm)",
              "spatial exit dev. (mm)", "exit error (mm)"]
    front = sorted(study.front, key=lambda r: r.wall_seconds)
    pareto_rows = [[r.family, r.spacing, r.particles, r.wall_seconds, r.deviation_mm,
                    r.deviations["exit_deviation_mm"], r.result.exit_error_mm] for r in front]
    families = []
    for family in dict.fromkeys(r.family for r in runs):
        members = [r for r in runs if r.family == family]
        ok = [r for r in members if r.ok]
        best = min(ok, key=lambda r: r.deviation_mm) if ok else None
        meeting = [r for r in ok if r.deviation_mm <= ACCURACY]
        cheapest = min(meeting, key=lambda r: r.wall_seconds) if meeting else None
        families.append([family, len(members), len(members) - len(ok),
                         best.deviation_mm if best else float("nan"),
                         f"{cheapest.spacing:g} mm, {cheapest.wall_seconds:.2f} s" if cheapest else "none",
                         "; ".join(sorted({r.reason[:120] + ("..." if len(r.reason) > 120 else "")
                                           for r in members if not r.ok})) or "-"])

    lines = [f"# Speed against accuracy: {scenario.name}", "",
             f"Regenerate: `python benchmarks/study_sh12.py` ({common.machine_note()}; "
             f"{time.perf_counter() - start:.0f} s in all).", "",
             f"Reference (finest run): {study.reference.label}, {study.reference.particles} particles, "
             f"{study.reference.wall_seconds:.1f} s, exit error {study.reference.result.exit_error_mm:.4f} mm. "
             "`deviation` is the largest of the spatial achieved-exit, material achieved-exit and "
             "exit-error-vector deviations from it, the spatial one only for a run of as many needle "
             "steps (stitchplan.study.sweep).", "",
             "## Pareto front", "", common.markdown_table(header, pareto_rows), "",
             "## Families", "",
             common.markdown_table(["family", "runs", "failed", "best deviation (mm)",
                                    f"cheapest run within {ACCURACY} mm", "failures"], families), ""]

    choice = study.auto
    if choice is not None:
        auto_run = next(r for r in runs if r.family == "auto")
        uniform_equal = [r for r in runs if r.family == "uniform" and r.ok and r.deviation_mm <= auto_run.deviation_mm]
        uniform_target = [r for r in runs if r.family == "uniform" and r.ok and r.deviation_mm <= ACCURACY]
        auto_wall = median_wall(choice.scenario, auto_run.wall_seconds)
        lines += ["## Auto discretization", "", choice.message, "",
                  f"- target {ACCURACY} mm; estimate {choice.estimate_mm:.4f} mm; deviation from the finest run "
                  f"{auto_run.deviation_mm:.4f} mm ({'meets' if auto_run.deviation_mm <= ACCURACY else 'misses'} the target)",
                  f"- chosen run: {auto_run.particles} particles, {auto_wall:.2f} s (median of 3); "
                  f"selection {choice.selection_seconds:.1f} s over {len(choice.trials)} runs (the chosen one included)"]
        for name, pool in (("equal accuracy (deviation <= the auto run's)", uniform_equal),
                           (f"the same target ({ACCURACY} mm)", uniform_target)):
            if pool:
                uniform = min(pool, key=lambda r: r.wall_seconds)
                uniform_wall = median_wall(uniform.scenario, uniform.wall_seconds)
                lines.append(f"- cheapest uniform run meeting {name}: spacing {uniform.spacing:g} mm, "
                             f"{uniform.particles} particles, deviation {uniform.deviation_mm:.4f} mm, "
                             f"{uniform_wall:.2f} s (median of 3): auto is {uniform_wall / auto_wall:.1f}x faster")
            else:
                lines.append(f"- no uniform run meets {name}")
        lines.append("")
    lines += [f"note: {note}" for note in study.notes]
    text = "\n".join(lines) + "\n"
    write_text(OUT / "study.md", text)
    print(text)
    print(f"wrote {OUT / 'study.csv'}, {OUT / 'speed_accuracy.png'}, {OUT / 'study.md'}", file=sys.stderr)


if __name__ == "__main__":
    main()
