"""Speed against accuracy: `stitchplan study` sweeps discretization and method choices
around a needle-insertion scenario and measures, for each run, its wall time and how far
its exit point lies from the finest run's.

A study is a set of *families*. A family fixes the method choices (particle grading,
dilation, quadrature order, basis order, needle step, tip tracking, linear solver) and is
swept over a list of spacings at the needle (the particle spacing of a uniform family, the
`needle_spacing` of a graded one). One more run, the *reference*, is the finest of the
study; every other run is compared with it.

The exit point is compared three ways (mm):

- `exit_deviation_mm`: the achieved exit, spatial (`achieved_exit_def`);
- `material_exit_deviation_mm`: the achieved exit, reference (`achieved_exit`): where in
  the tissue the needle comes out;
- `exit_error_deviation_mm`: the exit-error vector `achieved_exit_def - desired_exit_def`.

`deviation_mm` is the largest of the three. The first alone can mislead: with the needle
centre fixed, the spatial exit lies on the rigid needle circle where it meets the deformed
edge, so it barely moves with the discretization (on the SH 1/2 scene ~0.02 mm between
5 and 1.5 mm spacing) while the other two move by 0.1 mm and more.

Scenario block (optional; every key optional, unknown keys refused):

    study:
      spacing: [6.0, 4.0, 3.0, 2.0]         # mm at the needle, swept in every family
      families:                             # default: see default_families()
        - {name: uniform}
        - {name: graded, grading: 4}        # coarse spacing = 4 x the needle spacing
        - {name: minres, linear_solver: minres}
        - {name: dilation 1.5, dilation: 1.5, spacing: [4.0, 3.0]}
      reference: {grading: 4, spacing: 1.0} # the finest run (one spacing)
      repeats: 1                            # timing: median of this many runs
"""

from __future__ import annotations

import logging
import math
import statistics
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from ..config import Scenario, ScenarioError, parse_discretization
from ..config.study import StudyFamily, StudySpec

log = logging.getLogger(__name__)


# what a run may fail with: the project's exceptions (ScenarioError and SingularMomentMatrix
# are ValueErrors, InsertionFailure and SolverDivergence RuntimeErrors, InvertedMaterial and
# TipTrackingJump ArithmeticErrors) and the linear algebra's (LinAlgError, SuperLU's
# RuntimeError on a singular factor), plus running out of memory on a too fine model
RUN_FAILURES = (ValueError, ArithmeticError, RuntimeError, MemoryError)

COLUMNS = ("family", "label", "spacing_mm", "coarse_spacing_mm", "grading", "dilation",
           "quadrature_order", "basis_order", "step_rad", "tip_tracking", "linear_solver", "particles",
           "wall_seconds", "cpu_seconds", "steps", "newton_iterations", "minres_iterations", "events",
           "exit_error_mm", "achieved_exit_def_x", "achieved_exit_def_y", "achieved_exit_x",
           "achieved_exit_y", "exit_deviation_mm", "material_exit_deviation_mm",
           "exit_error_deviation_mm", "deviation_mm", "pareto", "status", "reason")


# --- defaults --------------------------------------------------------------------------


def default_spacings(scenario: Scenario, quick: bool = False) -> tuple[float, ...]:
    """Around the scenario's spacing at the needle h (its spacing on a uniform grid): from
    1.6 h down to 0.7 h (quick: 1.4 h and h)."""
    d = scenario.discretization
    h = d.needle_spacing if d.needle_spacing is not None else d.spacing
    factors = (1.4, 1.0) if quick else (1.6, 1.35, 1.15, 1.0, 0.85, 0.7)
    return tuple(round(h * f, 3) for f in factors)


