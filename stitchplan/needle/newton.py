"""The parts of a needle step's Newton solve (NeedleInsertion._newton, needle/equilibrium.py):
its tolerances (newton_tolerances) and tuning constants, when the kept factor of K + H is
renewed (renew_factor), the residuals of eq. 3.62 at one iterate (Residuals) and how far they
are from equilibrium (Balance), and what one solve remembers from its earlier iterations
(NewtonHistory), among them the Anderson mixing of its modified Newton steps
(AndersonMixing; Walker and Ni 2011).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from ..config import Scenario
from .geometry import length
from .steering import CenterAim

# a needle step's Newton tolerances (|r_u| / |f_needle|, |g| / R) by coupling, where the
# scenario's solver block leaves them unset. The mortar coupling's leave at most 1.4e-4 mm in
# the exit points of the shipped needle scenes, their verification replays and SH 1/2 on
# uniform 4 and 6 mm particles, 7x below the planner's 0.001 mm tolerance, in 0.6x the
# Newton iterations of 5e-6 and 1e-9 (benchmarks/results/solver_tolerance.md). The point
# coupling's constraint rows become nearly dependent where several needle points share a
# particle spacing, and the same residual then leaves more (5.4e-4 mm on the 4 mm particles,
# 0.014 mm on the 6 mm ones; 2.3e-5 and 0.0067 mm at 1e-4): it keeps 5e-6 and 1e-9.
NEWTON_TOLERANCES = {"mortar": (1e-3, 1e-7), "points": (5e-6, 1e-9)}
ANDERSON_DEPTH = 5  # steps mixed by the accelerated modified Newton (AndersonMixing)
# with the centre prescribed (unplanned runs, replays of a trajectory) the same depth so far: a
# depth of 1 took 2 % fewer iterations over the refined replays of the shipped trajectories and 6 %
# over those at twice the spacing, 1.6-6 % less time on six of the seven refined replays and 2 % more
# on wound_closure's (benchmarks/results/anderson_depth.md), but it moves the exit errors by up to
# 1.5e-4 mm, within the needle steps' tolerances, past the regression pins and the sample runs,
# which would be re-pinned and regenerated with it
FIXED_CENTER_ANDERSON_DEPTH = ANDERSON_DEPTH
STALE_CENTER_MOVES = 10.0  # d(d, lambda)/dC is re-solved while the centre moves more than this x tolerance
REFACTOR_CONTRACTION = 0.5  # a planner's step renews the factor of K + H below this contraction (renew_factor)
FRESH_FACTOR_LOSSES = 2  # steps on a fresh factor that may raise the residual before a solve gives up (_newton)


def newton_tolerances(scenario: Scenario) -> tuple[float, float]:
    """A needle step's Newton tolerances (|r_u| / |f_needle|, |g| / R): the solver block's,
    or NEWTON_TOLERANCES of the scenario's coupling where it leaves them unset."""
    residual, constraint = NEWTON_TOLERANCES[scenario.needle.coupling]
    solver = scenario.solver
    return (residual if solver.needle_residual_tolerance is None else solver.needle_residual_tolerance,
            constraint if solver.needle_constraint_tolerance is None else solver.needle_constraint_tolerance)


def renew_factor(measure: float, previous: float, earlier: float, planned: bool) -> bool:
    """Whether the modified Newton iteration renews the factor of K + H, from its
    convergence measure now, one and two iterations back. A planner's step (`planned`)
    renews it when an iteration contracts by less than REFACTOR_CONTRACTION. With the
    centre prescribed (unplanned runs, replays) only when the measure exceeds both of the
    last two (the iteration lost ground over two iterations): with Anderson mixing the
    iteration on an older factor still converges, if more slowly, and on the refined models a
    factorization costs tens of iterations (benchmarks/plan_speed.py, the replays' table: on
    the wound's replay at 0.75 mm the planner's rule renews it three times, which costs more
    than the 58 iterations they save). The planner's steps keep the faster renewal: changing
    it moves their plans within the planner's tolerance, which the shipped plans and pins
    would then have to follow."""
    if planned:
        return measure > REFACTOR_CONTRACTION * previous
    return measure > previous and measure > earlier


@dataclass(frozen=True)
class Residuals:
    """The residuals of eq. 3.62 at one state, with what their linearisation needs."""

    residual: np.ndarray  # r_u = f_int - f_needle + G lambda, (2 n_free,)
    violation: np.ndarray  # g_j, one per multiplier (coupling.ConstraintValues), (m,)
    normal: np.ndarray  # n_q at the constraint quadrature's points, (Q, 2)
    rho: np.ndarray  # |x_q - C|, (Q,)
    needle_force: float  # |f_needle|, N

    @property
    def worst_violation(self) -> float:
        return float(np.abs(self.violation).max()) if len(self.violation) else 0.0


