"""Models no bigger than the scene needs: the auto discretization.

`discretization: {accuracy: 0.05}` asks for the cheapest model whose exit point lies within
0.05 mm of the converged one. The exit point is measured as in stitchplan.study.sweep
(stitchplan.planning.verification.exit_deviations): the largest of the deviations of the spatial
achieved exit, the material (reference) achieved exit and the exit-error vector.

The candidates are particle sets graded toward the needle (stitchplan.tissue.particles.graded_particles):
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

Limits: no trial runs a model beyond the resource guard's particle limit
(stitchplan.resources.limits; `max_particles`, None for none). As soon as the first pair gives an
error constant, an accuracy that even the finest allowed model cannot reach (e(h_floor) >
accuracy, h_floor the finest needle spacing within the limit) is refused with the accuracy
that model would reach, instead of a search that halves on into models no machine holds.

The steps, in order: `first_resolution` (the safe methods at R/3, halved until a run
succeeds), `choose_tip_tracking`, `choose_linear_solver`, `estimate_error` (the resolution
ladder), `pick_resolution` (the final pick). Every run is an InsertionRun whose `family`
says what it was run for: "resolution", "tip tracking", "linear solver" or "chosen".
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

from ..config import Scenario
from ..errors import InputError
from ..events import Event, EventKind
from ..resources.limits import MAX_PARTICLES
from ..resources.model_size import model_size
from ..planning.verification import exit_deviations
from .runner import InsertionRun, events_of, run_timed

if TYPE_CHECKING:
    from ..needle.results import InsertionResult

log = logging.getLogger(__name__)

ASSUMED_ORDER = 1.0  # convergence order of the exit point in the needle spacing (conservative)
GRADING = 4  # coarse / needle spacing
MAX_HALVINGS = 5
SAFE_TRACKING, SAFE_SOLVER = "levenberg-marquardt", "direct"


@dataclass
class AutoChoice:
    accuracy: float  # mm, requested
    estimate_mm: float  # estimated exit-point error of the chosen discretization
    estimate_basis: str  # which two runs the estimate rests on
    scenario: Scenario  # the scenario with the chosen discretization and methods
    needle_spacing: float
    tip_tracking: str
    linear_solver: str
    result: InsertionResult  # of the chosen configuration
    cpu_seconds: float
    selection_seconds: float  # wall time of every trial run, the chosen one included
    trials: list[InsertionRun] = field(default_factory=list)
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
    cap = min(scenario.tissue.bounding_size) / 5.0
    grading = GRADING
    while grading > 1 and needle_spacing * grading > max(cap, needle_spacing):
        grading //= 2
    discretization = scenario.discretization.replaced(
        accuracy=None, needle_refinement=None, spacing=needle_spacing * grading,
        needle_spacing=needle_spacing if grading > 1 else None)
    needle = replace(scenario.needle, tip_tracking=tip_tracking, linear_solver=linear_solver)
    return replace(scenario, discretization=discretization, needle=needle)


class Trials:
    """The selection's runs, each configuration run at most once."""

    def __init__(self, scenario: Scenario, on_trial: Callable[[InsertionRun], None] | None = None,
                 max_particles: int | None = MAX_PARTICLES, accuracy: float | None = None):
        self.scenario = scenario
        self.on_trial = on_trial
        self.max_particles = max_particles
        self.accuracy = accuracy
        self.runs: list[InsertionRun] = []

    def particles(self, h: float) -> int:
        """The guard's particle count of the graded scenario at needle spacing h."""
        return model_size(graded_scenario(self.scenario, h, SAFE_TRACKING, SAFE_SOLVER)).particles

    def allowed(self, h: float) -> bool:
        return self.max_particles is None or self.particles(h) <= self.max_particles

    def finest_allowed(self, coarsest: float) -> float:
        """The finest needle spacing (down to coarsest / 2^(MAX_HALVINGS + 2), the finest
        the search may try) whose model stays within the particle limit."""
        finest = coarsest / 2 ** (MAX_HALVINGS + 2)
        if self.allowed(finest):
            return finest
        low, high = finest, coarsest  # low refused, high allowed (the caller ran it)
        for _ in range(10):  # to ~0.5 % of the spacing range
            middle = (low * high) ** 0.5
            low, high = (low, middle) if self.allowed(middle) else (middle, high)
        return high

    def run(self, purpose: str, h: float, tracking: str, solver: str) -> InsertionRun:
        """The graded scenario at needle spacing h with these methods, run (or the earlier
        run of the same configuration). A model beyond the particle limit is refused."""
        for done in self.runs:
            if (done.spacing, done.tip_tracking, done.linear_solver) == (h, tracking, solver):
                return done
        if not self.allowed(h):
            raise InputError(
                f"discretization.accuracy: got {self.accuracy:g} mm, expected an accuracy the model "
                f"reaches within {self.max_particles} particles (the next trial, needle spacing "
                f"{h:.3g} mm, needs about {self.particles(h)}): ask for a looser accuracy, or raise "
                "--max-particles")
        trial = run_timed(InsertionRun(purpose, f"{purpose} h={h:g} mm {tracking}/{solver}",
                                       graded_scenario(self.scenario, h, tracking, solver), h))
        self.runs.append(trial)
        log.info("auto discretization: %s run h=%.3g mm %s/%s: %s %.2f s", purpose, h, tracking, solver,
                 trial.status, trial.wall_seconds)
        if self.on_trial is not None:
            self.on_trial(trial)
        return trial


