"""Planning under parameter uncertainty: exit-error bands over sampled parameters, a robust
plan, and the exit's sensitivity to each parameter.

The robust plan is the nominal plan aimed with the mean exit shift:

1. plan on the scenario's values (Algorithm 2 with its passes, planning.planner.run_plan;
   the nominal plan, with the unplanned run of the nominal scene); with `verify`, as `plan`
   plans (planning.verification.plan_verified: aimed for the refined model and checked on
   it), and the refined model's offset delta = e_refined - e_base of its path measured;
2. replay the nominal plan's centre path on the training samples: exit error vectors e_i,
   deviations d_i = e_i - e_nominal (e_nominal: the nominal plan's own exit error), and
   the mean shift s = mean(d_i);
3. unless s is within the training samples' sampling noise (Hotelling's T^2 below its 95 %
   quantile for n samples, shift_threshold: then the robust plan is the nominal plan, since
   aiming at noise adds it to every exit; with fewer than 3 successful training runs, or
   deviations without a spread in some direction, their covariance is singular, T^2 is not
   defined and the robust plan is the nominal plan too), plan again on the scenario's values
   with the passes aiming the exit error at -s - delta (run_plan's `aim`, continuing the
   secant of the nominal passes, as plan_verified does for a refined model's offset; delta
   0 without `verify`). Every path near
   the nominal one moves the exit alike with the parameters, so that path misses sample i by about d_i - s: the cloud of exits
   centred on the desired exit, which minimises the expected squared miss
   E|e|^2 = |mean e|^2 + trace cov e over aimed plans. (Aiming instead at the minimum of
   the training samples' mean + p95 miss was tried: with 16 samples the p95 is the
   second-largest miss, and that aim chased the training set's extremes.)

Re-aiming moves the cloud of exits, not its spread: to first order every centre path near
the nominal one has the same sensitivities, so the spread comes from the parameters, and
the part of the miss a plan can remove is the cloud's offset from the desired exit (the
mean shift from the nonlinearity of the exit in the parameters, the truncation of the
distributions and the nominal plan's own miss) and its skew. When the spread dominates,
the robust plan is no better than the nominal one beyond sampling noise.

Evaluation: unplanned (fixed centre), nominal and robust paths replayed on the held-out
samples (sampling.py: drawn after the training samples from the same seed), which did not
build the robust plan; statistics over the samples where all three ran. The sampled runs
replay on the planning model; with `verify` the planned paths' exit error vectors are
reported with delta added (`UncertaintyResult.errors`): on the refined model to first
order, as the offset barely moves with the parameters (on sh12_100x100 each held-out
sample's own offset is within 0.7 µm of the 14 µm added: benchmarks/results/uncertainty_refined.md),
while the plans land -delta off on the planning model by design. When the robust
plan is worse than the nominal one there in mean or 95th percentile (or fails more
samples), the nominal plan is exported instead and the summary says so. The exported plan is
then checked as `plan` checks its own (check_exported_plan): with `verify` replayed on the
refined model at the scenario's values, else its exit error estimated at twice the spacing.

Sensitivity: central finite differences of the exit error vector (and of the achieved exit
point) per parameter, the nominal plan's path replayed at the scenario's value +- h,
h = SENSITIVITY_STEP x std (at most half the value), the other parameters at the
scenario's values.

Only the exit is aimed at: planner.target `symmetric` on a stitch across a wound (equal bites)
is refused (check_target).

Every sampled run is a task on the executor (parallel.executor.Executor); the two plans run in
this process. When every run on a sampled parameter set fails (training and held-out), the result
would say nothing about the uncertainty: that is a NumericalFailure naming how many failed
and the first reason; some failed runs are recorded and counted.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.stats import f as f_distribution

from ..config import Scenario
from ..config.uncertainty import Uncertainty, check_against_scenario, unit_of
from ..errors import InputError, NumericalFailure
from ..events import Event, EventKind
from ..parallel.executor import Executor, run_all
from ..planning.planner import PlanResult, run_plan
from ..planning.replay_models import aims_at_bites
from ..planning.verification import (AIMED_TOLERANCE_FRACTION, estimate_exit_error, exit_offset, plan_verified,
                                     verify_exported)
from .evaluation import SampleRun, run_sample
from .sampling import Design, draw, with_parameters

log = logging.getLogger(__name__)

SENSITIVITY_STEP = 0.5  # finite-difference step / std
CHI2_95_2D = 5.991464547107979  # chi^2 quantile, 2 degrees of freedom, 0.95: the 95 % ellipse
SHIFT_CONFIDENCE = 0.95  # of the test whether the mean exit shift is more than sampling noise
Z_95 = 1.959963984540054  # two-sided 95 % of a standard normal
LABELS = ("unplanned", "nominal", "robust")


def exit_statistics(errors: np.ndarray) -> dict[str, float | None]:
    """{mean_mm, p50_mm, p95_mm, max_mm} of the exit error distances |e| (errors (n, 2))."""
    distances = np.linalg.norm(np.asarray(errors, dtype=float).reshape(-1, 2), axis=1)
    if len(distances) == 0:
        return {"mean_mm": None, "p50_mm": None, "p95_mm": None, "max_mm": None}
    p50, p95 = np.percentile(distances, [50.0, 95.0])
    return {"mean_mm": float(distances.mean()), "p50_mm": float(p50), "p95_mm": float(p95),
            "max_mm": float(distances.max())}


def ellipse_95(errors: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Centre (2,) and the (2, 2) matrix A of the 95 % ellipse {c + A [cos t, sin t]} of a
    normal fitted to the points (n, 2); None for fewer than 3 points."""
    errors = np.asarray(errors, dtype=float).reshape(-1, 2)
    if len(errors) < 3:
        return None
    covariance = np.cov(errors.T)  # (2, 2)
    values, vectors = np.linalg.eigh(covariance)
    return errors.mean(axis=0), vectors * np.sqrt(np.maximum(values, 0.0) * CHI2_95_2D)


