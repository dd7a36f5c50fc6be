"""The state of one needle insertion and its constrained equilibrium (thesis eq. 3.59-3.65).

The state is the tissue's free coefficients, the needle track Gamma_N with its multipliers
(one per needle point, or the nodal values of the mortar multiplier field) and the needle
centre C. After each needle point is added, Newton brings the tissue to equilibrium on the
saddle-point system of eq. 3.62,

    r_u = f_int(d) - f_needle(d) + G(d) lambda = 0,    g(d) = 0,

under friction along the inserted needle and the cutting force at its tip (needle/coupling.py).

Algorithm 1's ramp: the step's load (the new segment's friction and the cutting force moved
to the new tip) is first applied whole; when Newton fails (no convergence, or det F <= 0
somewhere) the increment is halved down to RAMP_SMALLEST of the step's load, and doubled
again after each success. Equilibrium of the hyperelastic tissue does not depend on the
path, so a ramped step ends where the whole load would have (tests/test_simulation.py).
A step whose load cannot be carried stops the run with an InsertionFailure naming the step,
the angle and the share carried, whether the tissue gave way (the tangent's least stiffness on
the needle's constraints fallen over the step or negative, and where: needle/stability.py) or
Newton failed, and for Saint Venant-Kirchhoff its compression instability.
With the centre prescribed, Newton gives up on an increment once FRESH_FACTOR_LOSSES steps on
a freshly factored tangent have raised the residual, rather than refactoring on to its last
iteration: such steps go astray near an instability, and on the larger models each
factorization of an indefinite K + H costs seconds.

Converged means |r_u| <= needle_residual_tolerance x |f_needle| and every |g| <=
needle_constraint_tolerance x R (config Solver; NEWTON_TOLERANCES where they are unset).

The tangent is K + H, symmetric: the follower loads' own stiffness (friction and cutting force
turn with the needle's tangent at their points) is left out, so that K + H is factored by
Cholesky and kept over iterations. Measured with it in (benchmarks/results/entry_newton.md, the
full Jacobian LU-factored at every iteration): sh12_100x100 takes 76 Newton iterations instead
of 120 but 3.6 s instead of 0.3 s, the exit within 6e-6 mm; the 2.5 mm soft slab at a quarter
spacing stops at the same step and load, where Newton's linear model holds for 5 % of its step
and no equilibrium is found past 88.75 % of the step's load (a limit point: the tissue, not Newton).
"""

from __future__ import annotations

import functools
import logging
import math
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..config import Scenario, Solver
from ..config.boundary_points import shown_point
from ..errors import (ConstraintStall, InputError, InsertionFailure, InvertedMaterial, NewtonExhausted, NonFiniteResidual,
                      UnstableEquilibrium)
from ..events import Event, EventKind
from ..tissue.assembly import Assembler, stiffness_at_rest
from ..tissue.factorization import Factor, condition_estimate, factorize
from ..tissue.model import TissueModel, build_tissue_model
from ..tissue.solver import checked
from .coupling import NeedleCoupling
from .geometry import IDENTITY, length, needle_zone, orthogonal, scenario_needle
from .results import Snapshot
from .saddle_point import SaddlePointSolver, condition_numbers
from .stability import SoftestMode, mode_peak, softest_mode
from .steering import CenterAim

log = logging.getLogger(__name__)

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
CENTER_COLUMNS_ON_ROWS = True  # d(d, lambda)/dC from the kept K^-1 E^T where the coupling allows (_center_columns)
REFACTOR_CONTRACTION = 0.5  # a planner's step renews the factor of K + H below this contraction (renew_factor)
RAMP_SMALLEST = 1.0 / 64.0  # Algorithm 1's ramp: the smallest load increment tried within a step
# K0's condition number (condition_estimate) above which a discretization is refused as
# nearly singular: its solves then keep fewer than 4 of double precision's 16 digits. 1e4 at
# dilation 2 on SH 1/2, 4e6 at 3, 2e10 at 3.5 and 5e15 at 4 (benchmarks/results/dilation_conditioning.md)
STIFFNESS_CONDITION = 1e12
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
    violation: np.ndarray  # g_k = |x_k - C| - R, (k,)
    normal: np.ndarray  # n_k, (k, 2)
    rho: np.ndarray  # |x_k - C|, (k,)
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
class _Balance:
    """How far one Newton iterate is from equilibrium (NeedleInsertion._balance; converged as
    the module docstring says)."""

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
class _NewtonHistory:
    """What one Newton solve of a needle step (NeedleInsertion._newton) remembers from its
    earlier iterations: the convergence measure at the last two direct solves (when to renew
    the kept factor of K + H), the measure where a fresh factor was made and the steps on one
    that raised it (when to give up), the Anderson mixing of the modified Newton steps, and in
    a planner's step (`planned`: the centre an unknown, eq. 4.1) d(d, lambda)/dC and the last
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


def tissue_key(scenario: Scenario) -> tuple:
    """What a scenario's tissue model depends on (PreparedTissue)."""
    scenario = orthogonal(scenario)
    return scenario.tissue, scenario.discretization, scenario.needle


