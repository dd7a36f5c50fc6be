"""Curved-needle insertion into the deformable tissue (thesis section 3.1.5, Algorithm 1).

Each step rotates the rigid needle by `step` about its centre. The tip's new material point
is found by tip tracking (eq. 3.66-3.70) and appended to the needle trajectory Gamma_N; then
the tissue is brought to equilibrium under

- friction `friction` N per mm of needle inside the tissue, along the needle (eq. 3.58):
  a line load on Gamma_N, each segment between consecutive needle points carrying the
  needle length R * step it stands for, integrated with two Gauss points (eq. 3.64);
- the cutting force, spread over the tip segment ("the first segment of the needle");
- one constraint per needle point keeping its spatial position on the needle circle,
  written as the residual g_k = |x_k - C| - R that Newton drives to zero (eq. 3.59-3.65),
  so the points do not drift off the needle over many steps.

Algorithm 1 raises the insertion force in small increments until the tip force reaches the
cutting threshold, then adds a point. In the quasi-static limit the state at which each
point is added is the one solved here directly: friction over the inserted length plus the
threshold force at the tip (tests/test_simulation.py checks the two agree).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.optimize
import scipy.sparse as sp

from ..tissue.assembly import Assembler
from ..config import Scenario, ScenarioError
from ..errors import InsertionFailure
from ..tissue.model import TissueModel, build_tissue_model
from ..errors import InputError, TipTrackingJump
from ..events import Event, EventKind
from .geometry import NeedleGeometry, needle_zone, scenario_needle
from .tip_tracking import inverse_gradient_step, levenberg_marquardt_tip
from .saddle_point import SaddlePointSolver, condition_numbers
from ..tissue.solver import InvertedMaterial, checked_deformation_gradient, factorize

log = logging.getLogger(__name__)

CONSTRAINT_TOLERANCE = 1e-9  # mm, needle points on the needle after each converged step


@dataclass
class NeedleStep:
    step: int
    rotation: float  # rad since entry
    center: np.ndarray  # (2,) needle centre, spatial
    needle_tip: np.ndarray  # (2,) rigid needle tip, spatial
    tip_reference: np.ndarray  # (2,) tip material point, reference
    tip_spatial: np.ndarray  # (2,) tip material point, spatial
    needle_points: int
    friction_force: float  # N, total along the needle
    cutting_force: float  # N
    newton_iterations: int
    minres_iterations: int
    constraint_violation: float  # mm, max |g_k|
    tracking: str
    exit_displacement: np.ndarray  # (2,) u at the desired exit point
    planner_iterations: int = 0
    condition_saddle: float = float("nan")
    condition_preconditioned: float = float("nan")

    @property
    def insertion_force(self) -> float:
        return self.friction_force + self.cutting_force


@dataclass
class InsertionResult:
    scenario: Scenario
    model: TissueModel
    geometry: NeedleGeometry
    steps: list[NeedleStep]
    displacements: np.ndarray  # (n_steps + 1, NP, 2) particle displacements, step 0 = rest
    needle_points: np.ndarray  # (k, 2) reference trajectory Gamma_N at exit
    desired_exit: np.ndarray
    desired_exit_def: np.ndarray
    achieved_exit: np.ndarray
    achieved_exit_def: np.ndarray
    exit_rotation: float
    wall_seconds: float
    timings: dict[str, float]
    events: list[Event] = field(default_factory=list)
    solver_counts: dict[str, int] = field(default_factory=dict)

    @property
    def exit_error_mm(self) -> float:
        return float(np.linalg.norm(self.achieved_exit_def - self.desired_exit_def))

    @property
    def exit_error_material_mm(self) -> float:
        return float(np.linalg.norm(self.achieved_exit - self.desired_exit))


class NeedleInsertion:
    """State and steps of one insertion; `run` drives it to the exit."""

    def __init__(self, scenario: Scenario, model: TissueModel | None = None,
                 linear_solver: str | None = None, tip_tracking: str | None = None,
                 condition_numbers: bool = False):
        if scenario.needle is None:
            raise ScenarioError("needle: missing, required by simulate and plan")
        if scenario.discretization.integration != "gauss":
            raise ScenarioError(f"discretization.integration: got {scenario.discretization.integration!r}, "
                                "expected 'gauss' for simulate and plan (the needle's saddle-point solvers "
                                "need the symmetric Galerkin tangent; vci is for deform and calibrate)")
        self.scenario = scenario
        self.needle = scenario.needle
        self.domain = scenario.tissue.domain
        self.geometry = scenario_needle(scenario)
        self.timings = {"discretization": 0.0, "assembly": 0.0, "solve": 0.0, "tip_tracking": 0.0}
        start = time.perf_counter()
        self.model = model or build_tissue_model(scenario.tissue, scenario.discretization,
                                                 needle_zone=needle_zone(scenario))
        self.particle_values = self.model.shape_functions_at(self.model.particles).values
        self.timings["discretization"] += time.perf_counter() - start
        self.assembler = Assembler(self.model)
        self.linear_method = linear_solver or self.needle.linear_solver
        self.tip_tracking = tip_tracking or self.needle.tip_tracking
        self.want_condition = condition_numbers
        n_free = self.model.n_free
        self.free = np.zeros((n_free, 2))
        self.multipliers = np.zeros(0)
        self.points = np.zeros((0, 2))
        self.point_rows = sp.csr_matrix((0, n_free))  # N(Q) T, (k, n_free)
        self._point_rows_coo = self.point_rows.tocoo()
        self._expanded = self._expanded_rows()
        self.segment_points = np.zeros((0, 2))  # Gauss points on Gamma_N, reference, 2 per segment
        self.segment_rows = sp.csr_matrix((0, n_free))  # N(X_s) T at those points
        self.center = self.geometry.center.copy()
        self.events: list[Event] = []
        stiffness_factor = None
        if self.linear_method == "minres":
            start = time.perf_counter()
            self.assembler.update(np.tile(np.eye(2), (len(self.model.quadrature_weights), 1, 1)))
            stiffness_factor = factorize(self.assembler.tangent_matrix())  # K0 of eq. 3.72
            self.timings["solve"] += time.perf_counter() - start
        self.saddle = SaddlePointSolver(self.linear_method, stiffness_factor)
        self._k0_factor = stiffness_factor

    # --- fields --------------------------------------------------------------------------

    def coefficients(self) -> np.ndarray:
        return self.model.boundary.free_map @ self.free

    def displacement(self, points: np.ndarray, gradient: bool = False):
        # a probe outside the tissue (LM trying points past the exit) may lie outside every
        # kernel support: evaluate the field at the nearest tissue point instead
        points = self.domain.clip(np.atleast_2d(points))
        u, grad = self.model.field_at(points, self.coefficients(), gradients=gradient)  # grad (n, i, J)
        return (u, grad) if gradient else u

    def particle_displacements(self) -> np.ndarray:
        return self.particle_values @ self.coefficients()

    # --- needle loads and constraints ---------------------------------------------------

    def _needle_load_magnitudes(self) -> np.ndarray:
        """Force (N) carried by each Gauss point of Gamma_N: friction on every segment,
        plus the cutting force on the tip segment (eq. 3.58, 3.64)."""
        segments = len(self.segment_points) // 2
        per_segment = np.full(segments, self.needle.friction * self.geometry.insertion_step)
        if segments:
            per_segment[-1] += self.needle.cutting_force
        return np.repeat(0.5 * per_segment, 2)

    def _fields(self, free: np.ndarray, multipliers: np.ndarray, center: np.ndarray):
        """Residual r_u = f_int - f_needle + G lambda and constraint values g_k at (free, lambda).

        Returns (residual, violation, normal, rho, |f_needle|, load magnitudes); G and the
        constraint curvature are built only when a solve needs them.
        """
        coefficients = self.model.boundary.free_map @ free
        deformation_gradient = checked_deformation_gradient(self.model, coefficients)
        internal = self.assembler.update(deformation_gradient)
        spatial = self.points + self.point_rows @ free  # (k, 2)
        relative = spatial - center
        rho = np.linalg.norm(relative, axis=1)
        normal = relative / rho[:, None]
        violation = rho - self.geometry.radius  # g_k
        self._normals = normal
        load_points = self.segment_points + self.segment_rows @ free  # spatial Gauss points
        angles = np.arctan2(load_points[:, 1] - center[1], load_points[:, 0] - center[0])
        tangent = self.geometry.tangent(angles)  # a_0, direction of needle motion
        magnitude = self._needle_load_magnitudes()
        needle_force = (self.segment_rows.T @ (magnitude[:, None] * tangent)).ravel()  # eq. 3.64
        # G lambda = N^T (lambda_k n_k), interleaved
        constraint_force = self._expanded.T @ (multipliers[:, None] * normal).ravel()
        residual = internal - needle_force + constraint_force
        return residual, violation, normal, rho, float(np.linalg.norm(needle_force)), magnitude

    def _constraint_matrix(self, normal: np.ndarray) -> sp.csr_matrix:
        """G of eq. 3.65 for the residual form g_k = |x_k - C| - R: column k = N_k^T n_k."""
        rows = self._point_rows_coo
        return sp.csr_matrix(
            (np.concatenate([rows.data * normal[rows.row, 0], rows.data * normal[rows.row, 1]]),
             (np.concatenate([2 * rows.col, 2 * rows.col + 1]), np.concatenate([rows.row, rows.row]))),
            shape=(2 * self.model.n_free, len(self.points)))

    def _curvature(self, multipliers: np.ndarray, normal: np.ndarray, rho: np.ndarray) -> sp.csr_matrix:
        """sum_k lambda_k d^2 g_k = N^T blockdiag(lambda_k (I - n_k n_k^T) / rho_k) N."""
        k = len(self.points)
        if k == 0:
            return sp.csr_matrix((2 * self.model.n_free, 2 * self.model.n_free))
        blocks = multipliers[:, None, None] * (np.eye(2) - normal[:, :, None] * normal[:, None, :]) / rho[:, None, None]
        block_matrix = sp.bsr_matrix((blocks, np.arange(k), np.arange(k + 1)), shape=(2 * k, 2 * k)).tocsr()
        return (self._expanded.T @ block_matrix @ self._expanded).tocsr()

    def _state(self, free: np.ndarray, multipliers: np.ndarray, center: np.ndarray, rotation: float):
        """Residuals and linearisation of the constrained equilibrium at (free, multipliers):
        (r_u, g, G, curvature, |f_needle|, load magnitudes)."""
        residual, violation, normal, rho, force_norm, magnitude = self._fields(free, multipliers, center)
        return (residual, violation, self._constraint_matrix(normal), self._curvature(multipliers, normal, rho),
                force_norm, magnitude)

    def _expanded_rows(self) -> sp.csr_matrix:
        """N(Q) T acting on interleaved dofs: rows (k, i), columns (p, i)."""
        rows = self.point_rows.tocoo()
        k = len(self.points)
        return sp.csr_matrix(
            (np.concatenate([rows.data, rows.data]),
             (np.concatenate([2 * rows.row, 2 * rows.row + 1]), np.concatenate([2 * rows.col, 2 * rows.col + 1]))),
            shape=(2 * k, 2 * self.model.n_free))

    def add_point(self, reference_point: np.ndarray) -> None:
        free_map = self.model.boundary.free_map
        if len(self.points):
            gauss = 0.5 + np.array([-0.5, 0.5]) / math.sqrt(3.0)
            new = self.points[-1] + gauss[:, None] * (reference_point - self.points[-1])
            self.segment_points = np.vstack([self.segment_points, new])
            self.segment_rows = sp.vstack(
                [self.segment_rows, self.model.shape_functions_at(new).values @ free_map], format="csr")
        row = self.model.shape_functions_at(reference_point[None]).values @ free_map
        self.points = np.vstack([self.points, reference_point])
        self.point_rows = sp.vstack([self.point_rows, sp.csr_matrix(row)], format="csr")
        self._point_rows_coo = self.point_rows.tocoo()
        self._expanded = self._expanded_rows()
        self.multipliers = np.append(self.multipliers, 0.0)
        if self.saddle.schur is not None:
            spatial = reference_point + (row @ self.free)[0]
            relative = spatial - self.center
            normal = relative / np.linalg.norm(relative)
            column = np.zeros(2 * self.model.n_free)
            coo = sp.coo_matrix(row)
            column[2 * coo.col] = coo.data * normal[0]
            column[2 * coo.col + 1] = coo.data * normal[1]
            self.saddle.schur.add(column)

    # --- equilibrium ---------------------------------------------------------------------

    def equilibrate(self, center: np.ndarray, rotation: float, step: int) -> tuple[int, int, float]:
        """Newton on the saddle-point system (eq. 3.62). Returns (iterations, MINRES its, max |g|)."""
        settings = self.scenario.solver
        free, multipliers = self.free.ravel().copy(), self.multipliers.copy()
        n_dof = len(free)
        minres_total = 0
        previous = math.inf
        for iteration in range(settings.max_iterations + 1):
            t0 = time.perf_counter()
            try:
                residual, violation, normal, rho, force_norm, _ = self._fields(
                    free.reshape(-1, 2), multipliers, center)
            except InvertedMaterial as error:
                raise InsertionFailure(f"step {step} (needle rotation {rotation:.3f} rad): {error}") from None
            self.timings["assembly"] += time.perf_counter() - t0
            residual_norm = float(np.linalg.norm(residual))
            worst = float(np.abs(violation).max()) if len(violation) else 0.0
            if (residual_norm <= settings.residual_tolerance * max(force_norm, 1e-6) + 1e-12
                    and worst <= CONSTRAINT_TOLERANCE):
                self.free, self.multipliers = free.reshape(-1, 2), multipliers
                self.last_violation = worst
                return iteration, minres_total, worst
            if iteration == settings.max_iterations or not np.isfinite(residual_norm):
                break
            rhs = -np.concatenate([residual, violation])
            t0 = time.perf_counter()
            solution = None
            constraints = self._constraint_matrix(normal)
            if self.linear_method == "minres":
                curvature = self._curvature(multipliers, normal, rho)
                solution, its = self.saddle.solve_minres(
                    lambda v: self.assembler.tangent_product(v) + curvature @ v, constraints, rhs,
                    self._expanded, normal)
                minres_total += its
                if solution is None:
                    self.saddle.fallbacks += 1
                    message = (f"MINRES stagnated after {its} iterations at step {step} (needle rotation "
                               f"{rotation:.3f} rad): fell back to the direct solve")
                    self.events.append(Event(EventKind.MINRES_FALLBACK, message, step, rotation))
                    log.warning(message)
            if solution is None:
                # keep the factor of K while Newton contracts fast; renew it when it slows
                measure = residual_norm / max(force_norm, 1e-12) + worst
                refactor = measure > 0.2 * previous
                solution = self.saddle.solve_direct(
                    lambda: self.assembler.tangent_matrix() + self._curvature(multipliers, normal, rho),
                    constraints, rhs, refactor, self._expanded, normal)
                previous = measure
            self.timings["solve"] += time.perf_counter() - t0
            free = free + solution[:n_dof]
            multipliers = multipliers + solution[n_dof:]
        raise InsertionFailure(
            f"Newton did not converge at step {step} (needle rotation {rotation:.3f} rad): residual "
            f"{residual_norm:.3e} N, constraint violation {worst:.3e} mm after {settings.max_iterations} iterations")

    def center_sensitivity(self, center: np.ndarray, point: np.ndarray) -> np.ndarray:
        """d u(point) / d C (2 x 2) of the constrained equilibrium at the current state.

        Differentiating eq. 3.62's residuals with respect to the needle centre C:
        K du + G dl = -d r_u/dC dC with d r_u/dC = -sum_k lambda_k N_k^T (I - n_k n_k^T) / rho_k,
        and G^T du = -d g/dC dC with d g_k/dC = -n_k^T; solved with the current factor of K.
        """
        residual, violation, normal, rho, _, _ = self._fields(self.free, self.multipliers, center)
        constraints = self._constraint_matrix(normal)
        n_dof = 2 * self.model.n_free
        blocks = -self.multipliers[:, None, None] * (np.eye(2) - normal[:, :, None] * normal[:, None, :]) / rho[:, None, None]
        row = self.model.shape_functions_at(point[None]).values @ self.model.boundary.free_map
        multipliers, curvature_normal = self.multipliers, normal
        columns = []
        for j in range(2):
            force_change = self._expanded.T @ blocks[:, :, j].ravel()
            rhs = -np.concatenate([force_change, -normal[:, j]])
            solution = self.saddle.solve_direct(
                lambda: self.assembler.tangent_matrix() + self._curvature(multipliers, curvature_normal, rho),
                constraints, rhs, False, self._expanded, normal)
            columns.append((row @ solution[:n_dof].reshape(-1, 2))[0])
        return np.column_stack(columns)

    # --- tip tracking --------------------------------------------------------------------

    def track_tip(self, rotation_step: float, method: str) -> tuple[np.ndarray, str]:
        """Reference position X_{n+1} of the next tip point, one step of `rotation_step` along the
        needle from the current tip X_n (thesis figure 3.1 and eq. 3.66-3.70)."""
        previous = self.points[-1]
        u, grad = self.displacement(previous, gradient=True)
        spatial_previous = previous + u[0]
        relative = spatial_previous - self.center
        angle = math.atan2(relative[1], relative[0]) + self.geometry.sense * rotation_step
        target = self.center + self.geometry.radius * np.array([math.cos(angle), math.sin(angle)])
        expected_length = 2.0 * self.geometry.radius * math.sin(0.5 * rotation_step)  # chord
        rest_angle = math.atan2(*(previous - self.geometry.center)[::-1])
        expected_direction = self.geometry.tangent(rest_angle + 0.5 * self.geometry.sense * rotation_step)
        if method in ("auto", "inverse-gradient"):
            try:
                point = inverse_gradient_step(previous, spatial_previous, np.eye(2) + grad[0], target,
                                              expected_length, expected_direction,
                                              lambda x: self.displacement(x)[0])
                return point, "inverse-gradient"
            except TipTrackingJump as jump:
                if method == "inverse-gradient":
                    raise
                raise _Fallback(str(jump)) from None
        start = previous + expected_length * expected_direction  # eq. 3.70

        def field(x):
            u, grad = self.displacement(x, gradient=True)
            return u[0], grad[0]

        point, _ = levenberg_marquardt_tip(previous, self.center, self.geometry.radius, expected_length,
                                           start, field)
        return point, "levenberg-marquardt"

    def track(self, rotation_step: float, step: int, rotation: float) -> tuple[np.ndarray, str]:
        t0 = time.perf_counter()
        try:
            return self.track_tip(rotation_step, self.tip_tracking)
        except _Fallback as jump:
            message = (f"inverse-gradient tip tracking jumped at step {step} (needle rotation "
                       f"{rotation:.3f} rad): {jump}; fell back to Levenberg-Marquardt")
            self.events.append(Event(EventKind.TIP_TRACKING_FALLBACK, message, step, rotation))
            log.warning(message)
            return self.track_tip(rotation_step, "levenberg-marquardt")
        except TipTrackingJump as jump:
            raise InsertionFailure(f"inverse-gradient tip tracking jumped at step {step} (needle rotation "
                                   f"{rotation:.3f} rad): {jump}") from None
        finally:
            self.timings["tip_tracking"] += time.perf_counter() - t0

    def locate_exit(self, rotation: float, method: str) -> tuple[np.ndarray, float]:
        """Root-find, over the fraction of the last step, where the tip's material point meets
        the boundary: the signed distance to the boundary is continuous in the fraction, so
        Brent's method needs ~10 tip trackings where bisection needs ~45."""
        tracked = {0.0: self.points[-1]}  # fraction -> tip point, each tracked once

        def signed_distance(fraction: float) -> float:
            if fraction not in tracked:
                tracked[fraction] = self.track_tip(fraction * self.geometry.step, method)[0]
            return self.domain.outside_distance(tracked[fraction])

        if signed_distance(1.0) <= 0.0:  # the full step stays inside for this tracking method
            fraction = 1.0
        elif signed_distance(0.0) >= 0.0:
            fraction = 0.0
        else:
            fraction = scipy.optimize.brentq(signed_distance, 0.0, 1.0, xtol=1e-13, rtol=1e-15)
        signed_distance(fraction)  # brentq's root is one of its evaluations; tracked if not
        point = self.domain.clip(tracked[fraction])
        return point, rotation + fraction * self.geometry.step