def _deviation(a: InsertionRun, b: InsertionRun) -> float:
    return exit_deviations(a.result, b.result)["deviation_mm"]


# --- the steps ---------------------------------------------------------------------------


def first_resolution(trials: Trials, radius: float) -> tuple[float, InsertionRun]:
    """The first needle spacing h (R/3, halved up to MAX_HALVINGS times until a run
    succeeds) and its run with the safe methods."""
    h = round(radius / 3.0, 4)
    safe = trials.run("resolution", h, SAFE_TRACKING, SAFE_SOLVER)
    while not safe.ok and h > radius / 3.0 / 2 ** MAX_HALVINGS:
        h = round(h / 2, 4)
        safe = trials.run("resolution", h, SAFE_TRACKING, SAFE_SOLVER)
    if not safe.ok:
        raise InputError(f"discretization.accuracy: no auto discretization runs ({safe.reason})")
    return h, safe


def choose_tip_tracking(trials: Trials, h: float, safe: InsertionRun, accuracy: float) -> tuple[str, str]:
    """`auto` when the inverse gradient needs no fallback at h, its exit lies within
    accuracy/4 of Levenberg-Marquardt's (the `safe` run) and it is faster; with the reason."""
    trial = trials.run("tip tracking", h, "auto", SAFE_SOLVER)
    if not trial.ok:
        reason = f"inverse gradient failed at h={h:g} mm: {trial.reason.split(':')[0]}"
    elif fallbacks := events_of(trial.result, EventKind.TIP_TRACKING_FALLBACK):
        reason = f"inverse gradient needed {len(fallbacks)} fallbacks at h={h:g} mm"
    elif (gap := _deviation(trial, safe)) > accuracy / 4:
        reason = f"inverse gradient's exit {gap:.3g} mm from Levenberg-Marquardt's"
    elif trial.wall_seconds >= safe.wall_seconds:
        reason = "inverse gradient not faster"
    else:
        return "auto", (f"inverse gradient safe: exit within {gap:.2g} mm of Levenberg-Marquardt's, "
                        f"{safe.wall_seconds / trial.wall_seconds:.2g}x faster")
    return SAFE_TRACKING, "safe choice; " + reason