def default_families(scenario: Scenario, quick: bool = False) -> tuple[StudyFamily, ...]:
    """One family per method choice, each differing from the scenario in one thing."""
    base = [StudyFamily("uniform"), StudyFamily("graded x4", grading=4)]
    if quick:
        return tuple(base)
    d, needle = scenario.discretization, scenario.needle
    other_tracking = "auto" if needle.tip_tracking == "levenberg-marquardt" else "levenberg-marquardt"
    other_solver = "minres" if needle.linear_solver == "direct" else "direct"
    return tuple(base + [
        StudyFamily(f"tip tracking {other_tracking}", tip_tracking=other_tracking),
        StudyFamily(f"linear solver {other_solver}", linear_solver=other_solver),
        StudyFamily("dilation 1.5", dilation=1.5) if d.dilation != 1.5 else StudyFamily("dilation 2.5", dilation=2.5),
        StudyFamily(f"quadrature {d.quadrature_order + 1}", quadrature_order=d.quadrature_order + 1),
        # a quadratic basis needs the support to reach past two neighbours at the edges
        StudyFamily("basis order 2, dilation 2.5", basis_order=2, dilation=max(d.dilation, 2.5))
        if d.basis_order == 1 else StudyFamily("basis order 1", basis_order=1),
        StudyFamily(f"step {needle.step / 2:g}", step=needle.step / 2),
    ])


def default_reference(spacings: tuple[float, ...]) -> StudyFamily:
    """Graded x4 at half the finest swept spacing: finer at the needle than any run."""
    return StudyFamily("reference", spacing=(round(min(spacings) / 2, 4),), grading=4)


# --- one run ---------------------------------------------------------------------------


def configure(scenario: Scenario, family: StudyFamily, spacing: float) -> Scenario:
    """The scenario with the family's choices at `spacing` (mm at the needle)."""
    values = asdict(scenario.discretization)
    values.update(accuracy=None, needle_spacing=None, needle_refinement=None)
    for key in ("dilation", "quadrature_order", "basis_order", "cells_per_spacing"):
        if getattr(family, key) is not None:
            values[key] = getattr(family, key)
    if family.grading is not None:
        values.update(spacing=spacing * family.grading, needle_spacing=spacing)
    else:
        values["spacing"] = spacing
    needle = scenario.needle
    needle = replace(needle, **{k: getattr(family, k) for k in ("step", "tip_tracking", "linear_solver")
                                if getattr(family, k) is not None})
    return replace(scenario, discretization=parse_discretization(values, f"study {family.name!r}"),
                   needle=needle)


@dataclass
class StudyRun:
    family: str
    label: str
    scenario: Scenario
    spacing: float  # at the needle, mm
    particles: int = 0
    wall_seconds: float = math.nan
    cpu_seconds: float = math.nan
    status: str = "ok"
    reason: str = ""
    result: Any = None  # InsertionResult when ok
    deviations: dict[str, float] = field(default_factory=dict)
    pareto: bool = False

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def deviation_mm(self) -> float:
        return self.deviations.get("deviation_mm", math.nan)

    def row(self) -> list:
        d, needle = self.scenario.discretization, self.scenario.needle
        r = self.result
        grading = round(d.spacing / d.needle_spacing) if d.needle_spacing else 1
        steps = r.steps if r is not None else []
        nan2 = (math.nan, math.nan)
        return [
            self.family, self.label, self.spacing, d.spacing, grading, d.dilation, d.quadrature_order,
            d.basis_order, needle.step, needle.tip_tracking, needle.linear_solver, self.particles,
            self.wall_seconds, self.cpu_seconds, len(steps), sum(s.newton_iterations for s in steps),
            sum(s.minres_iterations for s in steps), len(r.events) if r is not None else 0,
            r.exit_error_mm if r is not None else math.nan,
            *(r.achieved_exit_def if r is not None else nan2), *(r.achieved_exit if r is not None else nan2),
            *(self.deviations.get(k, math.nan) for k in ("exit_deviation_mm", "material_exit_deviation_mm",
                                                          "exit_error_deviation_mm", "deviation_mm")),
            str(self.pareto).lower(), self.status, self.reason,
        ]