class PreparedTissue:
    """What every insertion into one scenario's tissue at one discretization starts from: the
    tissue model, the shape functions at the particles, and K0 (the tangent at rest, eq. 3.72)
    with its factor. Each insertion starts at rest with no multipliers, where K + H = K0, so
    its first saddle solves use this factor (SaddlePointSolver.start_at_rest). Made once per
    command and handed to each run on the same model (the planner's passes, the unplanned
    comparison, the verification's rounds); the model is built by the first run, K0's factor
    when first asked for. `model`: one built elsewhere instead (a finite-element model of the
    same tissue: benchmarks/needle_fem_reference.py)."""

    def __init__(self, scenario: Scenario, model: TissueModel | None = None):
        self.scenario = scenario
        # the model depends on these alone (the needle's: where the particles are graded, the
        # same for every lean of the needle at entry)
        self.key = tissue_key(scenario)
        self.seconds = 0.0  # building the model
        self._model, self._factor = model, None
        self.boundary_samples = None  # the boundary sampled at rest (tip_tracking.boundary_samples), once needed

    @property
    def built(self) -> bool:
        return self._model is not None

    @property
    def model(self) -> TissueModel:
        self._build()
        return self._model

    def _build(self) -> None:
        if self._model is None:
            start = time.perf_counter()
            self._model = build_tissue_model(self.scenario.tissue, self.scenario.discretization,
                                             needle_zone=needle_zone(self.scenario))
            self.seconds = time.perf_counter() - start

    def fits(self, scenario: Scenario) -> bool:
        """Whether `scenario` has this tissue, discretization and needle (leaning or not)."""
        return self.key == tissue_key(scenario)

    def stiffness_at_rest(self) -> sp.csr_matrix:
        """K0 (tissue.assembly.stiffness_at_rest)."""
        return stiffness_at_rest(self.model)

    @property
    def factorized(self) -> bool:
        return self._factor is not None

    def factor_at_rest(self) -> Factor:
        """The factor of K0, made the first time it is asked for; InputError where K0 is
        nearly singular (refuse_singular_stiffness)."""
        if self._factor is None:
            stiffness = self.stiffness_at_rest()
            factor = factorize(stiffness, symmetric_positive=True)
            refuse_singular_stiffness(condition_estimate(stiffness, factor), self.scenario.discretization,
                                      self.model.particles, self.model.support / self.scenario.discretization.dilation)
            self._factor = factor
        return self._factor


def refuse_singular_stiffness(condition: float, discretization, particles: np.ndarray | None = None,
                              local_spacing: np.ndarray | None = None) -> None:
    """Raise InputError where K0's `condition` number exceeds STIFFNESS_CONDITION. With a
    linear basis on evenly spaced particles the RK shape functions are the cubic-spline
    kernel's translates, and the kernel's Fourier transform, (sin(k a / 4) / (k a / 4))^4 per
    direction, vanishes at the particles' alternating mode (k = pi / spacing) for a = 4
    spacings: at dilation 4 that mode's coefficients make no displacement, and from ~3 on
    they make almost none. Newton then stalls on such a model (sh12_100x100 at dilation 4
    and half its spacing ran for more than 10 minutes at step 1). At a dilation of 3 or less
    (~1e4 at 2, ~2e6 at 3 on sh12_100x100: benchmarks/results/dilation_conditioning.md) the
    kernels are not the cause: particles closer together than their spacing are, the same
    alternating mode over half the distance (hole_near_stitch at 0.75 mm had ~3e13 from
    boundary particles added between the lattice's own along its top edge), and the advice
    is about those, not the dilation: with the `particles` (n, 2) and their `local_spacing`
    (n,), the line names the pair closest for their spacing, where to look."""
    if not condition > STIFFNESS_CONDITION:
        return
    estimate = f"~{condition:.0e}" if math.isfinite(condition) else "infinite to rounding"
    found = (f"discretization: dilation {discretization.dilation:g} with spacing {discretization.spacing:g} mm "
             f"makes the tissue's stiffness nearly singular (condition number {estimate}, estimated; ~1e4 at "
             f"dilation 2; above {STIFFNESS_CONDITION:.0e} its solves keep fewer than 4 of 16 digits)")
    if discretization.dilation > 3:
        raise InputError(f"{found}: kernels wider than ~3 spacings make the particles' coefficients nearly "
                         "dependent; use a dilation of 3 or less (2 is the default)")
    where = "" if particles is None or local_spacing is None else _closest_for_spacing(particles, local_spacing)
    raise InputError(f"{found}: at a dilation of 3 or less the kernels are not the cause; particles closer "
                     "together than the spacing are, likely where the boundary crowds them (a sharp corner, "
                     f"tissue or boundary features thinner than the spacing){where}; try another spacing, or "
                     "change the shape there")


def _closest_for_spacing(particles: np.ndarray, local_spacing: np.ndarray) -> str:
    """'; the particles closest for their spacing are d mm apart at [x, y] (f of the local
    spacing, h mm)': the pair whose distance over the smaller of their spacings is least."""
    from scipy.spatial import cKDTree

    if len(particles) < 2:
        return ""
    distance, index = cKDTree(particles).query(particles, k=2)
    neighbour = index[:, 1]
    spacing = np.minimum(local_spacing, local_spacing[neighbour])
    k = int(np.argmin(distance[:, 1] / spacing))
    middle = 0.5 * (particles[k] + particles[neighbour[k]])
    return (f"; the particles closest for their spacing are {distance[k, 1]:.3g} mm apart at {shown_point(middle)} "
            f"({distance[k, 1] / spacing[k]:.2g} of the local spacing, {spacing[k]:.3g} mm)")