def choose_linear_solver(trials: Trials, h: float, tracking: str, accuracy: float) -> tuple[str, str]:
    """`minres` when it needs no fallback to the direct solve at h, agrees with it
    (accuracy/10) and is at least 20 % faster; with the reason."""
    direct = trials.run("resolution", h, tracking, "direct")
    if not direct.ok:  # the ladder's first run then says why
        return "direct", f"the direct solve failed at h={h:g} mm: {direct.reason.split(':')[0]}"
    trial = trials.run("linear solver", h, tracking, "minres")
    if not trial.ok:
        return "direct", f"MINRES failed at h={h:g} mm: {trial.reason.split(':')[0]}"
    if events_of(trial.result, EventKind.MINRES_FALLBACK):
        return "direct", f"MINRES fell back to the direct solve at h={h:g} mm"
    if _deviation(trial, direct) > accuracy / 10:
        return "direct", "MINRES and the direct solve disagree"
    if trial.wall_seconds > 0.8 * direct.wall_seconds:
        return "direct", (f"direct faster: {direct.wall_seconds:.2f} s against MINRES "
                          f"{trial.wall_seconds:.2f} s at h={h:g} mm")
    return "minres", f"MINRES {direct.wall_seconds / trial.wall_seconds:.2g}x faster than direct at h={h:g} mm"


@dataclass
class ErrorEstimate:
    """e(h') ~ constant h'^p from the pair of runs at h and h/2 (module docstring)."""

    h: float  # needle spacing of the pair's coarser run, mm
    fine: InsertionRun  # the run at h/2
    difference: float  # mm, between the pair's exit points
    constant: float  # C of e(h') ~ C h'^p
    first: bool  # the ladder's first pair (the ladder may then reach up to 2 h)

    def at(self, spacing: float) -> float:
        return self.constant * spacing ** ASSUMED_ORDER

    @property
    def basis(self) -> str:
        return (f"runs at needle spacing {self.h:.3g} and {self.h / 2:.3g} mm differ by {self.difference:.3g} mm, "
                f"order {ASSUMED_ORDER:g} assumed")


def estimate_error(trials: Trials, h: float, tracking: str, solver: str, accuracy: float) -> ErrorEstimate:
    """The resolution ladder: pairs (h, h/2) with the chosen methods, halved while the
    accuracy lies beyond one more halving (e(h/4) > accuracy), at most MAX_HALVINGS times."""
    coarse = trials.run("resolution", h, tracking, solver)
    if not coarse.ok:
        raise InputError(f"discretization.accuracy: the auto discretization's first run failed ({coarse.reason})")
    estimate = None
    first = True
    for _ in range(MAX_HALVINGS):
        fine = trials.run("resolution", round(h / 2, 4), tracking, solver)
        if not fine.ok:
            break
        difference = _deviation(coarse, fine)
        constant = difference / (h ** ASSUMED_ORDER * (1.0 - 2.0 ** -ASSUMED_ORDER))  # e(h') ~ C h'^p
        estimate = ErrorEstimate(h, fine, difference, constant, first)
        unreachable(trials, estimate, accuracy)
        # extrapolate at most one halving beyond the pair; halve the pair when the target lies further
        if estimate.at(h / 4) <= accuracy:
            break
        h, coarse, first = h / 2, fine, False
    if estimate is None:
        raise InputError(f"discretization.accuracy: no two resolutions ran to estimate the error "
                            f"(h = {h / 2:.3g} mm: {fine.reason})")
    return estimate


def unreachable(trials: Trials, estimate: ErrorEstimate, accuracy: float) -> None:
    """Refuse an accuracy the finest model within the particle limit does not reach by the
    estimate (the search would otherwise halve on until it hits the limit or its last
    halving)."""
    if trials.max_particles is None:
        return
    floor = trials.finest_allowed(estimate.h)
    reachable = estimate.at(floor)
    if reachable > accuracy:
        raise InputError(
            f"discretization.accuracy: got {accuracy:g} mm, expected at least {reachable:.2g} mm: the "
            f"finest model within {trials.max_particles} particles (needle spacing {floor:.3g} mm) "
            f"reaches an estimated {reachable:.2g} mm ({estimate.basis}); ask for a looser accuracy, "
            "or raise --max-particles")