@dataclass(frozen=True)
class Sensitivity:
    """d(exit)/d(parameter) by central differences (mm per unit of the parameter)."""

    name: str
    std: float
    step: float  # the finite-difference half step h
    exit_error: np.ndarray | None  # (2,) of the exit error vector; None: a run failed
    achieved_exit: np.ndarray | None  # (2,) of the achieved exit point (deformed)
    reason: str = ""

    @property
    def spread_mm(self) -> float:
        """|d e / d p| std: the exit's 1-sigma move from this parameter alone (mm)."""
        return float("nan") if self.exit_error is None else float(np.linalg.norm(self.exit_error) * self.std)


@dataclass
class UncertaintyResult:
    uncertainty: Uncertainty
    design: Design
    nominal: PlanResult  # with the nominal scene's unplanned run
    robust: PlanResult | None  # None: no training run succeeded
    exported: str  # "robust" or "nominal"
    shift: np.ndarray  # (2,) mean training exit error - the nominal plan's own
    training: list[SampleRun]  # the nominal path on the training samples
    held_out: dict[str, list[SampleRun]]  # LABELS -> runs on the held-out samples
    sensitivities: list[Sensitivity]
    where: str  # the executor
    notes: list[str] = field(default_factory=list)
    # (2,) the robust plan's exit error aimed at on the planning model (-shift - the refined offset;
    # where it is the nominal plan, that plan's own exit error there); None: no robust plan
    aim: np.ndarray | None = None
    deviations: np.ndarray | None = None  # (n_ok, 2) training exit errors - the nominal plan's own
    shift_significance: float | None = None  # Hotelling T^2 of the mean shift; None: not tested
    shift_threshold: float | None = None  # its 95 % quantile for the training runs (shift_threshold)
    # (2,) the refined model's exit offset of the nominal path (e_refined - e_base) the plans
    # aim by; None: not verified (the module docstring)
    refined_offset: np.ndarray | None = None

    def on_refined_model(self, errors: np.ndarray, label: str) -> np.ndarray:
        """A planned path's exit error vectors on the planning model with the refined model's
        offset added (the unplanned path's, and all without an offset, as they are)."""
        if self.refined_offset is None or label == "unplanned":
            return errors
        return errors + self.refined_offset

    def training_prediction(self) -> dict | None:
        """The training samples' miss statistics predicted for the nominal (d_i + e_nominal)
        and the robust (d_i + aim) plans."""
        if self.aim is None:
            return None
        own = self.nominal.planned.exit_error_vector_mm
        return {"nominal": exit_statistics(self.on_refined_model(self.deviations + own, "nominal")),
                "robust": exit_statistics(self.on_refined_model(self.deviations + self.aim, "robust"))}

    @property
    def exported_plan(self) -> PlanResult:
        return self.robust if self.exported == "robust" else self.nominal

    @property
    def robust_is_nominal(self) -> bool:
        """Whether the robust plan is the nominal one (no shift to aim with, or one within the
        training samples' noise): then both have the same held-out runs."""
        return self.robust is None or self.robust is self.nominal

    @property
    def evaluated(self) -> np.ndarray:
        """Held-out samples where every path ran (bool, (samples,))."""
        return np.all([[run.ok for run in self.held_out[label]] for label in LABELS], axis=0)

    def errors(self, label: str, evaluated_only: bool = True) -> np.ndarray:
        """Exit error vectors (n, 2) of a path on the held-out samples (a planned path's on
        the refined model, on_refined_model)."""
        errors = self.on_refined_model(np.array([run.exit_error for run in self.held_out[label]]).reshape(-1, 2),
                                       label)
        return errors[self.evaluated] if evaluated_only else errors

    @property
    def statistics(self) -> dict[str, dict]:
        return {label: exit_statistics(self.errors(label)) for label in LABELS}

    def failures(self) -> list[dict]:
        """Every failed run: sample set, index, path and reason."""
        runs = [("training", "nominal", self.training)] + [("held_out", label, self.held_out[label])
                                                           for label in LABELS]
        return [{"set": name, "sample": index, "path": label, "reason": run.reason}
                for name, label, group in runs for index, run in enumerate(group) if not run.ok]

    def failed_in(self, sample_set: str) -> int:
        """Samples of one set ("training" or "held_out") with at least one failed run."""
        return len({record["sample"] for record in self.failures() if record["set"] == sample_set})

    @property
    def failed_training_samples(self) -> int:
        """Training samples whose run (the nominal path) failed."""
        return self.failed_in("training")

    @property
    def failed_held_out_samples(self) -> int:
        """Held-out samples with a failed run of any path: those not evaluated."""
        return self.failed_in("held_out")

    def dominant(self) -> Sensitivity | None:
        """The parameter moving the exit most over its std (|sensitivity| x std)."""
        known = [s for s in self.sensitivities if s.exit_error is not None]
        return max(known, key=lambda s: s.spread_mm) if known else None

    def linearised_spread_mm(self) -> float | None:
        """The 95 % half-width of the exit errors from all parameters together, linearised:
        1.96 sqrt(largest eigenvalue of J C J^T), J the sensitivities (2, k), C the
        parameters' covariance (correlations included), formed as (J S) R (J S)^T with S the
        stds and R the correlation matrix, so that no product of two stds can overflow."""
        if any(s.exit_error is None for s in self.sensitivities):
            return None
        scaled = np.array([s.exit_error * s.std for s in self.sensitivities]).T  # (2, k): J S
        covariance = scaled @ self.uncertainty.correlation @ scaled.T  # (2, 2)
        if not np.all(np.isfinite(covariance)):
            return None
        return float(Z_95 * np.sqrt(max(np.linalg.eigvalsh(covariance).max(), 0.0)))

    def dominance_line(self) -> str:
        """"exit spread dominated by <param> (... mm of ... mm p95)": the 95 % exit move from
        that parameter alone against the linearised 95 % spread from all of them, and the
        exported plan's held-out p95 miss; where correlated parameters cancel (the one alone
        moves the exit more than all together) the line says so instead."""
        dominant = self.dominant()
        if dominant is None:
            return "exit spread: unknown (a sensitivity run failed)"
        total = self.linearised_spread_mm()
        of_total = ("; the linearised p95 of all is unknown: a sensitivity run failed" if total is None
                    else f" of {total:.3g} mm p95, linearised")
        p95 = self.statistics[self.exported]["p95_mm"]
        miss = "" if p95 is None else f"; held-out p95 miss {p95:.3g} mm"
        alone = Z_95 * dominant.spread_mm
        if total is not None and alone > total:  # correlated parameters cancel: not a share of the total
            names = list(self.uncertainty.names)
            row = self.uncertainty.correlation[names.index(dominant.name)]
            partners = [f"{name} ({row[k]:+.3g})" for k, name in enumerate(names)
                        if name != dominant.name and row[k] != 0.0]
            return (f"exit spread: {dominant.name} alone would move the exit {alone:.3g} mm (p95, std "
                    f"{dominant.std:g} {unit_of(dominant.name)}), more than the {total:.3g} mm p95 of all "
                    f"parameters together (linearised): its correlation with {', '.join(partners)} cancels "
                    f"most of it{miss}")
        return (f"exit spread dominated by {dominant.name} ({alone:.3g} mm{of_total}; "
                f"std {dominant.std:g} {unit_of(dominant.name)}{miss})")