def count_particles(scenario: Scenario) -> int:
    """Particles of the scenario's discretization, without building shape functions."""
    import numpy as np

    from ..needle.geometry import needle_zone
    from ..tissue.model import graded_particles, grid_particles

    d = scenario.discretization
    zone = needle_zone(scenario)
    if zone is not None:
        return len(graded_particles(scenario.tissue.size, d.spacing, d.needle_spacing,
                                    np.asarray(zone[0]), zone[1]).particles)
    return len(grid_particles(scenario.tissue.size, d.spacing)[0])


def run_once(run: StudyRun, repeats: int = 1) -> StudyRun:
    """Run the insertion (`repeats` times for the timing median); a failure is recorded
    with its reason, never raised."""
    from ..needle.insertion import run_insertion

    try:
        run.particles = count_particles(run.scenario)
    except RUN_FAILURES:
        run.particles = 0
    walls, cpus = [], []
    for _ in range(repeats):
        start, cpu = time.perf_counter(), time.process_time()
        try:
            result = run_insertion(run.scenario)
        except RUN_FAILURES as error:
            run.status, run.reason = "failed", f"{type(error).__name__}: {error}"
            run.wall_seconds = time.perf_counter() - start
            run.cpu_seconds = time.process_time() - cpu
            run.result = None
            log.info("study run %s failed: %s", run.label, run.reason)
            return run
        walls.append(result.wall_seconds)
        cpus.append(time.process_time() - cpu)
        run.result = result
    run.particles = run.result.model.n_particles
    run.wall_seconds, run.cpu_seconds = statistics.median(walls), statistics.median(cpus)
    return run


def exit_deviations(result, reference) -> dict[str, float]:
    """Distances (mm) between the exit points of two insertions; see the module docstring."""
    import numpy as np

    spatial = float(np.linalg.norm(result.achieved_exit_def - reference.achieved_exit_def))
    material = float(np.linalg.norm(result.achieved_exit - reference.achieved_exit))
    error = float(np.linalg.norm((result.achieved_exit_def - result.desired_exit_def)
                                 - (reference.achieved_exit_def - reference.desired_exit_def)))
    return {"exit_deviation_mm": spatial, "material_exit_deviation_mm": material,
            "exit_error_deviation_mm": error, "deviation_mm": max(spatial, material, error)}


def pareto_front(runs: list[StudyRun]) -> list[StudyRun]:
    """Runs no other run beats in both wall time and deviation (successful, compared runs)."""
    candidates = sorted((r for r in runs if r.ok and math.isfinite(r.deviation_mm)),
                        key=lambda r: (r.wall_seconds, r.deviation_mm))
    front, best = [], math.inf
    for run in candidates:
        if run.deviation_mm < best:
            front.append(run)
            best = run.deviation_mm
    return front


# --- the study -------------------------------------------------------------------------


@dataclass
class StudyResult:
    scenario: Scenario
    runs: list[StudyRun]  # every run, the reference last
    reference: StudyRun
    notes: list[str] = field(default_factory=list)
    auto: Any = None  # stitchplan.auto.AutoChoice when the scenario asks for an accuracy

    @property
    def front(self) -> list[StudyRun]:
        return [r for r in self.runs if r.pareto]

    @property
    def failed(self) -> list[StudyRun]:
        return [r for r in self.runs if not r.ok]


def plan_runs(scenario: Scenario, quick: bool = False) -> tuple[list[StudyRun], StudyRun, int]:
    """The runs of the study (families x spacings) and the reference run, not yet run."""
    if scenario.needle is None:
        raise ScenarioError("needle: missing, required by study (it sweeps the needle insertion)")
    spec = scenario.study or StudySpec()
    if quick:
        spacings = default_spacings(scenario, quick=True)
        families = default_families(scenario, quick=True)
        reference = default_reference(spacings)
    else:
        spacings = spec.spacing or default_spacings(scenario)
        families = spec.families or default_families(scenario)
        reference = spec.reference or default_reference(
            tuple(s for f in families for s in (f.spacing or spacings)))
    runs = []
    for family in families:
        for spacing in family.spacing or spacings:
            label = f"{family.name} h={spacing:g}"
            runs.append(StudyRun(family.name, label, configure(scenario, family, spacing), spacing))
    spacing = reference.spacing[0]
    reference_run = StudyRun("reference", f"reference h={spacing:g}", configure(scenario, reference, spacing),
                             spacing)
    return runs, reference_run, spec.repeats