class _Fallback(Exception):
    pass


CenterUpdate = Callable[["NeedleInsertion", int, float, np.ndarray], tuple[np.ndarray, int]]


def run_insertion(
    scenario: Scenario,
    center_update: CenterUpdate | None = None,
    center_path: np.ndarray | None = None,
    linear_solver: str | None = None,
    tip_tracking: str | None = None,
    condition_numbers: bool = False,
    on_step: Callable[[NeedleStep], None] | None = None,
    max_steps: int | None = None,
    center_predictor: Callable[[np.ndarray], np.ndarray] | None = None,
) -> InsertionResult:
    """Insert the needle step by step until its tip leaves the tissue.

    center_update(insertion, step, rotation, center) -> (new centre, planner iterations) lets
    the planner move the centre after each step (Algorithm 2); center_path (n, 2) replays
    prescribed centres, row n used for step n (row 0 is the entry centre);
    center_predictor(centre) -> centre gives the planner's first guess for the
    centre of a step, once the tip has advanced about the previous one.
    """
    if scenario.discretization.accuracy is not None:
        raise InputError("discretization.accuracy: got an accuracy target, expected a discretization "
                         "chosen before the run (stitchplan.study.auto.resolve_accuracy)")
    wall_start = time.perf_counter()
    insertion = NeedleInsertion(scenario, linear_solver=linear_solver, tip_tracking=tip_tracking,
                                condition_numbers=condition_numbers)
    geometry = insertion.geometry
    insertion.add_point(geometry.entry.copy())
    desired_exit = geometry.desired_exit
    displacements = [np.zeros_like(insertion.model.particles)]
    steps: list[NeedleStep] = []
    limit = max_steps or int(math.ceil(2.0 * math.pi / geometry.step)) + 2
    center = geometry.center.copy()
    if center_path is not None:
        center = np.asarray(center_path[0], dtype=float)
    insertion.center = center
    exit_point = exit_rotation = None
    method_used = insertion.tip_tracking
    for step in range(1, limit + 1):
        rotation = step * geometry.step
        insertion.center = center  # the tip advances about the centre of the previous step
        point, method_used = insertion.track(geometry.step, step, rotation)
        if insertion.domain.outside_distance(point) > 0.0:
            method = "levenberg-marquardt" if method_used == "levenberg-marquardt" else insertion.tip_tracking
            if method == "auto":
                method = "inverse-gradient"
            t0 = time.perf_counter()
            try:
                exit_point, exit_rotation = insertion.locate_exit(rotation - geometry.step, method)
            except TipTrackingJump:
                exit_point, exit_rotation = insertion.locate_exit(rotation - geometry.step, "levenberg-marquardt")
            insertion.timings["tip_tracking"] += time.perf_counter() - t0
            break
        insertion.add_point(point)
        if center_path is not None:
            if step >= len(center_path):
                raise ScenarioError(f"centre path: {len(center_path)} rows end before the tip exits "
                                    f"(step {step}); expected one row per step")
            center = np.asarray(center_path[step], dtype=float)
            insertion.center = center
        elif center_predictor is not None:
            center = np.asarray(center_predictor(center), dtype=float)
            insertion.center = center
        iterations, minres_its, violation = insertion.equilibrate(center, rotation, step)
        planner_iterations = 0
        if center_update is not None:
            center, planner_iterations = center_update(insertion, step, rotation, center)
            insertion.center = center
            violation = insertion.last_violation
        u_tip = insertion.displacement(point)[0]
        u_exit = insertion.displacement(desired_exit)[0]
        record = NeedleStep(
            step=step, rotation=rotation, center=center.copy(), needle_tip=geometry.tip(rotation, center),
            tip_reference=point.copy(), tip_spatial=point + u_tip, needle_points=len(insertion.points),
            friction_force=insertion.needle.friction * geometry.radius * geometry.step * (len(insertion.points) - 1),
            cutting_force=insertion.needle.cutting_force, newton_iterations=iterations,
            minres_iterations=minres_its, constraint_violation=violation, tracking=method_used,
            exit_displacement=u_exit, planner_iterations=planner_iterations,
        )
        if condition_numbers:
            record.condition_saddle, record.condition_preconditioned = insertion_condition_numbers(insertion, rotation)
        steps.append(record)
        displacements.append(insertion.particle_displacements())
        if on_step is not None:
            on_step(record)
    if exit_point is None:
        raise InsertionFailure(f"the needle tip did not leave the tissue within {limit} steps "
                               f"(needle rotation {limit * geometry.step:.3f} rad)")
    u_now = insertion.displacement(np.vstack([exit_point, desired_exit]))
    wall = time.perf_counter() - wall_start
    return InsertionResult(
        scenario=scenario, model=insertion.model, geometry=geometry, steps=steps,
        displacements=np.asarray(displacements), needle_points=insertion.points.copy(),
        desired_exit=desired_exit, desired_exit_def=desired_exit + u_now[1],
        achieved_exit=exit_point, achieved_exit_def=exit_point + u_now[0], exit_rotation=exit_rotation,
        wall_seconds=wall, timings=insertion.timings, events=insertion.events,
        solver_counts={"factorizations": insertion.saddle.factorizations,
                       "minres_iterations": insertion.saddle.minres_iterations,
                       "minres_fallbacks": insertion.saddle.fallbacks,
                       "tangent_products": insertion.assembler.tangent_products},
    )


def insertion_condition_numbers(insertion: NeedleInsertion, rotation: float) -> tuple[float, float]:
    """Condition numbers of the saddle matrix and of the block-preconditioned one (figures 5.2-5.8)."""
    residual, violation, constraints, curvature, _, _ = insertion._state(
        insertion.free, insertion.multipliers, insertion.center, rotation)
    stiffness = insertion.assembler.tangent_matrix() + curvature
    factor = insertion._k0_factor
    if factor is None:
        insertion.assembler.update(np.tile(np.eye(2), (len(insertion.model.quadrature_weights), 1, 1)))
        factor = factorize(insertion.assembler.tangent_matrix())
        insertion._k0_factor = factor
        insertion._state(insertion.free, insertion.multipliers, insertion.center, rotation)
    n = stiffness.shape[0]
    k0_inv_g = np.column_stack([factor.solve(c) for c in constraints.T.toarray()]) if constraints.shape[1] else np.zeros((n, 0))
    schur_inverse = np.linalg.inv(constraints.T @ k0_inv_g)
    return condition_numbers(stiffness, constraints, factor, schur_inverse)