def shift_significance(deviations: np.ndarray) -> float | None:
    """Hotelling's T^2 = n s^T W^-1 s of the mean s of the deviations (n, 2), W their sample
    covariance; None where T^2 is not defined: fewer than 3 deviations, or a singular W (no
    spread in some direction; W's rank below 2). 0 for an exact zero shift."""
    deviations = np.asarray(deviations, dtype=float).reshape(-1, 2)
    n = len(deviations)
    if n < 3:
        return None
    shift = deviations.mean(axis=0)
    if not np.any(shift):
        return 0.0
    covariance = np.cov(deviations.T)  # (2, 2)
    if not np.all(np.isfinite(covariance)) or np.linalg.matrix_rank(covariance) < 2:
        return None
    return float(n * shift @ np.linalg.solve(covariance, shift))


def shift_threshold(n: int) -> float | None:
    """The 95 % quantile of Hotelling's T^2 for n deviations in 2 dimensions under a zero
    mean shift: 2 (n - 1) / (n - 2) F_0.95(2, n - 2) (798 for 3, 57.0 for 4, 8.01 for 16,
    tending to the chi^2 quantile 5.99); None below 3."""
    if n < 3:
        return None
    return float(2.0 * (n - 1) / (n - 2) * f_distribution.ppf(SHIFT_CONFIDENCE, 2, n - 2))