def run_study(scenario: Scenario, quick: bool = False,
              on_run: Callable[[StudyRun], None] | None = None,
              auto: bool | None = None) -> StudyResult:
    """Run every configuration of the study, then the reference; compare each with it.

    With an `accuracy` in the scenario's discretization (or auto=True) the auto
    discretization is chosen too and its run added as family "auto".
    """
    runs, reference, repeats = plan_runs(scenario, quick)
    notes: list[str] = []
    for run in runs:
        run_once(run, repeats)
        if on_run is not None:
            on_run(run)
    run_once(reference, 1)
    if on_run is not None:
        on_run(reference)
    chosen = None
    wants_auto = scenario.discretization.accuracy is not None if auto is None else auto
    if wants_auto:
        from .auto import choose_discretization

        accuracy = scenario.discretization.accuracy or 0.05
        chosen = choose_discretization(scenario, accuracy)
        auto_run = StudyRun("auto", f"auto (accuracy {accuracy:g} mm)", chosen.scenario, chosen.needle_spacing)
        auto_run.result, auto_run.particles = chosen.result, chosen.result.model.n_particles
        auto_run.wall_seconds, auto_run.cpu_seconds = chosen.result.wall_seconds, chosen.cpu_seconds
        runs.append(auto_run)
        notes.append(chosen.message)
        if on_run is not None:
            on_run(auto_run)
    compared = reference
    if not reference.ok:
        finest = [r for r in runs if r.ok]
        if not finest:
            raise ScenarioError(f"study: every run failed (reference: {reference.reason})")
        compared = min(finest, key=lambda r: (r.spacing, -r.particles))
        notes.append(f"the reference run failed ({reference.reason}); deviations are measured from "
                     f"the finest successful run, {compared.label}")
    for run in runs + [reference]:
        if run.ok:
            run.deviations = exit_deviations(run.result, compared.result)
    for run in pareto_front([r for r in runs if r is not compared]):
        run.pareto = True
    failed = [r for r in runs + [reference] if not r.ok]
    if failed:
        notes.append(f"{len(failed)} of {len(runs) + 1} runs failed; their reasons are in study.csv")
    return StudyResult(scenario, runs + [reference], compared, notes, chosen)


def study_size(scenario: Scenario, quick: bool = False) -> int:
    runs, _, _ = plan_runs(scenario, quick)
    return len(runs) + 1 + (1 if scenario.discretization.accuracy is not None else 0)


# --- writers ---------------------------------------------------------------------------


def write_study_outputs(result: StudyResult, out: Path) -> tuple[Path, Path]:
    """out/study.csv (one row per run) and out/speed_accuracy.png."""
    from ..io.files import write_csv
    from ..io.plots import plot_speed_accuracy

    out = Path(out)
    csv_path, png_path = out / "study.csv", out / "speed_accuracy.png"
    write_csv(csv_path, COLUMNS, [run.row() for run in result.runs])
    plot_speed_accuracy(png_path, result)
    return csv_path, png_path


def summary_lines(result: StudyResult) -> list[str]:
    ok = [r for r in result.runs if r.ok]
    lines = [f"study: {len(result.runs)} runs ({len(ok)} ok, {len(result.runs) - len(ok)} failed); "
             f"reference {result.reference.label}: {result.reference.particles} particles, "
             f"{result.reference.wall_seconds:.2f} s"]
    for run in sorted(result.front, key=lambda r: r.wall_seconds):
        lines.append(f"  Pareto: {run.label:32s} {run.particles:6d} particles {run.wall_seconds:7.2f} s  "
                     f"deviation {run.deviation_mm:.4f} mm")
    return lines + [f"note: {note}" for note in result.notes]
