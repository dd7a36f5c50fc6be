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
Newton's parts (its tolerances and tuning, the factor's renewal, Anderson mixing, what a solve
remembers) are needle/newton.py's; the tissue model and K0's factor that every insertion
starts from, needle/prepared_tissue.py's; what a failed step says, needle/step_failures.py's.

The tangent is K + H, symmetric: the follower loads' own stiffness (friction and cutting force
turn with the needle's tangent at their points) is left out, so that K + H is factored by
Cholesky and kept over iterations. Measured with it in (benchmarks/results/entry_newton.md, the
full Jacobian LU-factored at every iteration): sh12_100x100 takes 76 Newton iterations instead
of 120 but 3.6 s instead of 0.3 s, the exit within 6e-6 mm; the 2.5 mm soft slab at a quarter
spacing stops at the same step and load, where Newton's linear model holds for 5 % of its step
and no equilibrium is found past 88.75 % of the step's load (a limit point: the tissue, not Newton).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable

import numpy as np
import scipy.sparse as sp

from ..config import Scenario, Solver
from ..errors import InputError, InsertionFailure, InvertedMaterial, UnstableEquilibrium
from ..events import Event, EventKind
from ..tissue.assembly import Assembler
from ..tissue.solver import checked
from .coupling import NeedleCoupling
from .geometry import IDENTITY, length, scenario_needle
from .newton import Balance, NewtonHistory, Residuals, newton_tolerances
from .prepared_tissue import PreparedTissue
from .results import Snapshot
from .saddle_point import SaddlePointSolver, condition_numbers
from .stability import SoftestMode, softest_mode
from .steering import CenterAim
from .step_failures import diverged, mode_place, not_converged, ramp_failure, stability_note

log = logging.getLogger(__name__)