def planned_tasks(uncertainty: Uncertainty) -> int:
    """Sampled runs of plan_under_uncertainty (for a progress bar): the training runs, three
    paths on the held-out samples, two runs per sensitivity."""
    return 4 * uncertainty.samples + 2 * len(uncertainty.names)


def check_target(scenario: Scenario, source: str = "scenario") -> None:
    """Refuse planner.target `symmetric` on a stitch across a wound (`source`: the scenario's
    file, for the message). The plans here aim at the exit point: the training shift, the
    robust aim and the held-out statistics are exit error vectors. A symmetric plan aims at
    equal bites and trades exit error for them (planning.planner.run_plan), so its passes
    would override the robust aim and the statistics would measure what it does not aim at."""
    if aims_at_bites(scenario):
        raise InputError(f"{source}: planner.target: got 'symmetric', expected 'exit' with --uncertainty (plans "
                         "under uncertainty aim at the exit point and report its spread; a symmetric plan aims at "
                         "equal bites across the wound instead: plan it without --uncertainty, or plan the exit "
                         "under uncertainty with planner.target: exit)")


def check_inputs(uncertainty: Uncertainty, scenario: Scenario, scenario_path: str | Path) -> None:
    """Refuse, before any run, what plan_under_uncertainty could not honour: parameters the
    scenario cannot vary as the file asks (config.uncertainty.check_against_scenario), a
    symmetric target (check_target) and a distribution mostly below zero (draw)."""
    check_against_scenario(uncertainty, scenario, scenario_path)
    check_target(scenario, str(scenario_path))
    draw(uncertainty, scenario)


