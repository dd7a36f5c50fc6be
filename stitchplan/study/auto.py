"""Models no bigger than the scene needs: the auto discretization.

`discretization: {accuracy: 0.05}` asks for the cheapest model whose exit point lies within
0.05 mm of the converged one. The exit point is measured as in stitchplan.study: the
largest of the deviations of the spatial achieved exit, the material (reference) achieved
exit and the exit-error vector.

The candidates are particle sets graded toward the needle (discretization.graded_particles):
spacing h within `needle_zone` (1.5) needle radii of the needle centre, growing away from it
to `grading` x h (4, capped at a fifth of the tissue's smaller side), each particle's kernel
support following its local spacing. The exit error is dominated by the resolution where
the needle cuts, so a graded set reaches a given accuracy with a fraction of the particles
of a uniform one.

Error estimate from two resolutions: runs at h and h/2 give d = |x(h) - x(h/2)|; with
x(h) - x* ~ C h^p,

    C = d / (h^p (1 - 2^-p)),  e(h') ~ C h'^p.

p = 1 is assumed: the exit point converges at least that fast on the shipped scenes (the
observed order on SH 1/2 is ~1.2-1.6), so the estimate errs on the safe side. The pair
starts at (R/3, R/6) and is halved while the accuracy lies beyond one more halving
(e(h/4) > accuracy), so the estimate never extrapolates further than that; then the
largest h' on a 2^(-1/4) ladder with e(h') <= accuracy is run and returned (from the first
pair the ladder reaches up to 2 h, so a loose accuracy gets a model coarser than R/3).

Methods, chosen on the first (cheapest) pair's discretization, the cheaper where safe:

- tip tracking: `auto` (inverse gradient, Levenberg-Marquardt fallback) when it needs no
  fallback there, its exit lies within accuracy/4 of Levenberg-Marquardt's, and it is
  faster; otherwise `levenberg-marquardt`;
- linear solver: `minres` when it needs no fallback to the direct solve, agrees with it
  (accuracy/10) and is at least 20 % faster; otherwise `direct`.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import asdict, dataclass, field, replace

from ..config import Scenario, ScenarioError, parse_discretization
from ..events import Event, EventKind

log = logging.getLogger(__name__)

ASSUMED_ORDER = 1.0  # convergence order of the exit point in the needle spacing (conservative)
GRADING = 4  # coarse / needle spacing
MAX_HALVINGS = 5


@dataclass
class Trial:
    """One run of the selection."""

    role: str  # "resolution", "tip tracking", "linear solver", "chosen"
    scenario: Scenario
    needle_spacing: float
    tip_tracking: str
    linear_solver: str
    particles: int = 0
    wall_seconds: float = math.nan
    cpu_seconds: float = math.nan
    status: str = "ok"
    reason: str = ""
    result: object = None


@dataclass
class AutoChoice:
    accuracy: float  # mm, requested
    estimate_mm: float  # estimated exit-point error of the chosen discretization
    estimate_basis: str  # which two runs the estimate rests on
    scenario: Scenario  # the scenario with the chosen discretization and methods
    needle_spacing: float
    tip_tracking: str
    linear_solver: str
    result: object  # InsertionResult of the chosen configuration
    cpu_seconds: float
    selection_seconds: float  # wall time of every trial run, the chosen one included
    trials: list[Trial] = field(default_factory=list)
    reasons: dict[str, str] = field(default_factory=dict)
    verified: bool = True  # False when the ladder ran out before the estimate met the accuracy

    @property
    def discretization(self):
        return self.scenario.discretization

    @property
    def message(self) -> str:
        d = self.discretization
        grading = (f"graded: spacing {d.needle_spacing:.3g} mm within {d.needle_zone:g} needle radii of "
                   f"the needle centre, {d.spacing:.3g} mm away from it"
                   if d.needle_spacing is not None else f"uniform spacing {d.spacing:.3g} mm")
        met = "meets" if self.estimate_mm <= self.accuracy else "does NOT meet"
        return (f"auto discretization: accuracy {self.accuracy:g} mm on the exit point; chose {grading} "
                f"({self.result.model.n_particles} particles, dilation {d.dilation:g}), estimated error "
                f"{self.estimate_mm:.3g} mm ({self.estimate_basis}; {met} the target); tip tracking "
                f"{self.tip_tracking} ({self.reasons.get('tip_tracking', '')}); linear solver "
                f"{self.linear_solver} ({self.reasons.get('linear_solver', '')}); selection took "
                f"{len(self.trials)} runs, {self.selection_seconds:.1f} s")


def graded_scenario(scenario: Scenario, needle_spacing: float, tip_tracking: str,
                    linear_solver: str) -> Scenario:
    """The scenario graded toward the needle at `needle_spacing` (coarse spacing GRADING x,
    at most a fifth of the smaller tissue side, and never below the needle spacing)."""
    cap = min(scenario.tissue.size) / 5.0
    grading = GRADING
    while grading > 1 and needle_spacing * grading > max(cap, needle_spacing):
        grading //= 2
    values = asdict(scenario.discretization)
    values.update(accuracy=None, needle_refinement=None, spacing=needle_spacing * grading,
                  needle_spacing=needle_spacing if grading > 1 else None)
    needle = replace(scenario.needle, tip_tracking=tip_tracking, linear_solver=linear_solver)
    return replace(scenario, discretization=parse_discretization(values, "discretization"), needle=needle)


def _run(trial: Trial) -> Trial:
    from ..needle.insertion import run_insertion
    from .sweep import RUN_FAILURES

    start, cpu = time.perf_counter(), time.process_time()
    try:
        trial.result = run_insertion(trial.scenario)
    except RUN_FAILURES as error:
        trial.status, trial.reason = "failed", f"{type(error).__name__}: {error}"
        trial.wall_seconds = time.perf_counter() - start
        trial.cpu_seconds = time.process_time() - cpu
        return trial
    trial.wall_seconds = trial.result.wall_seconds
    trial.cpu_seconds = time.process_time() - cpu
    trial.particles = trial.result.model.n_particles
    return trial


def _deviation(a, b) -> float:
    from .sweep import exit_deviations

    return exit_deviations(a.result, b.result)["deviation_mm"]


def choose_discretization(scenario: Scenario, accuracy: float, tip_tracking: str | None = None,
                          linear_solver: str | None = None, on_trial=None) -> AutoChoice:
    """The cheapest graded discretization (and methods) whose estimated exit-point error is
    at most `accuracy` mm; see the module docstring. Explicit tip_tracking/linear_solver are
    kept as given."""
    if scenario.needle is None:
        raise ScenarioError("discretization.accuracy: needs a needle (the accuracy is on its exit point)")
    if not accuracy > 0:
        raise ScenarioError(f"discretization.accuracy: got {accuracy!r}, expected a positive distance (mm)")
    trials: list[Trial] = []
    reasons: dict[str, str] = {}

    def run(role: str, h: float, tracking: str, solver: str) -> Trial:
        for done in trials:  # same configuration already run
            if (done.needle_spacing, done.tip_tracking, done.linear_solver) == (h, tracking, solver):
                return done
        trial = _run(Trial(role, graded_scenario(scenario, h, tracking, solver), h, tracking, solver))
        trials.append(trial)
        log.info("auto discretization: %s run h=%.3g mm %s/%s: %s %.2f s", role, h, tracking, solver,
                 trial.status, trial.wall_seconds)
        if on_trial is not None:
            on_trial(trial)
        return trial

    radius = scenario.needle.radius
    h = round(radius / 3.0, 4)
    tracking, solver = "levenberg-marquardt", "direct"  # the safe pair, used for the ladder
    coarse = run("resolution", h, tracking, solver)
    while not coarse.status == "ok" and h > radius / 3.0 / 2 ** MAX_HALVINGS:
        h = round(h / 2, 4)
        coarse = run("resolution", h, tracking, solver)
    if coarse.status != "ok":
        raise ScenarioError(f"discretization.accuracy: no auto discretization runs ({coarse.reason})")

    # methods, on the cheapest pair's discretization
    if tip_tracking is not None:
        tracking, reasons["tip_tracking"] = tip_tracking, "given"
    else:
        trial = run("tip tracking", h, "auto", solver)
        events = ([e for e in trial.result.events if e.kind is EventKind.TIP_TRACKING_FALLBACK]
                  if trial.status == "ok" else [])
        if trial.status != "ok":
            reasons["tip_tracking"] = f"inverse gradient failed at h={h:g} mm: {trial.reason.split(':')[0]}"
        elif events:
            reasons["tip_tracking"] = f"inverse gradient needed {len(events)} fallbacks at h={h:g} mm"
        else:
            gap = _deviation(trial, coarse)
            if gap > accuracy / 4:
                reasons["tip_tracking"] = f"inverse gradient's exit {gap:.3g} mm from Levenberg-Marquardt's"
            elif trial.wall_seconds >= coarse.wall_seconds:
                reasons["tip_tracking"] = "inverse gradient not faster"
            else:
                tracking = "auto"
                reasons["tip_tracking"] = (f"inverse gradient safe: exit within {gap:.2g} mm of "
                                           f"Levenberg-Marquardt's, {coarse.wall_seconds / trial.wall_seconds:.2g}x faster")
        if tracking == "levenberg-marquardt":
            reasons["tip_tracking"] = "safe choice; " + reasons["tip_tracking"]
    base = run("resolution", h, tracking, "direct")
    if linear_solver is not None:
        solver, reasons["linear_solver"] = linear_solver, "given"
    else:
        trial = run("linear solver", h, tracking, "minres")
        if trial.status != "ok":
            reasons["linear_solver"] = f"MINRES failed at h={h:g} mm: {trial.reason.split(':')[0]}"
        elif trial.result.solver_counts.get("minres_fallbacks", 0):
            reasons["linear_solver"] = f"MINRES fell back to the direct solve at h={h:g} mm"
        elif _deviation(trial, base) > accuracy / 10:
            reasons["linear_solver"] = "MINRES and the direct solve disagree"
        elif trial.wall_seconds > 0.8 * base.wall_seconds:
            reasons["linear_solver"] = (f"direct faster: {base.wall_seconds:.2f} s against MINRES "
                                        f"{trial.wall_seconds:.2f} s at h={h:g} mm")
        else:
            solver = "minres"
            reasons["linear_solver"] = (f"MINRES {base.wall_seconds / trial.wall_seconds:.2g}x faster "
                                        f"than direct at h={h:g} mm")

    # resolution ladder with the chosen methods
    coarse = run("resolution", h, tracking, solver)
    if coarse.status != "ok":
        raise ScenarioError(f"discretization.accuracy: the auto discretization's first run failed ({coarse.reason})")
    pair = None
    first = True
    for _ in range(MAX_HALVINGS):
        fine = run("resolution", round(h / 2, 4), tracking, solver)
        if fine.status != "ok":
            break
        difference = _deviation(coarse, fine)
        constant = difference / (h ** ASSUMED_ORDER * (1.0 - 2.0 ** -ASSUMED_ORDER))  # e(h') ~ C h'^p
        pair = (h, fine, difference, constant, first)
        # extrapolate at most one halving beyond the pair; halve the pair when the target lies further
        if constant * (h / 4) ** ASSUMED_ORDER <= accuracy:
            break
        h, coarse, first = h / 2, fine, False
    if pair is None:
        raise ScenarioError(f"discretization.accuracy: no two resolutions ran to estimate the error "
                            f"(h = {h / 2:.3g} mm: {fine.reason})")
    h, fine, difference, constant, first = pair
    basis = (f"runs at needle spacing {h:.3g} and {h / 2:.3g} mm differ by {difference:.3g} mm, "
             f"order {ASSUMED_ORDER:g} assumed")
    verified = constant * (h / 4) ** ASSUMED_ORDER <= accuracy
    chosen = fine
    # the largest spacing on a 2^(1/4) ladder whose estimated error meets the accuracy:
    # between h/2 and h/4, or up to 2h coarser than the pair when it is the first one
    ladder = tuple(2.0 ** (-k / 4) for k in range(-4 if first else 0, 9))
    target = next((round(h * f, 4) for f in ladder if constant * (h * f) ** ASSUMED_ORDER <= accuracy),
                  round(h / 4, 4))
    candidate = run("chosen", target, tracking, solver)
    if candidate.status == "ok":
        chosen = candidate
    estimate = constant * chosen.needle_spacing ** ASSUMED_ORDER
    if chosen.role == "resolution":
        chosen.role = "chosen"
    return AutoChoice(
        accuracy=accuracy, estimate_mm=estimate, estimate_basis=basis, scenario=chosen.scenario,
        needle_spacing=chosen.needle_spacing, tip_tracking=tracking, linear_solver=solver,
        result=chosen.result, cpu_seconds=chosen.cpu_seconds,
        selection_seconds=sum(t.wall_seconds for t in trials), trials=trials, reasons=reasons,
        verified=verified)


def resolve_accuracy(scenario: Scenario, tip_tracking: str | None = None,
                     linear_solver: str | None = None) -> tuple[Scenario, Event | None]:
    """The scenario with the auto discretization in place of `accuracy`, and the note that
    says what was chosen and why (None when the scenario gives no accuracy). Called once,
    before a run: every insertion of a `plan` then uses the same model."""
    if scenario.discretization.accuracy is None:
        return scenario, None
    choice = choose_discretization(scenario, scenario.discretization.accuracy, tip_tracking, linear_solver)
    note = Event(EventKind.AUTO_DISCRETIZATION, choice.message)
    return replace(choice.scenario, source_text=scenario.source_text, name=scenario.name), note
