"""Speed against accuracy: `stitchplan study` sweeps discretization and method choices
around a needle-insertion scenario and measures, for each run, its wall time and how far
its exit point lies from the finest run's.

A study is a set of *families*. A family fixes the method choices (particle grading,
dilation, quadrature order, basis order, needle step, tip tracking, linear solver) and is
swept over a list of spacings at the needle (the particle spacing of a uniform family, the
`needle_spacing` of a graded one). One more run, the *reference*, is the finest of the
study (in spacing, and in the needle step where a family takes a smaller one than the
scenario); every other run is compared with it.

The exit point is compared three ways (mm):

- `exit_deviation_mm`: the achieved exit, spatial (`achieved_exit_def`);
- `material_exit_deviation_mm`: the achieved exit, reference (`achieved_exit`): where in
  the tissue the needle comes out;
- `exit_error_deviation_mm`: the exit-error vector `achieved_exit_def - desired_exit_def`.

`deviation_mm` is the largest of the three (of the last two when the run took another
number of needle steps than the reference: it then ends in another needle state, and its
spatial exit deviation measures that step). No one of them alone will do: with the needle
centre fixed, the spatial exit lies on the rigid needle circle where it meets the deformed
edge, and it may move less with the discretization than the other two or more (README,
Speed against accuracy).

Scenario block (optional; every key optional, unknown keys refused):

    study:
      spacing: [6.0, 4.0, 3.0, 2.0]         # mm at the needle, swept in every family
      families:                             # default: see default_families()
        - {name: uniform}
        - {name: graded, grading: 4}        # coarse spacing = 4 x the needle spacing
        - {name: minres, linear_solver: minres}
        - {name: dilation 1.5, dilation: 1.5, spacing: [4.0, 3.0]}
      reference: {grading: 4, spacing: 1.0} # the finest run (one spacing)
      repeats: 1                            # timing: median of this many runs (the reference: one)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

from ..config import Scenario
from ..config.fields import MAX_QUADRATURE_ORDER
from ..config.study import StudyFamily, StudySpec
from ..errors import InputError, NumericalFailure
from ..parallel.executor import Executor, run_all
from .auto import AutoChoice, choose_discretization
from ..planning.verification import exit_deviations
from .runner import REFUSED, InsertionRun, run_timed

# the study.csv and speed_accuracy.png writers: stitchplan.io.study_reports

DEFAULT_ACCURACY = 0.05  # mm, asked of the auto discretization when the scenario gives none
# a family's choices the resource guard may refuse, naming the study field that set them
GUARDED_CHOICES = ("dilation", "quadrature_order", "cells_per_spacing", "step")


# --- defaults --------------------------------------------------------------------------


def default_spacings(scenario: Scenario, quick: bool = False) -> tuple[float, ...]:
    """Around the scenario's spacing at the needle h (its spacing on a uniform grid): from
    1.6 h down to 0.7 h (quick: 1.4 h and h)."""
    d = scenario.discretization
    h = d.needle_spacing if d.needle_spacing is not None else d.spacing
    factors = (1.4, 1.0) if quick else (1.6, 1.35, 1.15, 1.0, 0.85, 0.7)
    return _rounded(tuple(h * f for f in factors), 3)


def default_families(scenario: Scenario, quick: bool = False) -> tuple[StudyFamily, ...]:
    """One family per method choice, each differing from the scenario in one thing."""
    base = [StudyFamily("uniform"), StudyFamily("graded x4", grading=4)]
    if quick:
        return tuple(base)
    d, needle = scenario.discretization, scenario.needle
    other_tracking = "auto" if needle.tip_tracking == "levenberg-marquardt" else "levenberg-marquardt"
    other_solver = "minres" if needle.linear_solver == "direct" else "direct"
    other_order = d.quadrature_order + 1 if d.quadrature_order < MAX_QUADRATURE_ORDER else d.quadrature_order - 1
    return tuple(base + [
        StudyFamily(f"tip tracking {other_tracking}", tip_tracking=other_tracking),
        StudyFamily(f"linear solver {other_solver}", linear_solver=other_solver),
        StudyFamily("dilation 1.5", dilation=1.5) if d.dilation != 1.5 else StudyFamily("dilation 2.5", dilation=2.5),
        # one more Gauss point a direction, one fewer where the scenario's is the largest allowed
        StudyFamily(f"quadrature {other_order}", quadrature_order=other_order),
        # a quadratic basis needs the support to reach past two neighbours at the edges
        StudyFamily("basis order 2, dilation 2.5", basis_order=2, dilation=max(d.dilation, 2.5))
        if d.basis_order == 1 else StudyFamily("basis order 1", basis_order=1),
        StudyFamily(f"step {needle.step / 2:g}", step=needle.step / 2),
    ])


def default_reference(spacings: tuple[float, ...]) -> StudyFamily:
    """Graded x4 at half the finest swept spacing: finer at the needle than any run (plan_runs
    gives it the sweep's smallest needle step)."""
    finest = min(spacings)
    # half of the smallest float is 0: then the finest itself, which plan_runs refuses
    return StudyFamily("reference", spacing=_rounded((finest / 2 or finest, finest), 4)[:1], grading=4)


def _rounded(spacings: tuple[float, ...], decimals: int) -> tuple[float, ...]:
    """The spacings to `decimals` decimals for readable labels, with more where fewer would
    make one 0 or two alike (a spacing of 1e-4 mm halved to 0.0001 mm, not below it)."""
    while True:
        rounded = tuple(round(s, decimals) for s in spacings)
        if all(rounded) and len(set(rounded)) == len(set(spacings)):
            return rounded
        if decimals > 330:  # past the smallest float: as they are
            return spacings
        decimals += 1


# --- the runs --------------------------------------------------------------------------


def configure(scenario: Scenario, family: StudyFamily, spacing: float) -> Scenario:
    """The scenario with the family's choices at `spacing` (mm at the needle): graded
    particles (coarse spacing `grading` x spacing) or uniform ones, never an accuracy."""

    def chosen(keys: tuple[str, ...]) -> dict:
        return {key: getattr(family, key) for key in keys if getattr(family, key) is not None}

    changes = chosen(("dilation", "quadrature_order", "basis_order", "cells_per_spacing"))
    if family.grading is not None:
        changes.update(spacing=spacing * family.grading, needle_spacing=spacing)
    else:
        changes.update(spacing=spacing, needle_spacing=None)
    discretization = scenario.discretization.replaced(
        path=f"study {family.name!r}", accuracy=None, needle_refinement=None, **changes)
    needle = replace(scenario.needle, **chosen(("step", "tip_tracking", "linear_solver")))
    return replace(scenario, discretization=discretization, needle=needle)


@dataclass
class StudyRun(InsertionRun):
    """A run of the study and how far its exit point lies from the reference's."""

    deviations: dict[str, float] = field(default_factory=dict)  # exit_deviations(), mm
    pareto: bool = False
    source: str = ""  # what set the run's spacing (`study.families[1].spacing`), for refusals
    # the fields that set its other choices ({"dilation": "study.families[1].dilation"}), for
    # refusals: those it leaves to the scenario are the scenario's own
    fields: dict[str, str] = field(default_factory=dict)

    @property
    def deviation_mm(self) -> float:
        return self.deviations.get("deviation_mm", math.nan)


def pareto_front(runs: list[StudyRun]) -> list[StudyRun]:
    """Runs no other run beats in both wall time and `deviation_mm` (successful, compared
    runs): the study's one front, flagged `pareto` and shown as such in study.csv,
    study.json and both panels of speed_accuracy.png."""
    candidates = sorted((r for r in runs if r.ok and math.isfinite(r.deviation_mm)),
                        key=lambda r: (r.wall_seconds, r.deviation_mm))
    front, best = [], math.inf
    for run in candidates:
        if run.deviation_mm < best:
            front.append(run)
            best = run.deviation_mm
    return front


def plan_runs(scenario: Scenario, quick: bool = False) -> tuple[list[StudyRun], StudyRun, int]:
    """The runs of the study (families x spacings), the reference run, not yet run, and
    the number of timing repeats."""
    if scenario.needle is None:
        raise InputError("needle: missing, required by study (it sweeps the needle insertion)")
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
    def source(k: int, family) -> str:
        if quick:
            return "the --quick sweep's spacings"
        if spec.families and family.spacing:
            return f"study.families[{k}].spacing"
        return "study.spacing" if spec.spacing else "the study's default spacings"

    def fields(k: int, family) -> dict[str, str]:
        given = f"study.families[{k}]" if spec.families and not quick else None
        return {key: f"{given}.{key}" if given else f"{key} of the study's default family {family.name!r}"
                for key in GUARDED_CHOICES if getattr(family, key) is not None}

    runs = [StudyRun(family.name, f"{family.name} h={spacing:g} mm", configure(scenario, family, spacing), spacing,
                     source=source(k, family), fields=fields(k, family))
            for k, family in enumerate(families) for spacing in family.spacing or spacings]
    reference_fields = {key: f"study.reference.{key}" for key in GUARDED_CHOICES
                        if getattr(reference, key) is not None} if spec.reference and not quick else {}
    # the finest run in the needle step too: a family with a smaller step than the scenario's
    # would otherwise be finer in time than the run it is compared with
    finest_step = min(family.step or scenario.needle.step for family in families)
    if reference.step is None and finest_step < scenario.needle.step:
        reference = replace(reference, step=finest_step)
        finest_family = min(range(len(families)), key=lambda k: families[k].step or math.inf)
        reference_fields["step"] = fields(finest_family, families[finest_family])["step"]
    if reference.step is not None and reference.step > finest_step:  # the finest in time too
        raise InputError(f"study.reference.step: got {reference.step:g} rad, expected at most the finest step of "
                         f"the sweep, {finest_step:g} rad (the runs' deviations are measured from the reference)")
    spacing = reference.spacing[0]
    finest = min(run.spacing for run in runs)
    named = "study.reference.spacing" if spec.reference and not quick else "the study's default reference spacing"
    if spacing >= finest:  # every deviation is measured from the reference: it must be the finest
        raise InputError(f"{named}: got {spacing:g} mm, expected less than the finest "
                         f"spacing of the sweep, {finest:g} mm (the runs' deviations are measured from "
                         "the reference)")
    reference_run = StudyRun("reference", f"reference h={spacing:g} mm", configure(scenario, reference, spacing),
                             spacing, source=named, fields=reference_fields)
    return runs, reference_run, spec.repeats


def study_size(scenario: Scenario, quick: bool = False) -> int:
    """How many runs run_study reports through on_run (for a progress bar)."""
    runs, _, _ = plan_runs(scenario, quick)
    return len(runs) + 1 + (1 if scenario.discretization.accuracy is not None else 0)


# --- the study -------------------------------------------------------------------------


@dataclass
class StudyResult:
    scenario: Scenario
    runs: list[StudyRun]  # every run, the reference last
    reference: StudyRun  # the run the others are compared with (the finest that succeeded)
    notes: list[str] = field(default_factory=list)
    auto: AutoChoice | None = None  # when the scenario asks for an accuracy
    # where the runs ran (Executor.where): their wall times compete for the cores there
    executor: str = "in-process"

    @property
    def front(self) -> list[StudyRun]:
        return [r for r in self.runs if r.pareto]

    @property
    def failed(self) -> list[StudyRun]:
        return [r for r in self.runs if not r.ok]


def auto_run(choice: AutoChoice) -> StudyRun:
    """The auto discretization's chosen run as a run of the study (family "auto")."""
    return StudyRun("auto", f"auto (accuracy {choice.accuracy:g} mm)", choice.scenario, choice.needle_spacing,
                    particles=choice.result.model.n_particles, wall_seconds=choice.result.wall_seconds,
                    cpu_seconds=choice.cpu_seconds, result=choice.result)


class EveryRunFailed(NumericalFailure):
    """Every run of the study failed: no run to measure deviations from."""


def compared_run(runs: list[StudyRun], reference: StudyRun, notes: list[str]) -> StudyRun:
    """The reference, or when it failed the finest successful run (noted)."""
    if reference.ok:
        return reference
    finest = [r for r in runs if r.ok]
    if not finest and all(r.reason.startswith(REFUSED) for r in [*runs, reference]):
        # the study's choices make no model: an input to mend, as simulate refuses them (exit 2)
        raise InputError(f"study: every one of its {len(runs) + 1} runs was refused by its choices, the reference "
                         f"{reference.label!r} as: {reference.reason.removeprefix(REFUSED)}; expected families and "
                         "a reference whose choices make a model")
    if not finest:  # each reason once, the reference's first: no file is written to hold them
        reasons = dict.fromkeys(run.reason for run in [reference, *runs])
        said = "; ".join(f"{next(r.label for r in [reference, *runs] if r.reason == reason)!r} as: {reason}"
                         for reason in list(reasons)[:3])
        more = f"; {len(reasons) - 3} other reasons" if len(reasons) > 3 else ""
        raise EveryRunFailed(f"study: every one of its {len(runs) + 1} runs failed, {said}{more}")
    compared = min(finest, key=lambda r: (r.spacing, -r.particles))
    notes.append(f"the reference run failed ({reference.reason}); deviations are measured from "
                 f"the finest successful run, {compared.label}")
    return compared


def run_study(scenario: Scenario, quick: bool = False,
              on_run: Callable[[StudyRun], None] | None = None,
              auto: bool | None = None, executor: Executor | None = None) -> StudyResult:
    """Run every configuration of the study and the reference, each a task on `executor`
    (default: one after another in this process); compare each with the reference.

    With an `accuracy` in the scenario's discretization (or auto=True) the auto
    discretization is chosen too (in this process) and its run added as family "auto".
    Wall times are each run's own: on a cluster of more workers than free cores the runs
    compete for them, so for timings that compare, run with one worker (--workers 1 or 0).
    """
    report = on_run or (lambda run: None)
    runs, reference, repeats = plan_runs(scenario, quick)
    notes: list[str] = []
    if quick and scenario.study is not None:
        notes.append("--quick: the scenario's study: block was not used (the quick sweep's two families at "
                     "1.4 h and h instead)")
    done = run_all(run_timed, [*runs, reference], [repeats] * len(runs) + [1], executor=executor,
                   on_result=lambda index, run: report(run))
    runs, reference = done[:-1], done[-1]  # from a cluster: the workers' copies
    choice = None
    wants_auto = scenario.discretization.accuracy is not None if auto is None else auto
    if wants_auto:
        choice = choose_discretization(scenario, scenario.discretization.accuracy or DEFAULT_ACCURACY)
        runs.append(auto_run(choice))
        notes.append(choice.message)
        report(runs[-1])
    compared = compared_run(runs, reference, notes)
    for run in runs + [reference]:
        if run.ok:
            run.deviations = exit_deviations(run.result, compared.result)
    for run in pareto_front([r for r in runs if r is not compared]):
        run.pareto = True
    failed = [r for r in runs + [reference] if not r.ok]
    if failed:
        notes.append(f"{len(failed)} of {len(runs) + 1} runs failed; their reasons are in study.csv")
    return StudyResult(scenario, runs + [reference], compared, notes, choice,
                       executor.where if executor is not None else "in-process")