def plan_under_uncertainty(scenario: Scenario, uncertainty: Uncertainty, executor: Executor | None = None,
                           on_run: Callable[[str], None] | None = None, verify: bool = False,
                           **options) -> UncertaintyResult:
    """The nominal and robust plans, their held-out exit statistics and the sensitivities
    (module docstring); `options` go to the insertions (linear_solver, tip_tracking);
    `on_run(description)` after each plan and each sampled run; with `verify` the nominal plan
    is plan_verified's (its `verification` set) and the plans aim for the refined model."""
    if scenario.needle is None:
        raise InputError("needle: missing, required by plan")
    check_target(scenario)
    report = on_run or (lambda description: None)
    design = draw(uncertainty, scenario)
    steps = np.minimum(uncertainty.std * SENSITIVITY_STEP, design.nominal / 2.0)
    train, held, probes = _sampled_scenarios(scenario, uncertainty.names, design, steps)
    nominal, offset = _nominal_plan(scenario, verify, options)
    report("nominal plan")
    training, unplanned, nominal_held, probe_runs = _replay_nominal(nominal, train, held, probes, executor, options,
                                                                    report)
    _refuse_all_failed(training, unplanned, nominal_held)
    sensitivities = _sensitivities(uncertainty.names, uncertainty.std, steps, probe_runs)
    held_out = {"unplanned": unplanned, "nominal": nominal_held, "robust": nominal_held}
    ok = [run.exit_error for run in training if run.ok]
    if len(ok) < 2:
        notes = [f"{len(ok)} of {uncertainty.samples} training runs succeeded: no mean shift to aim with; the "
                 "nominal plan is exported"]
        _robust_runs_skipped(report, held)
        return UncertaintyResult(uncertainty, design, nominal, None, "nominal", np.zeros(2), training, held_out,
                                 sensitivities, _where(executor), notes, refined_offset=offset)
    own = nominal.planned.exit_error_vector_mm  # where the nominal plan exits on the planning model
    deviations = np.asarray(ok) - own  # (n_ok, 2)
    shift = deviations.mean(axis=0)
    significance, threshold = shift_significance(deviations), shift_threshold(len(ok))
    if significance is None or significance < threshold:  # aiming at noise only adds it to every exit
        notes = [_unaimed_note(shift, significance, threshold, len(ok))]
        _robust_runs_skipped(report, held)
        return UncertaintyResult(uncertainty, design, nominal, nominal, "robust", shift, training, held_out,
                                 sensitivities, _where(executor), notes, aim=own, deviations=deviations,
                                 shift_significance=significance, shift_threshold=threshold, refined_offset=offset)
    aim = -shift if offset is None else -shift - offset  # the refined model's exit centred on the desired one
    log.info("mean exit shift over %d training samples (%.4g, %.4g) mm, T^2 %.3g >= %.3g; re-planning aimed "
             "at (%.4g, %.4g) mm", len(ok), *shift, significance, threshold, *aim)
    robust = _robust_plan(scenario, nominal, aim, options)
    report("robust plan")
    robust_held = _runs(executor, held, [robust.exported_centers] * len(held), options, report)
    held_out = {"unplanned": unplanned, "nominal": nominal_held, "robust": robust_held}
    result = UncertaintyResult(uncertainty, design, nominal, robust, "robust", shift, training, held_out,
                               sensitivities, _where(executor), [], aim=aim, deviations=deviations,
                               shift_significance=significance, shift_threshold=threshold, refined_offset=offset)
    _choose(result)
    return result


def _robust_runs_skipped(report: Callable[[str], None], held: list) -> None:
    """The robust plan and its held-out runs, not run where the nominal plan stands for it:
    reported as done, so that a progress bar over planned_tasks + 2 ends full."""
    for _ in range(1 + len(held)):
        report("robust plan: the nominal plan")