class NeedleInsertion:
    """The state of one insertion and the steps that change it: `add_point`, `equilibrate`,
    `move_center`; `center_sensitivity` linearises the equilibrium in the centre."""

    def __init__(self, scenario: Scenario, linear_solver: str | None = None, tip_tracking: str | None = None,
                 tissue: PreparedTissue | None = None):
        self.geometry = scenario_needle(scenario)  # refuses a scenario without a needle
        if scenario.discretization.integration != "gauss":
            raise InputError(f"discretization.integration: got {scenario.discretization.integration!r}, "
                             "expected 'gauss' for simulate and plan (the needle's saddle-point solvers "
                             "need the symmetric Galerkin tangent; vci is for deform and calibrate)")
        self.scenario = scenario
        self.needle = scenario.needle
        self.domain = scenario.tissue.domain
        self.linear_method = linear_solver or self.needle.linear_solver
        self.tip_tracking = tip_tracking or self.needle.tip_tracking
        self.timings = {"discretization": 0.0, "assembly": 0.0, "solve": 0.0, "tip_tracking": 0.0}
        self.events: list[Event] = []
        self._told_steered_direct = False  # that the planner's steps solve directly (once per run)
        tissue = self.tissue = tissue or PreparedTissue(scenario)
        if not tissue.fits(scenario):
            raise ValueError("a prepared tissue of another scenario's tissue or discretization")
        built_here = not tissue.built
        self.model = tissue.model
        if built_here:
            self.timings["discretization"] += tissue.seconds
        self.assembler = Assembler(self.model)
        self._last_internal: tuple[np.ndarray, np.ndarray] | None = None  # (free, f_int): _internal_force
        self.coupling = NeedleCoupling(self.model, self.geometry, self.needle, scenario.discretization.dilation)
        self.saddle = SaddlePointSolver(tissue.factor_at_rest)
        if self.linear_method == "direct":
            self.saddle.start_at_rest(made_here=not tissue.factorized)
        else:
            self.saddle.precondition_at_rest(made_here=not tissue.factorized)
        self.free = np.zeros((self.model.n_free, 2))
        self._coefficients: tuple[np.ndarray | None, np.ndarray | None] = (None, None)  # (free, T free)
        self.multipliers = np.zeros(0)
        self.center = self.geometry.center.copy()
        self.last_violation = 0.0  # max |g_e| of the last converged equilibrium, mm
        self.newton_tolerances = newton_tolerances(scenario)  # (|r_u| / |f_needle|, |g| / R)
        self.residual_tolerance = self.newton_tolerances[0]
        self.constraint_tolerance = self.newton_tolerances[1] * self.geometry.radius  # mm
        self.ramp_increments = 0  # load increments beyond the first, over the run
        self._free_rows: dict[tuple[float, ...], np.ndarray] = {}
        # every Newton iteration of every solve (the planner's centre tries and failed ramp
        # increments included), and the solves
        self.newton_iterations = 0
        self.equilibrium_solves = 0

    # --- fields ------------------------------------------------------------------------------

    @property
    def points(self) -> np.ndarray:
        """Gamma_N, the needle points in the reference configuration, (k, 2)."""
        return self.coupling.points

    def coefficients(self) -> np.ndarray:
        """d = T free (NP, 2), kept while `free` is the same array (tip tracking asks at every
        evaluation; `free` is replaced after each solve, never changed in place)."""
        if self._coefficients[0] is not self.free:
            self._coefficients = (self.free, self.model.boundary.free_map @ self.free)
        return self._coefficients[1]

    def displacement(self, points: np.ndarray, gradient: bool = False):
        """u (n, 2) at reference points, and with `gradient` also grad u (n, i, J)."""
        # a probe outside the tissue (LM trying points past the exit) may lie outside every
        # kernel support: evaluate the field at the nearest tissue point instead
        points = self.domain.clip(np.atleast_2d(points))
        u, grad = self.model.field_at(points, self.coefficients(), gradients=gradient)
        return (u, grad) if gradient else u

    def free_rows(self, point: np.ndarray) -> np.ndarray:
        """N(X) T as a dense row (n_free,): u(X) = row @ free for one reference point, kept per
        point (the planner asks for the desired exit point's at every centre iteration; a dense
        row's product costs a tenth of a sparse one's on these models)."""
        key = tuple(np.asarray(point, dtype=float).ravel())
        rows = self._free_rows.get(key)
        if rows is None:
            clipped = self.domain.clip(np.atleast_2d(point))
            rows = self.model.free_rows_at(clipped).toarray()[0]
            self._free_rows[key] = rows
        return rows

    def point_displacement(self, point: np.ndarray) -> np.ndarray:
        """u (2,) at one reference point (free_rows)."""
        return self.free_rows(point) @ self.free

    def tip_displacement(self) -> np.ndarray:
        """u (2,) at the last needle point, from the row the coupling evaluated when adding it."""
        return self.coupling.tip_row @ self.free

    def particle_displacements(self) -> np.ndarray:
        """u (NP, 2) at the particles (a run records its coefficients: InsertionResult.displacements)."""
        return self.model.particle_shape_values() @ self.coefficients()

    # --- state -------------------------------------------------------------------------------

    def snapshot(self, coupling: bool = False) -> Snapshot:
        """The state now; with `coupling` also the needle coupling's (after a step: what a
        later run takes over)."""
        return Snapshot(self.free.copy(), self.multipliers.copy(), self.center.copy(), self.last_violation,
                        self.coupling.state() if coupling else None, self.saddle.state() if coupling else None)

    def restore(self, snapshot: Snapshot) -> None:
        self.free, self.multipliers = snapshot.free, snapshot.multipliers
        self.center, self.last_violation = snapshot.center, snapshot.violation

    def take_over(self, state: Snapshot) -> None:
        """The equilibrium an earlier run on this model reached after this step, from the same
        state before it, with the same tip point and centre: its needle coupling and state,
        instead of adding the point and solving the same equations again (run_insertion)."""
        self.coupling.restore(state.coupling)
        if state.solver is not None:  # else (a state from another process) this run's factor solves on
            self.saddle.restore(state.solver)
        self.restore(state)

    def move_center(self, center: np.ndarray) -> None:
        """Place the needle centre; the tissue follows at the next `equilibrate`."""
        self.center = np.asarray(center, dtype=float)

    def add_point(self, reference_point: np.ndarray, gap: bool = False, fraction: float = 1.0) -> None:
        """Append a needle point to Gamma_N; the multipliers carry over to the new constraint
        set (a new one starts at zero). The step's load starts at the previous step's.
        `gap`, `fraction`: see NeedleCoupling.add (a stitch across a wound)."""
        self.multipliers = self.coupling.add(reference_point, self.multipliers, gap, fraction)
        self.coupling.load_factor = 0.0

    # --- equilibrium -------------------------------------------------------------------------

    def residuals(self, free: np.ndarray, multipliers: np.ndarray, center: np.ndarray) -> Residuals:
        """r_u and g of eq. 3.62 at (free (n_free, 2), multipliers, centre)."""
        internal = self._internal_force(free)
        constraints, needle_force, constraint_force = self.coupling.residual_terms(free, multipliers, center)
        residual = internal - needle_force + constraint_force
        return Residuals(residual, constraints.violation, constraints.normal, constraints.rho,
                         length(needle_force))

    def _internal_force(self, free: np.ndarray) -> np.ndarray:
        """f_int at `free` (n_free, 2), the assembler updated to it. The last one is kept: a
        step's first residual is taken where the step before ended, at the displacements of
        that step's last residual (only the needle's terms differ)."""
        vector = free.reshape(-1)
        last = self._last_internal
        if last is not None and np.array_equal(last[0], vector):
            return last[1]
        gradient = (self.assembler.gradient @ vector).reshape(-1, 2, 2)  # grad u (nq, i, J)
        internal = self.assembler.update(checked(self.model, gradient + IDENTITY))
        self._last_internal = (vector.copy(), internal)
        return internal

    def _stiffness(self, multipliers: np.ndarray, state: Residuals):
        """K + H at the state the assembler was last updated to, built when a solver asks."""
        return lambda: self.assembler.tangent_matrix() + self.coupling.curvature(multipliers, state.normal, state.rho)

    def equilibrate(self, rotation: float, step: int, aim: CenterAim | None = None,
                    guess: Snapshot | None = None) -> tuple[int, int, float]:
        """Equilibrium under the step's full load about the current centre, reached by
        Algorithm 1's ramp when the load is not yet carried: the cutting force and the added
        friction (needle/coupling.py, load_factor beta) rise from the previous step's load in
        increments, first the whole, halved when Newton fails (step cutting) down to
        RAMP_SMALLEST, doubled again after a success. Returns (Newton iterations, MINRES
        iterations, max |g_e| in mm) summed over the increments.

        `guess`: where the step starts from an earlier, similar run on this model (the replay
        of a nearby centre path: run_insertion `start_from`). Newton starts there under the
        whole load; should it fail, the step starts again from the previous step's state."""
        coupling = self.coupling
        if guess is not None and guess.free.shape == self.free.shape \
                and guess.multipliers.shape == self.multipliers.shape:
            carried, load = self.snapshot(), coupling.load_factor
            self.free, self.multipliers = guess.free.copy(), guess.multipliers.copy()
            coupling.load_factor = 1.0
            try:
                return self._newton(rotation, step, aim)
            except InsertionFailure:
                self.restore(carried)
                coupling.load_factor = load
                self.saddle.forget()
                if aim is not None:
                    aim.restart()
                log.info("step %d (needle rotation %.3f rad): Newton from the earlier run's state failed; "
                         "starting again from the previous step's", step, rotation)
        if coupling.load_factor >= 1.0:
            return self._newton(rotation, step, aim)
        increment, newton, minres = 1.0, 0, 0
        carried = step_start = self.snapshot()
        while coupling.load_factor < 1.0:
            start = coupling.load_factor
            coupling.load_factor = min(1.0, start + increment)
            try:
                its, minres_its, worst = self._newton(rotation, step, aim)
                if increment < 1.0:  # a cut ramp: near an instability Newton may land on the unstable branch
                    self._refuse_unstable(rotation, step)
            except InsertionFailure as failure:
                coupling.load_factor = start
                self.restore(carried)
                self.saddle.forget()  # the factor of a failed iterate is no start for the next
                increment *= 0.5
                log.info("step %d (needle rotation %.3f rad): Newton failed at %.0f %% of the step's load; "
                         "the ramp goes on in increments of %.3g %%", step, rotation,
                         100 * min(1.0, start + 2 * increment), 100 * increment)
                if increment < RAMP_SMALLEST:
                    raise InsertionFailure(self._ramp_failure(rotation, step, start, failure, step_start)) from None
                self.ramp_increments += 1
                continue
            newton, minres = newton + its, minres + minres_its
            carried = self.snapshot()
            increment = min(1.0, 2.0 * increment)
        return newton, minres, worst

    def _refuse_unstable(self, rotation: float, step: int) -> None:
        """An UnstableEquilibrium where the state Newton reached has a negative least stiffness
        on the needle's constraints: the tissue would leave it, so the ramp takes a smaller
        increment (on the 2.5 mm neo-Hookean slab at a quarter spacing, step 16's increment to
        94 % of the load converged to such a state; in two halves it stays on the stable one,
        benchmarks/results/entry_stability.md)."""
        mode = self.softest_mode()
        if mode is not None and mode.stiffness < 0.0:
            raise UnstableEquilibrium(
                f"Newton reached an unstable state at step {step} (needle rotation {rotation:.3f} rad), "
                f"{100 * self.coupling.load_factor:.3g} % of the step's load: the tangent's least stiffness on the "
                f"needle's constraints is negative, {self._mode_place(mode)}")

    def _ramp_failure(self, rotation: float, step: int, carried: float, failure: InsertionFailure,
                      step_start: Snapshot) -> str:
        """What went wrong when even the smallest load increment fails, and what to try. The
        state is the last load carried; `step_start` the step's first."""
        message = (f"step {step} (needle rotation {rotation:.3f} rad): the needle's load could not be "
                   f"carried: {100 * carried:.0f} % of the step's cutting force and added friction held, "
                   f"the next {100 * RAMP_SMALLEST:.2g} % increment failed ({failure})")
        if isinstance(failure, (NonFiniteResidual, ConstraintStall)):  # not the material's doing
            return message
        iterations = self.scenario.solver.max_iterations
        if isinstance(failure, NewtonExhausted) and iterations < Solver().max_iterations:
            # Newton ran out of the few iterations it was given: no sign of the material's doing
            return message + (f"; solver.max_iterations is {iterations} (the default "
                              f"{Solver().max_iterations}): give Newton more iterations")
        message += self._stability_note(step_start)
        models = {self.scenario.tissue.material.model}
        models |= {region.material.model for region in getattr(self.scenario.tissue, "regions", None) or []}
        if "saint-venant-kirchhoff" in models:
            message += ("; Saint Venant-Kirchhoff is unstable under strong compression (its stress "
                        "turns back to zero as det F -> 0, so the tissue in front of the tip collapses): "
                        "use `model: neo-hookean`, which stiffens instead")
        return message

    def softest_mode(self) -> SoftestMode | None:
        """The least stiffness of the tangent on the needle's constraints at the current
        state, and its mode (needle/stability.py)."""
        state = self.residuals(self.free, self.multipliers, self.center)
        return softest_mode(self._stiffness(self.multipliers, state)(),
                            self.coupling.constraint_matrix(state.normal))

    def _stability_note(self, step_start: Snapshot) -> str:
        """Whether the tissue itself gave way where a step's load could not be carried: its
        least stiffness on the needle's constraints at the last load carried, negative (the
        state is unstable) or against the step's start (falling toward zero, a limit point,
        or not: Newton's failure), and where its mode moves the tissue most. Empty where the
        eigensolver does not answer or nothing of the step was carried to compare."""
        now = self.softest_mode()
        if now is None:
            return ""
        where = self._mode_place(now)
        if now.stiffness < 0.0:
            return (f"; the state carried is unstable: the tangent's least stiffness on the needle's constraints "
                    f"is negative, {where}: the tissue buckles or creases there, which the model does not follow "
                    "(the needle is a line and the tissue does not touch itself)")
        if np.array_equal(step_start.free, self.free):  # nothing of the step carried: nothing to compare
            return ""
        carried = self.snapshot()
        self.restore(step_start)
        before = self.softest_mode()
        self.restore(carried)
        if before is None or before.stiffness <= 0.0:
            return ""
        percent = round(100.0 * now.stiffness / before.stiffness)
        if percent < 100:
            return (f"; the tangent's least stiffness on the needle's constraints fell to {percent} % of the "
                    f"step's start (at zero the tissue has no stable equilibrium), {where}")
        return (f"; the tangent's least stiffness on the needle's constraints did not fall over the step "
                f"({percent} % of the step's start): the tissue is not softening, Newton's steps failed")

    def _mode_place(self, mode: SoftestMode) -> str:
        """`its mode largest at [x, y] mm`, the particle it moves most, with `, the needle's entry`,
        `tip` or `entry and tip`: those of the two (reference) within two of the particle's
        spacings of it."""
        particle = mode_peak(mode, self.model.boundary.free_map)
        near = 2.0 * self.model.support[particle] / self.scenario.discretization.dilation
        where = self.model.particles[particle]
        points = {"entry": self.geometry.entry, "tip": self.points[-1] if len(self.points) else None}
        names = [name for name, point in points.items()
                 if point is not None and length(where - np.asarray(point, dtype=float)) <= near]
        return f"its mode largest at {shown_point(where)} mm" + (f", the needle's {' and '.join(names)}" if names else "")

    def _newton(self, rotation: float, step: int, aim: CenterAim | None = None) -> tuple[int, int, float]:
        """Newton on the saddle-point system (eq. 3.62) at the current load, about the
        current centre or, with `aim`, with the centre as a third unknown (CenterAim, eq. 4.1).
        Each iteration: the residuals; converged?; a step of the linearised system, by MINRES
        (eq. 3.71-3.74) or on a kept factor of K + H renewed when Newton slows, whose steps are
        Anderson-mixed (Walker and Ni 2011); with `aim`, the centre's move; the update. What the
        iterations remember is a _NewtonHistory.
        Returns (Newton iterations, MINRES iterations, max |g_e| in mm)."""
        settings = self.scenario.solver
        free, multipliers, center = self.free.ravel().copy(), self.multipliers.copy(), self.center.copy()
        n_dof = len(free)
        history = _NewtonHistory(planned=aim is not None)
        for iteration in range(settings.max_iterations + 1):
            state = self._timed_residuals(free.reshape(-1, 2), multipliers, center, rotation, step)
            balance = self._balance(state)
            steering = aim is not None and aim.held is None
            log.debug("step %d (needle rotation %.3f rad), load %.3g, Newton iteration %d: residual %.3e N "
                      "(needle force %.3e N), constraint violation %.3e mm", step, rotation,
                      self.coupling.load_factor, iteration, balance.residual_norm, state.needle_force, balance.worst)
            if balance.balanced and not steering:
                self._accept(free, multipliers, center, balance.worst, iteration)
                return iteration, history.minres_iterations, balance.worst
            if iteration == settings.max_iterations or not balance.finite:
                break
            if history.lost_fresh_factor(balance.measure, balance.forces_balance):
                self._count(iteration)
                raise self._diverged(step, rotation, history.losses, balance)
            fresh = steering and history.stale_center_columns(aim.tolerance)
            rhs, on_rows = self._newton_rhs(state, free, multipliers, center, fresh)
            solution, modified = self._linear_step(state, multipliers, rhs, on_rows, balance, history, fresh,
                                                   steering, rotation, step)
            if fresh:
                solution, history.per_center = solution[:, 0], solution[:, 1:]
            if steering:
                solution = self._steer(aim, history, free, center, solution, balance.balanced)
                if solution is None:  # the centre has settled
                    self._accept(free, multipliers, center, balance.worst, iteration)
                    return iteration, history.minres_iterations, balance.worst
            else:
                solution = np.concatenate([solution, np.zeros(2)])  # the centre stays
            if modified:
                solution = history.mix(free, multipliers, center, solution, aim if steering else None)
            free, multipliers, center = free + solution[:n_dof], multipliers + solution[n_dof:-2], center + solution[-2:]
        self._count(iteration)
        raise self._not_converged(step, rotation, iteration, balance)

    def _balance(self, state: Residuals) -> _Balance:
        """How far the iterate of `state` is from equilibrium, against the step's tolerances."""
        residual_norm, worst = length(state.residual), state.worst_violation
        # a needle force so large that its norm overflows would make every residual look small
        finite = math.isfinite(residual_norm) and math.isfinite(state.needle_force)
        forces_balance = finite and residual_norm <= self.residual_tolerance * max(state.needle_force, 1e-6) + 1e-12
        balanced = forces_balance and worst <= self.constraint_tolerance
        return _Balance(residual_norm, worst, state.needle_force, finite, forces_balance, balanced)

    def _newton_rhs(self, state: Residuals, free: np.ndarray, multipliers: np.ndarray, center: np.ndarray,
                    fresh: bool) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
        """-(r_u, g) of eq. 3.62 and, where the centre's columns are to be solved again (`fresh`),
        the equilibrium's change per unit move of the centre: as columns beside it, or as the
        saddle solver's `on_rows` (_center_columns)."""
        rhs = -np.concatenate([state.residual, state.violation])
        on_rows = None
        if fresh:
            columns, on_rows = self._center_columns(free.reshape(-1, 2), multipliers, center, state)
            if columns is not None:
                rhs = np.column_stack([rhs, columns])
        return rhs, on_rows

    def _linear_step(self, state: Residuals, multipliers: np.ndarray, rhs: np.ndarray,
                     on_rows: tuple[np.ndarray, np.ndarray] | None, balance: _Balance, history: _NewtonHistory,
                     fresh: bool, steering: bool, rotation: float, step: int) -> tuple[np.ndarray, bool]:
        """The Newton step for `rhs` (its columns solved together), and whether it is a modified
        Newton step (_direct_step, to be mixed). By MINRES (eq. 3.71-3.74) where asked for and the
        centre is fixed, directly where MINRES stagnates; directly in the planner's steps (the
        centre's rows border the system MINRES is preconditioned for: _tell_steered_direct)."""
        t0 = time.perf_counter()
        solution, modified = None, False
        if balance.balanced and not fresh:  # steering in equilibrium: only the centre's move is left to check
            solution = np.zeros_like(rhs)
        elif self.linear_method == "minres" and not steering:
            constraints = self.coupling.constraint_matrix(state.normal)
            solution, its = self._minres_step(state, multipliers, constraints, rhs, rotation, step)
            history.minres_iterations += its
        elif self.linear_method == "minres" and not self._told_steered_direct:
            self._tell_steered_direct(step, rotation)
        if solution is None:
            solution, modified = self._direct_step(state, multipliers, rhs, on_rows, balance.measure, history), True
        self.timings["solve"] += time.perf_counter() - t0
        return solution, modified

    def _direct_step(self, state: Residuals, multipliers: np.ndarray, rhs: np.ndarray,
                     on_rows: tuple[np.ndarray, np.ndarray] | None, measure: float,
                     history: _NewtonHistory) -> np.ndarray:
        """The step by block elimination on the kept factor of K + H (SaddlePointSolver.solve_direct),
        renewed where Newton slows (_NewtonHistory.renew): a modified Newton step."""
        refactor = history.renew(measure)
        solution = self.saddle.solve_direct(self._stiffness(multipliers, state), rhs,
                                            refactor, self.coupling.expanded_rows,
                                            self.coupling.normal_weights(state.normal), on_rows)
        history.solved_directly(measure, refactor)
        return solution

    def _steer(self, aim: CenterAim, history: _NewtonHistory, free: np.ndarray, center: np.ndarray,
               solution: np.ndarray, balanced: bool) -> np.ndarray | None:
        """The step with the centre's move (CenterAim.update, eq. 4.1) appended, the equilibrium's
        part moved with it by d(d, lambda)/dC; None where the tissue is balanced and the centre
        settled or held."""
        n_dof = len(free)
        per_center = history.per_center
        move = aim.update(free, center, np.column_stack([solution[:n_dof], per_center[:n_dof]]),
                          self.free_rows(aim.exit_point), balanced)
        if balanced and move is None:
            return None
        move = np.zeros(2) if move is None else move
        history.moved_center(move, aim.tolerance)
        return np.concatenate([solution + per_center @ move, move])

    def _tell_steered_direct(self, step: int, rotation: float) -> None:
        """The event, once per run, that the planner's steps solve directly under `--linear-solver
        minres`: MINRES solves the symmetric saddle-point system; the centre as a third unknown
        (CenterAim) borders it with the exit's rows, which only the direct path takes."""
        message = ("the planner's steps solve directly, not by MINRES (--linear-solver minres): with the "
                   "centre as an unknown the Newton system is no longer the saddle-point system MINRES is "
                   "preconditioned for; MINRES solves the steps whose centre is fixed (simulate, the "
                   "replays)")
        self.events.append(Event(EventKind.MINRES_FALLBACK, message, step, rotation))
        self._told_steered_direct = True
        log.info(message)

    def _diverged(self, step: int, rotation: float, losses: int, balance: _Balance) -> InsertionFailure:
        """Why _newton gave up: `losses` steps on a freshly factored tangent raised the residual
        (FRESH_FACTOR_LOSSES)."""
        return InsertionFailure(
            f"Newton diverged at step {step} (needle rotation {rotation:.3f} rad): {losses} steps on "
            f"a freshly factored tangent raised the residual (now {balance.residual_norm:.3e} N, constraint "
            f"violation {balance.worst:.3e} mm)")

    def _not_converged(self, step: int, rotation: float, iteration: int, balance: _Balance) -> InsertionFailure:
        """Why _newton stopped short of equilibrium at its last `iteration`: a residual that is
        not finite, the forces out of balance after solver.max_iterations, or the forces balanced
        with the needle constraints stalled above their tolerance."""
        if not balance.finite:
            return NonFiniteResidual(
                f"Newton stopped at step {step} (needle rotation {rotation:.3f} rad): the residual is not finite "
                f"after {iteration} iterations (needle force {balance.needle_force:.3e} N): the loads or the "
                "deformation overflow floating point")
        message = (f"Newton did not converge at step {step} (needle rotation {rotation:.3f} rad): residual "
                   f"{balance.residual_norm:.3e} N, constraint violation {balance.worst:.3e} mm after "
                   f"{self.scenario.solver.max_iterations} iterations")
        if not balance.forces_balance:
            return NewtonExhausted(message)
        remedy = "refine the spacing or lengthen the needle step"
        if self.needle.coupling == "points":
            remedy = "refine the spacing, lengthen the needle step or use `needle.coupling: mortar`"
        return ConstraintStall(f"{message}; the forces balance, but the needle constraints stall above their "
                               f"tolerance of {self.constraint_tolerance:.3e} mm: their rows are nearly dependent, "
                               f"needle points closer together than the particles resolve ({remedy})")

    def _accept(self, free: np.ndarray, multipliers: np.ndarray, center: np.ndarray, worst: float,
                iterations: int) -> None:
        self.free, self.multipliers, self.center, self.last_violation = free.reshape(-1, 2), multipliers, center, worst
        self._count(iterations)

    def _center_columns(self, free: np.ndarray, multipliers: np.ndarray, center: np.ndarray,
                        state: Residuals) -> tuple[np.ndarray | None, tuple[np.ndarray, np.ndarray] | None]:
        """-d(r_u, g)/dC: the right-hand sides whose solutions are the equilibrium's change per
        unit move of the centre (center_sensitivity). As (None, (C, h)) with -d r_u/dC = E^T C
        (2Q, 2) on the constraint rows and h = -dg/dC (m, 2), the saddle solver's `on_rows`,
        where the coupling can (NeedleCoupling.center_derivative_on_rows; CENTER_COLUMNS_ON_ROWS);
        else as (columns (n + m, 2), None)."""
        coupling = self.coupling
        constraint_part = -coupling.constraint_center_derivative(state.normal)
        on_rows = (coupling.center_derivative_on_rows(free, multipliers, state.normal, state.rho, center)
                   if CENTER_COLUMNS_ON_ROWS else None)
        if on_rows is not None:
            return None, (-on_rows, constraint_part)
        force_change = (coupling.center_derivative(multipliers, state.normal, state.rho)
                        - coupling.needle_force_center_derivative(free, center))  # (2 n_free, 2)
        return np.vstack([-force_change, constraint_part]), None

    def _count(self, iterations: int) -> None:
        self.newton_iterations += iterations
        self.equilibrium_solves += 1

    def _timed_residuals(self, free: np.ndarray, multipliers: np.ndarray, center: np.ndarray, rotation: float,
                         step: int) -> Residuals:
        t0 = time.perf_counter()
        try:
            return self.residuals(free, multipliers, center)
        except InvertedMaterial as error:
            raise InsertionFailure(f"step {step} (needle rotation {rotation:.3f} rad): {error}") from None
        finally:
            self.timings["assembly"] += time.perf_counter() - t0

    def _minres_step(self, state: Residuals, multipliers: np.ndarray, constraints: sp.csr_matrix,
                     rhs: np.ndarray, rotation: float, step: int) -> tuple[np.ndarray | None, int]:
        """A Newton step by MINRES; None (and an event) when it stagnates."""
        curvature = self.coupling.curvature(multipliers, state.normal, state.rho)
        solution, its = self.saddle.solve_minres(
            lambda v: self.assembler.tangent_product(v) + curvature @ v, constraints, rhs,
            self.coupling.expanded_rows, self.coupling.weights_matrix(state.normal))
        if solution is None:
            self.saddle.fallbacks += 1
            message = (f"MINRES stagnated after {its} iterations at step {step} (needle rotation "
                       f"{rotation:.3f} rad): fell back to the direct solve")
            self.events.append(Event(EventKind.MINRES_FALLBACK, message, step, rotation))
            log.info(message)  # the user sees it once, as a `note:` from the event
        return solution, its

    def center_sensitivity(self, point: np.ndarray, refactor: bool = False) -> np.ndarray:
        """d u(point) / d C (2 x 2) of the constrained equilibrium at the current state.

        Differentiating eq. 3.62's residuals with respect to the needle centre C:
        K du + G dl = -d r_u/dC dC with
        d r_u/dC = -sum_q w_q lambda_e(q) N_q^T (I - n_q n_q^T) / rho_q - d f_needle/dC
        (the loads follow the needle's tangent, which turns with C), and G^T du = -d g/dC dC
        with d g_e/dC = -sum_q w_q n_q^T. Solved with the current factor of K + H (an older
        iterate's, as Newton keeps it), or a fresh one with `refactor`. The follower loads'
        own stiffness d f_needle/dd is left out of K, as in Newton: it is of order
        (needle force) / R against the tissue's stiffness.
        """
        state = self.residuals(self.free, self.multipliers, self.center)
        columns, on_rows = self._center_columns(self.free, self.multipliers, self.center, state)
        n_rows = 2 * self.model.n_free + self.coupling.multiplier_count
        rhs = columns if columns is not None else np.zeros((n_rows, 0))
        solution = self.saddle.solve_direct(self._stiffness(self.multipliers, state), rhs, refactor,
                                            self.coupling.expanded_rows, self.coupling.normal_weights(state.normal),
                                            on_rows)
        row = self.free_rows(point)
        n_dof = 2 * self.model.n_free
        return np.column_stack([row @ solution[:n_dof, j].reshape(-1, 2) for j in range(2)])

    def condition_numbers(self) -> tuple[float, float]:
        """cond of the saddle matrix at the current state, and of the block-preconditioned one
        (figures 5.2-5.8); dense, for small systems."""
        state = self.residuals(self.free, self.multipliers, self.center)
        stiffness = self._stiffness(self.multipliers, state)()
        return condition_numbers(stiffness, self.coupling.constraint_matrix(state.normal),
                                 self.saddle.stiffness_at_rest)