class AndersonMixing:
    """Anderson acceleration of the modified Newton iteration x <- x + f(x), f the step
    solved with an older factor of K + H (Walker and Ni 2011, type II): the next step is
    the combination of the last `depth` steps whose linearised step is smallest, which for
    a linear problem is GMRES on the old-factor-preconditioned system. Modified Newton
    contracts by ~0.1-0.2 per iteration on the needle scenes; mixing makes it superlinear
    without refactorizing."""

    def __init__(self, depth: int):
        self.depth = depth
        self.reset()

    def reset(self) -> None:
        self._last: tuple[np.ndarray, np.ndarray] | None = None
        self._states: list[np.ndarray] = []
        self._steps: list[np.ndarray] = []

    def step(self, state: np.ndarray, step: np.ndarray) -> np.ndarray:
        """The accelerated increment at `state` given the plain step f(state)."""
        if self.depth == 0:
            return step
        if self._last is not None and len(self._last[0]) == len(state):
            self._states.append(state - self._last[0])
            self._steps.append(step - self._last[1])
            del self._states[:-self.depth], self._steps[:-self.depth]
        self._last = (state, step.copy())  # the plain step, whatever the caller does to the one returned
        if not self._steps:
            return step
        steps = np.column_stack(self._steps)
        gamma = np.linalg.lstsq(steps, step, rcond=1e-10)[0]
        return step - (np.column_stack(self._states) + steps) @ gamma


@dataclass(frozen=True)
class Balance:
    """How far one Newton iterate is from equilibrium (NeedleInsertion._balance; converged as
    needle/equilibrium.py's docstring says)."""

    residual_norm: float  # |r_u|, N
    worst: float  # max |g|, mm
    needle_force: float  # |f_needle|, N
    finite: bool  # |r_u| and |f_needle| finite
    forces_balance: bool  # |r_u| within its tolerance
    balanced: bool  # and every |g| within its own

    @functools.cached_property
    def measure(self) -> float:
        """The convergence measure |r_u| / |f_needle| + max |g| (renew_factor)."""
        return self.residual_norm / max(self.needle_force, 1e-12) + self.worst


@dataclass
class NewtonHistory:
    """What one Newton solve of a needle step (NeedleInsertion._newton) remembers from its
    earlier iterations: the convergence measure at the last two direct solves (when to renew
    the kept factor of K + H), the measure where a fresh factor was made and the steps on one
    that raised it (when to give up), the Anderson mixing of the modified Newton steps, and in
    a planner's step (`planned`: the centre an unknown, Algorithm 2) d(d, lambda)/dC and the last
    centre move."""

    planned: bool
    previous: float = math.inf  # the convergence measure at the last direct solve (inf after a centre move)
    earlier: float = math.inf  # and at the one before
    factored_at: float | None = None  # the measure where the last step's factor was made
    losses: int = 0  # steps on a fresh factor that raised the residual
    per_center: np.ndarray | None = None  # d(d, lambda)/dC (n + m, 2)
    moved: float = math.inf  # the last centre move, mm
    minres_iterations: int = 0

    def __post_init__(self) -> None:
        self.mixing = AndersonMixing(ANDERSON_DEPTH if self.planned else FIXED_CENTER_ANDERSON_DEPTH)

    def lost_fresh_factor(self, measure: float, forces_balance: bool) -> bool:
        """Whether the solve gives up: the step on a freshly made factor raised the measure above
        where it was made (the forces not yet balanced), for the FRESH_FACTOR_LOSSES-th time."""
        if self.factored_at is not None and measure > self.factored_at and not forces_balance:
            self.losses += 1
            if self.losses >= FRESH_FACTOR_LOSSES:
                return True
        self.factored_at = None
        return False

    def stale_center_columns(self, tolerance: float) -> bool:
        """Whether d(d, lambda)/dC is to be solved (again): not yet, or the centre moved more than
        STALE_CENTER_MOVES x `tolerance`."""
        return self.per_center is None or self.moved > STALE_CENTER_MOVES * tolerance

    def renew(self, measure: float) -> bool:
        """Whether the direct solve at `measure` renews the factor of K + H: kept while Newton
        contracts fast, renewed when it slows (renew_factor)."""
        refactor = renew_factor(measure, self.previous, self.earlier, self.planned)
        if refactor and not self.planned:  # a Newton step on the tangent here, which must not lose
            self.factored_at = measure
        self.earlier = self.previous
        return refactor

    def solved_directly(self, measure: float, refactor: bool) -> None:
        if refactor or measure > self.previous:
            self.mixing.reset()  # another iteration map (new factor), or a step that failed
        self.previous = measure

    def moved_center(self, move: np.ndarray, tolerance: float) -> None:
        self.moved = length(move)
        if self.moved > tolerance:
            self.previous = math.inf  # the next residual measures the move, not the factor

    def mix(self, free: np.ndarray, multipliers: np.ndarray, center: np.ndarray, step: np.ndarray,
            aim: CenterAim | None) -> np.ndarray:
        """The modified Newton `step` at the iterate mixed with the earlier ones (AndersonMixing);
        with `aim` (steering) the mixed centre kept within the move limits."""
        mixed = self.mixing.step(np.concatenate([free, multipliers, center]), step)
        if aim is not None:
            mixed[-2:] = aim.feasible(center + mixed[-2:]) - center
        return mixed