def _sampled_scenarios(scenario: Scenario, names: tuple[str, ...], design: Design,
                       steps: np.ndarray) -> tuple[list[Scenario], list[Scenario], list[Scenario]]:
    """The scenario at the training and the held-out parameter sets, and the sensitivity
    probes: each parameter at its value + and - its step `steps[k]`, the others at theirs."""
    train = [with_parameters(scenario, names, values) for values in design.train]
    held = [with_parameters(scenario, names, values) for values in design.held_out]
    probes = [with_parameters(scenario, (name,), [design.nominal[k] + sign * steps[k]])
              for k, name in enumerate(names) for sign in (1.0, -1.0)]
    return train, held, probes


def _nominal_plan(scenario: Scenario, verify: bool, options: dict) -> tuple[PlanResult, np.ndarray | None]:
    """The plan on the scenario's values with its unplanned run (step 1 of the module
    docstring) and the refined model's exit offset of its path: with `verify` plan_verified's
    (None when its path could not be replayed there), else run_plan's and None."""
    if not verify:
        return run_plan(scenario, compare=True, **options), None
    nominal = plan_verified(scenario, compare=True, **options)
    refined = nominal.verification.result
    return nominal, None if refined is None else exit_offset(refined, nominal.planned)


def _replay_nominal(nominal: PlanResult, train: list[Scenario], held: list[Scenario], probes: list[Scenario],
                    executor: Executor | None, options: dict, report: Callable[[str], None]) -> tuple[list, ...]:
    """One batch of sampled runs: the nominal path on the training samples, the fixed centre
    (unplanned) and the nominal path on the held-out ones, the nominal path on the probes;
    returns the runs of these four groups."""
    path = nominal.exported_centers
    runs = _runs(executor, [*train, *held, *held, *probes],
                 [path] * len(train) + [None] * len(held) + [path] * (len(held) + len(probes)), options, report)
    n, m = len(train), len(train) + len(held)
    return runs[:n], runs[n:m], runs[m:m + len(held)], runs[m + len(held):]


def _unaimed_note(shift: np.ndarray, significance: float | None, threshold: float | None, successes: int) -> str:
    """Why the robust plan is the nominal plan: the mean exit shift over `successes` training
    runs is within their sampling noise, or cannot be tested against it."""
    if significance is None:
        why = (f"{successes} training runs succeeded, and Hotelling's T^2 needs at least 3" if successes < 3 else
               "the training deviations have no spread in some direction (a singular covariance)")
        return (f"the mean exit shift ({shift[0]:.3g}, {shift[1]:.3g}) mm cannot be tested against the "
                f"training samples' sampling noise ({why}): the robust plan is the nominal plan")
    return (f"the mean exit shift ({shift[0]:.3g}, {shift[1]:.3g}) mm is within the training samples' "
            f"sampling noise (Hotelling T^2 {significance:.3g} < {threshold:.3g}, its 95 % quantile "
            f"for {successes} samples): the robust plan is the nominal plan")


def _robust_plan(scenario: Scenario, nominal: PlanResult, aim: np.ndarray, options: dict) -> PlanResult:
    """The plan again on the scenario's values, its passes aiming the exit error at `aim` and
    continuing the nominal plan's secant (step 3); its record carries the nominal plan's
    unplanned run and passes before its own."""
    robust = run_plan(scenario, compare=False, aim=aim, shooting=nominal.shooting,
                      tolerance=AIMED_TOLERANCE_FRACTION * scenario.planner.exit_tolerance, **options)
    robust.unplanned = nominal.unplanned
    robust.passes = nominal.passes + [{**record, "round": "robust"} for record in robust.passes]
    return robust


def check_exported_plan(scenario: Scenario, result: UncertaintyResult, verify: bool = False,
                        **options) -> PlanResult:
    """The exported plan checked as `plan` checks its own, with an accuracy-check event first
    among its planned run's saying how: with `verify` replayed on the refined model at the
    scenario's values (verify_exported), else its exit error estimated from its path
    replayed at twice the spacing (as `plan --no-verify` estimates it)."""
    plan = result.exported_plan
    if verify:
        if plan.verification is None:  # the re-aimed robust plan; the nominal one was verified as `plan` verifies
            verify_exported(scenario, plan, **options)
        note = _verification_note(result.refined_offset)
    else:
        note = "the plans under uncertainty are not verified on a refined model (--no-verify)"
        plan.estimate = estimate_exit_error(scenario, plan.planned, plan.exported_centers, **options)
    plan.planned.events.insert(0, Event(EventKind.ACCURACY_CHECK, note))
    return plan