def pick_resolution(trials: Trials, estimate: ErrorEstimate, tracking: str, solver: str,
                    accuracy: float) -> InsertionRun:
    """The run at the largest spacing on a 2^(1/4) ladder whose estimated error meets the
    accuracy: between h/2 and h/4, or up to 2h coarser than the pair when it is the first
    one. Falls back to the pair's finer run when that run fails."""
    h = estimate.h
    ladder = tuple(2.0 ** (-k / 4) for k in range(-4 if estimate.first else 0, 9))
    target = next((round(h * f, 4) for f in ladder if estimate.at(h * f) <= accuracy), round(h / 4, 4))
    candidate = trials.run("chosen", target, tracking, solver)
    chosen = candidate if candidate.ok else estimate.fine
    if chosen.family == "resolution":
        chosen.family = "chosen"
    return chosen


# --- the selection -------------------------------------------------------------------------


def choose_discretization(scenario: Scenario, accuracy: float, tip_tracking: str | None = None,
                          linear_solver: str | None = None,
                          on_trial: Callable[[InsertionRun], None] | None = None,
                          max_particles: int | None = MAX_PARTICLES) -> AutoChoice:
    """The cheapest graded discretization (and methods) whose estimated exit-point error is
    at most `accuracy` mm; see the module docstring. Explicit tip_tracking/linear_solver are
    kept as given; no trial model exceeds `max_particles` (None: no limit)."""
    if scenario.needle is None:
        raise InputError("discretization.accuracy: needs a needle (the accuracy is on its exit point)")
    if not accuracy > 0:
        raise InputError(f"discretization.accuracy: got {accuracy!r}, expected a positive distance (mm)")
    trials = Trials(scenario, on_trial, max_particles, accuracy)
    h, safe = first_resolution(trials, scenario.needle.radius)
    # methods, on the cheapest pair's discretization
    tracking, tracking_reason = ((tip_tracking, "given") if tip_tracking is not None
                                 else choose_tip_tracking(trials, h, safe, accuracy))
    solver, solver_reason = ((linear_solver, "given") if linear_solver is not None
                             else choose_linear_solver(trials, h, tracking, accuracy))
    # resolution ladder with the chosen methods, then the final pick
    estimate = estimate_error(trials, h, tracking, solver, accuracy)
    chosen = pick_resolution(trials, estimate, tracking, solver, accuracy)
    return AutoChoice(
        accuracy=accuracy, estimate_mm=estimate.at(chosen.spacing), estimate_basis=estimate.basis,
        scenario=chosen.scenario, needle_spacing=chosen.spacing, tip_tracking=tracking, linear_solver=solver,
        result=chosen.result, cpu_seconds=chosen.cpu_seconds,
        selection_seconds=sum(t.wall_seconds for t in trials.runs), trials=trials.runs,
        reasons={"tip_tracking": tracking_reason, "linear_solver": solver_reason},
        verified=estimate.at(estimate.h / 4) <= accuracy)


def resolve_accuracy(scenario: Scenario, tip_tracking: str | None = None,
                     linear_solver: str | None = None,
                     max_particles: int | None = MAX_PARTICLES) -> tuple[Scenario, Event | None]:
    """The scenario with the auto discretization in place of `accuracy`, and the note that
    says what was chosen and why (None when the scenario gives no accuracy). Called once,
    before a run: every insertion of a `plan` then uses the same model."""
    if scenario.discretization.accuracy is None:
        return scenario, None
    choice = choose_discretization(scenario, scenario.discretization.accuracy, tip_tracking, linear_solver,
                                   max_particles=max_particles)
    note = Event(EventKind.AUTO_DISCRETIZATION, choice.message)
    return replace(choice.scenario, source_text=scenario.source_text, name=scenario.name), note