CENTER_COLUMNS_ON_ROWS = True  # d(d, lambda)/dC from the kept K^-1 E^T where the coupling allows (_center_columns)
RAMP_SMALLEST = 1.0 / 64.0  # Algorithm 1's ramp: the smallest load increment tried within a step
# a step whose ramp is still cutting its load after this long says so by a warning (shown without
# -v; each cut is logged at INFO): a 0.5 mm thin strip's first step cut for minutes in silence
LONG_STEP_SECONDS = 30.0


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
        # called with (step, load carried, next increment) as the ramp cuts or carries an
        # increment (run_insertion's on_ramp: a progress bar's note)
        self.on_ramp: Callable[[int, float, float], None] | None = None
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
        started, warned = time.perf_counter(), False
        while coupling.load_factor < 1.0:
            start = coupling.load_factor
            coupling.load_factor = min(1.0, start + increment)
            try:
                its, minres_its, worst = self._newton(rotation, step, aim)
                if increment < 1.0:  # a cut ramp: near an instability Newton may land on the unstable branch
                    self._refuse_unstable(rotation, step)
            except InsertionFailure as failure:
                failed, coupling.load_factor = coupling.load_factor, start
                self.restore(carried)
                self.saddle.forget()  # the factor of a failed iterate is no start for the next
                increment *= 0.5
                # a doubled increment capped at the whole load: its halves may reach the whole
                # load again, a try of the same state at the same load, which fails alike
                while start + increment >= failed and increment >= RAMP_SMALLEST:
                    increment *= 0.5
                if increment < RAMP_SMALLEST:  # the error says where it stopped, no "goes on" before it
                    raise InsertionFailure(self._ramp_failure(rotation, step, start, failure, step_start)) from None
                log.info("step %d (needle rotation %.3f rad): Newton failed at %.3g %% of the step's load; "
                         "the ramp goes on in increments of %.3g %%", step, rotation, 100 * failed, 100 * increment)
                self.ramp_increments += 1
                warned = self._ramp_progress(step, rotation, start, increment, started, warned)
                continue
            newton, minres = newton + its, minres + minres_its
            carried = self.snapshot()
            increment = min(1.0, 2.0 * increment)
            if coupling.load_factor < 1.0:
                warned = self._ramp_progress(step, rotation, coupling.load_factor, increment, started, warned)
        return newton, minres, worst

    def _ramp_progress(self, step: int, rotation: float, carried: float, increment: float, started: float,
                       warned: bool) -> bool:
        """Report the ramp's state (on_ramp), and once a step, past LONG_STEP_SECONDS, a warning
        line; whether it has been given."""
        if self.on_ramp is not None:
            self.on_ramp(step, carried, increment)
        elapsed = time.perf_counter() - started
        if warned or elapsed < LONG_STEP_SECONDS:
            return warned
        log.warning("step %d (needle rotation %.3f rad) is still cutting its load after %.0f s: %.0f %% carried, "
                    "the ramp goes on in increments of %.3g %% down to %.3g %% (-v shows each cut)", step, rotation,
                    elapsed, 100 * carried, 100 * increment, 100 * RAMP_SMALLEST)
        return True

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
        """What went wrong when even the smallest load increment fails (step_failures.ramp_failure).
        The state is the last load carried; `step_start` the step's first."""
        tissue = self.scenario.tissue
        models = {tissue.material.model} | {region.material.model for region in getattr(tissue, "regions", None) or []}
        return ramp_failure(step, rotation, carried, RAMP_SMALLEST, failure, self.scenario.solver.max_iterations,
                            Solver().max_iterations, models, lambda: self._stability_note(step_start))

    def softest_mode(self) -> SoftestMode | None:
        """The least stiffness of the tangent on the needle's constraints at the current
        state, and its mode (needle/stability.py)."""
        state = self.residuals(self.free, self.multipliers, self.center)
        return softest_mode(self._stiffness(self.multipliers, state)(),
                            self.coupling.constraint_matrix(state.normal))

    def _stability_note(self, step_start: Snapshot) -> str:
        """step_failures.stability_note at the last load carried, against the step's start
        (none where nothing of the step was carried)."""
        now = self.softest_mode()
        if now is None:
            return ""
        before = None
        if now.stiffness >= 0.0 and not np.array_equal(step_start.free, self.free):
            carried = self.snapshot()
            self.restore(step_start)
            before = self.softest_mode()
            self.restore(carried)
        return stability_note(now, self._mode_place(now), before)

    def _mode_place(self, mode: SoftestMode) -> str:
        """Where the mode moves the tissue most, near the needle's entry or tip (step_failures.mode_place)."""
        return mode_place(mode, self.model, self.scenario.discretization.dilation, self.geometry.entry,
                          self.points[-1] if len(self.points) else None)

    def _newton(self, rotation: float, step: int, aim: CenterAim | None = None) -> tuple[int, int, float]:
        """Newton on the saddle-point system (eq. 3.62) at the current load, about the
        current centre or, with `aim`, with the centre as a third unknown (CenterAim, Algorithm 2's update).
        Each iteration: the residuals; converged?; a step of the linearised system, by MINRES
        (eq. 3.71-3.74) or on a kept factor of K + H renewed when Newton slows, whose steps are
        Anderson-mixed (Walker and Ni 2011); with `aim`, the centre's move; the update. What the
        iterations remember is a NewtonHistory.
        Returns (Newton iterations, MINRES iterations, max |g_e| in mm)."""
        settings = self.scenario.solver
        free, multipliers, center = self.free.ravel().copy(), self.multipliers.copy(), self.center.copy()
        n_dof = len(free)
        history = NewtonHistory(planned=aim is not None)
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
                raise diverged(step, rotation, history.losses, balance)
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
        raise not_converged(step, rotation, iteration, balance, settings.max_iterations, self.needle.coupling == "points",
                            self.constraint_tolerance)

    def _balance(self, state: Residuals) -> Balance:
        """How far the iterate of `state` is from equilibrium, against the step's tolerances."""
        residual_norm, worst = length(state.residual), state.worst_violation
        # a needle force so large that its norm overflows would make every residual look small
        finite = math.isfinite(residual_norm) and math.isfinite(state.needle_force)
        forces_balance = finite and residual_norm <= self.residual_tolerance * max(state.needle_force, 1e-6) + 1e-12
        balanced = forces_balance and worst <= self.constraint_tolerance
        return Balance(residual_norm, worst, state.needle_force, finite, forces_balance, balanced)

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
                     on_rows: tuple[np.ndarray, np.ndarray] | None, balance: Balance, history: NewtonHistory,
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
                     history: NewtonHistory) -> np.ndarray:
        """The step by block elimination on the kept factor of K + H (SaddlePointSolver.solve_direct),
        renewed where Newton slows (NewtonHistory.renew): a modified Newton step."""
        refactor = history.renew(measure)
        solution = self.saddle.solve_direct(self._stiffness(multipliers, state), rhs,
                                            refactor, self.coupling.expanded_rows,
                                            self.coupling.normal_weights(state.normal), on_rows)
        history.solved_directly(measure, refactor)
        return solution

    def _steer(self, aim: CenterAim, history: NewtonHistory, free: np.ndarray, center: np.ndarray,
               solution: np.ndarray, balanced: bool) -> np.ndarray | None:
        """The step with the centre's move (CenterAim.update, Algorithm 2) appended, the equilibrium's
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