def _verification_note(offset: np.ndarray | None) -> str:
    """What the refined model did for the plans: aimed them by its offset for the nominal
    plan's path (None: that path could not be replayed on it)."""
    if offset is None:
        return ("verification: the nominal plan's trajectory could not be replayed on the refined model: no "
                "refined offset is added to the plans' statistics, and a re-aimed robust plan aims by the mean "
                "shift alone")
    return (f"verification: the plans aim for the refined model (its exit offset for the nominal plan's path, "
            f"({offset[0]:.3g}, {offset[1]:.3g}) mm), the exported plan replayed on it at the scenario's "
            "values; the sampled runs replay on the planning model, the plans' exit errors are reported "
            "with that offset added")


def _runs(executor: Executor | None, scenarios: list[Scenario], paths: list, options: dict,
          report: Callable[[str], None]) -> list[SampleRun]:
    return run_all(run_sample, scenarios, paths, [options] * len(scenarios), executor=executor,
                   on_result=lambda index, run: report("sampled runs"))


def _where(executor: Executor | None) -> str:
    return executor.where if executor is not None else "in-process"


def _refuse_all_failed(training: list[SampleRun], unplanned: list[SampleRun], nominal: list[SampleRun]) -> None:
    """A NumericalFailure when no run on a sampled parameter set succeeded: the runs say
    nothing about the uncertainty then, and statistics over none of them are no result."""
    groups = [("training", "nominal", training), ("held-out", "unplanned", unplanned), ("held-out", "nominal", nominal)]
    runs = [(name, label, index, run) for name, label, group in groups for index, run in enumerate(group)]
    if any(run.ok for *_, run in runs):
        return
    name, label, index, run = runs[0]
    reason = " ".join(run.reason.split())
    raise NumericalFailure(f"plan --uncertainty: all {len(runs)} sampled runs failed ({len(training)} training, "
                           f"{len(unplanned) + len(nominal)} held-out), so they tell nothing about the "
                           f"uncertainty; the first, {name} sample {index} ({label} path): {reason}")


def _sensitivities(names, std, steps, runs: list[SampleRun]) -> list[Sensitivity]:
    found = []
    for k, name in enumerate(names):
        plus, minus = runs[2 * k], runs[2 * k + 1]
        if plus.ok and minus.ok:
            found.append(Sensitivity(name, float(std[k]), float(steps[k]),
                                     (plus.exit_error - minus.exit_error) / (2.0 * steps[k]),
                                     (plus.achieved_exit_def - minus.achieved_exit_def) / (2.0 * steps[k])))
        else:
            found.append(Sensitivity(name, float(std[k]), float(steps[k]), None, None,
                                     plus.reason or minus.reason))
    return found


def _choose(result: UncertaintyResult) -> None:
    """Keep the robust plan unless it is worse than the nominal one on the held-out samples
    (mean or p95 of the miss, or more failed runs): then export the nominal plan."""
    stats = result.statistics
    robust, nominal = stats["robust"], stats["nominal"]
    failed = {label: sum(not run.ok for run in result.held_out[label]) for label in ("nominal", "robust")}
    if robust["mean_mm"] is None:
        worse = ["no held-out sample ran every path"]
    else:
        worse = [f"{key[:-3]} {robust[key]:.4g} mm > {nominal[key]:.4g} mm" for key in ("mean_mm", "p95_mm")
                 if robust[key] > nominal[key]]
    if failed["robust"] > failed["nominal"]:
        worse.append(f"{failed['robust']} failed held-out runs > {failed['nominal']}")
    if worse:
        result.exported = "nominal"
        result.notes.append("the robust plan is not better than the nominal plan on the held-out samples ("
                            + "; ".join(worse) + "); the nominal plan is exported")
