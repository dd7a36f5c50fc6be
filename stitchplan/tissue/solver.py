"""Total-Lagrangian Newton solver with load stepping and step cutting (thesis eq. 3.44-3.57)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from .assembly import Assembler
from .factorization import factorize
from ..config import Solver
from ..errors import InvertedMaterial, IterationLimit, SolverDivergence
from .model import TissueModel
from .material import determinant

log = logging.getLogger(__name__)


@dataclass
class StepRecord:
    load_fraction: float
    iterations: int
    residual: float
    increment: float
    cuts: int


@dataclass
class NewtonReport:
    steps: list[StepRecord] = field(default_factory=list)
    linear_solves: int = 0
    factorizations: int = 0
    krylov_iterations: int = 0
    linear_solver: str = "pcg"  # TangentSolver.mode
    linear_solver_backends: list[str] = field(default_factory=list)  # every factorization's, in order met

    @property
    def iterations(self) -> int:
        return sum(step.iterations for step in self.steps)

    @property
    def cuts(self) -> int:
        return sum(step.cuts for step in self.steps)


def checked_deformation_gradient(model: TissueModel, coefficients: np.ndarray) -> np.ndarray:
    """F at the quadrature points; raises InvertedMaterial where det F <= 0."""
    return checked(model, model.deformation_gradient(coefficients))


def checked(model: TissueModel, deformation_gradient: np.ndarray) -> np.ndarray:
    """`deformation_gradient` (nq, 2, 2) itself; raises InvertedMaterial where det F <= 0."""
    jacobian = determinant(deformation_gradient)
    if not np.all(np.isfinite(jacobian)) or jacobian.min() <= 0.0:
        worst = int(np.nanargmin(np.where(np.isfinite(jacobian), jacobian, -np.inf)))
        x, y = model.quadrature_points[worst]
        raise InvertedMaterial(f"det F = {jacobian[worst]:.3g} at ({x:.3g}, {y:.3g}) mm")
    return deformation_gradient


def preconditioned_cg(
    operator: Callable[[np.ndarray], np.ndarray],
    preconditioner: Callable[[np.ndarray], np.ndarray],
    rhs: np.ndarray,
    rtol: float,
    max_iterations: int,
) -> tuple[np.ndarray | None, int]:
    """Conjugate gradients; returns (None, its) on negative curvature or no convergence."""
    x = np.zeros_like(rhs)
    r = rhs.copy()
    target = rtol * np.linalg.norm(rhs)
    z = preconditioner(r)
    p = z.copy()
    rz = r @ z
    for iteration in range(1, max_iterations + 1):
        kp = operator(p)
        curvature = p @ kp
        if curvature <= 0.0:
            return None, iteration
        alpha = rz / curvature
        x += alpha * p
        r -= alpha * kp
        if np.linalg.norm(r) <= target:
            return x, iteration
        z = preconditioner(r)
        rz_new = r @ z
        p = z + (rz_new / rz) * p
        rz = rz_new
    return None, max_iterations


def preconditioned_gmres(
    operator: Callable[[np.ndarray], np.ndarray],
    preconditioner: Callable[[np.ndarray], np.ndarray],
    rhs: np.ndarray,
    rtol: float,
    max_iterations: int,
) -> tuple[np.ndarray | None, int]:
    """GMRES (Krylov spaces of up to max_iterations, at most three cycles: scipy may end a cycle
    early on its preconditioned residual estimate) for nonsymmetric tangents; returns
    (None, its) unless the true residual reaches ~rtol |rhs|."""
    import scipy.sparse.linalg as spla  # here: the needle commands import this module but never need it

    n = len(rhs)
    count = [0]
    a = spla.LinearOperator((n, n), matvec=operator, dtype=float)
    m = spla.LinearOperator((n, n), matvec=preconditioner, dtype=float)
    x, info = spla.gmres(a, rhs, M=m, rtol=rtol, atol=0.0, restart=max_iterations, maxiter=3,
                         callback=lambda _r: count.__setitem__(0, count[0] + 1), callback_type="pr_norm")
    if info != 0 or np.linalg.norm(rhs - operator(x)) > 10 * rtol * np.linalg.norm(rhs):
        return None, count[0]
    return x, count[0]


class TangentSolver:
    """Solves K dx = -r for the successive tangents of a Newton run.

    mode "direct": factorize every tangent. mode "pcg": conjugate gradients on the
    matrix-free tangent, preconditioned by the factorization of an earlier tangent (the
    thesis's K_Inv of eq. 3.72, taken at zero deformation and renewed when it stops
    working: CG needing more than `refactor_after` iterations, or meeting negative curvature).
    """

    def __init__(self, mode: str = "pcg", refactor_after: int = 25, rtol: float = 1e-6):
        self.mode = mode
        self.refactor_after = refactor_after
        self.rtol = rtol
        self.factor = None
        self.factorizations = 0
        self.krylov_iterations = 0
        self.backends: list[str] = []  # the sparse factorizations that ran (factorization.py `backend`)

    def _refactor(self, matrix: sp.spmatrix) -> None:
        self.factor = factorize(matrix)
        self.factorizations += 1
        if self.factor.backend not in self.backends:
            self.backends.append(self.factor.backend)

    def solve(self, problem, rhs: np.ndarray) -> np.ndarray:
        if self.mode == "pcg" and self.factor is not None:
            if getattr(problem, "symmetric", True):
                x, iterations = preconditioned_cg(problem.tangent_product, self.factor.solve, rhs,
                                                  self.rtol, self.refactor_after)
            else:  # Petrov-Galerkin tangent (integration "vci"): GMRES, same preconditioner
                x, iterations = preconditioned_gmres(problem.tangent_product, self.factor.solve, rhs,
                                                     self.rtol, self.refactor_after)
            self.krylov_iterations += iterations
            if x is not None:
                return x
        self._refactor(problem.tangent_matrix())
        return self.factor.solve(rhs)


def newton(
    problem,
    start: np.ndarray,
    settings: Solver,
    reference_force: float,
    length_scale: float,
    linear: TangentSolver,
) -> tuple[np.ndarray, int, float, float, float]:
    """Newton iterations on problem.residual(x) = 0 from `start`.

    Converged when |r| <= residual_tolerance * max(reference, |r_0|) and the last increment
    |dx|_inf <= increment_tolerance * (|x|_inf + length_scale), or the residual is 1000x
    below its tolerance. Raises InvertedMaterial or SolverDivergence; the caller cuts the step.
    Returns (x, iterations, |r|, |dx|_inf, |r_0|).
    """
    x = start.copy()
    increment_norm = np.inf
    residual_norm = np.inf
    for iteration in range(settings.max_iterations + 1):
        residual = problem.residual(x)
        residual_norm = float(np.linalg.norm(residual))
        if not np.isfinite(residual_norm):
            raise SolverDivergence(f"residual is not finite after {iteration} iterations")
        if iteration == 0:
            initial = residual_norm
            tolerance = settings.residual_tolerance * max(reference_force, residual_norm, 1e-300)
        log.debug("Newton iteration %d: residual %.3e N (tolerance %.3e N)", iteration, residual_norm,
                  tolerance)
        small_step = increment_norm <= settings.increment_tolerance * (np.abs(x).max() + length_scale)
        if residual_norm <= tolerance and (small_step or residual_norm <= 1e-3 * tolerance):
            return x, iteration, residual_norm, increment_norm, initial
        if iteration == settings.max_iterations:
            break
        delta = linear.solve(problem, -residual)
        if not np.all(np.isfinite(delta)):
            raise SolverDivergence(f"linear solve failed at iteration {iteration + 1}")
        x = x + delta
        increment_norm = float(np.abs(delta).max())
    iterations = f"{settings.max_iterations} iteration{'s' * (settings.max_iterations != 1)}"
    if residual_norm <= tolerance:  # the forces balance; the increments have not settled
        limit = settings.increment_tolerance * (np.abs(x).max() + length_scale)
        raise IterationLimit(
            f"no convergence in {iterations} (residual {residual_norm:.3e} N, within its "
            f"tolerance {tolerance:.3e} N, but the last increment {increment_norm:.3e} mm above its tolerance "
            f"{limit:.3e} mm)")
    raise IterationLimit(
        f"no convergence in {iterations} (residual {residual_norm:.3e} N)"
    )


class StaticProblem:
    """f_int(d) - lambda f_ext = 0 on the free coefficients, with g = lambda g_final."""

    def __init__(self, model: TissueModel, assembler: Assembler, external_force: np.ndarray,
                 prescribed: np.ndarray):
        self.model = model
        self.assembler = assembler
        self.external_force = external_force
        self.prescribed = prescribed
        self.load_fraction = 0.0
        self.symmetric = model.symmetric

    def residual(self, x: np.ndarray) -> np.ndarray:
        coefficients = self.model.coefficients(x.reshape(-1, 2), self.load_fraction * self.prescribed)
        deformation_gradient = checked_deformation_gradient(self.model, coefficients)
        return self.assembler.update(deformation_gradient) - self.load_fraction * self.external_force

    def tangent_product(self, vector: np.ndarray) -> np.ndarray:
        return self.assembler.tangent_product(vector)

    def tangent_matrix(self) -> sp.csr_matrix:
        return self.assembler.tangent_matrix()


@dataclass
class StaticSolution:
    free: np.ndarray  # (n_free, 2)
    coefficients: np.ndarray  # (NP, 2)
    report: NewtonReport


def solve_static(
    model: TissueModel,
    external_force: np.ndarray,
    prescribed: np.ndarray,
    load_steps: int,
    settings: Solver,
    assembler: Assembler | None = None,
    on_step: Callable[[int, StepRecord], None] | None = None,
    linear: TangentSolver | None = None,
) -> StaticSolution:
    """Incremental-iterative solve of f_int(d) = lambda f_ext with g = lambda g_final.

    external_force (2 n_free,) interleaved; prescribed (Nb, 2) final boundary displacements.
    A step whose Newton iterations fail (divergence or det F <= 0) is halved, up to
    settings.max_step_cuts times; then SolverDivergence names the step and load fraction.
    """
    problem = StaticProblem(model, assembler or Assembler(model), external_force, prescribed)
    linear = linear or TangentSolver()
    path = LoadPath(problem, settings, linear, float(np.linalg.norm(external_force)), model.spacing,
                    1.0 / load_steps)
    report = NewtonReport()
    for step in range(1, load_steps + 1):
        record = path.step(step, step / load_steps)
        report.steps.append(record)
        if on_step is not None:
            on_step(step, record)
    report.linear_solves = report.iterations
    report.factorizations = linear.factorizations
    report.krylov_iterations = linear.krylov_iterations
    report.linear_solver, report.linear_solver_backends = linear.mode, list(linear.backends)
    coefficients = model.coefficients(path.free, prescribed)
    return StaticSolution(path.free, coefficients, report)


class LoadPath:
    """solve_static's march along the load fraction: the free coefficients (n_free, 2) reached
    at `fraction`, each increment started from the secant predictor (the last increment per
    nominal step) and halved where Newton fails."""

    def __init__(self, problem: StaticProblem, settings: Solver, linear: TangentSolver,
                 reference_force: float, length_scale: float, nominal: float):
        self.problem, self.settings, self.linear = problem, settings, linear
        self.reference_force, self.length_scale, self.nominal = reference_force, length_scale, nominal
        self.free = np.zeros((problem.model.n_free, 2))
        self.previous_increment = np.zeros_like(self.free)
        # largest out-of-balance force a step started from: the force scale of displacement
        # control, where a step whose predictor is already exact starts at round-off
        self.out_of_balance = 0.0
        self.fraction = 0.0

    def step(self, step: int, target: float) -> StepRecord:
        """Load step `step`, up to load fraction `target`: increments of the nominal size, the
        size halved at each failure, at most settings.max_step_cuts times."""
        cuts = iterations = 0
        size = self.nominal
        while self.fraction < target - 1e-12:
            trial = min(self.fraction + size, target)
            scale = (trial - self.fraction) / self.nominal
            try:
                x, its, residual, increment, initial = self._newton(trial, scale)
            except (SolverDivergence, InvertedMaterial) as failure:
                if cuts >= self.settings.max_step_cuts:
                    error = SolverDivergence(f"Newton failed at load step {step} (load fraction {trial:.4f}) after "
                                             f"{cuts} step cuts: {failure}")
                    error.last_try = failure
                    raise error from None
                cuts += 1
                size *= 0.5
                self.previous_increment = np.zeros_like(self.free)
                log.info("load step %d: cutting to %.4g (%s)", step, size, failure)
                continue
            self._accept(x, trial, scale, initial)
            iterations += its
        return StepRecord(target, iterations, residual, increment, cuts)

    def _newton(self, trial: float, scale: float) -> tuple[np.ndarray, int, float, float, float]:
        """newton at load fraction `trial` from the secant predictor, `scale` nominal steps on."""
        self.problem.load_fraction = trial
        start = self.free + scale * self.previous_increment  # secant predictor
        return newton(self.problem, start.ravel(), self.settings,
                      max(trial * self.reference_force, self.out_of_balance), self.length_scale, self.linear)

    def _accept(self, x: np.ndarray, trial: float, scale: float, initial: float) -> None:
        """Move to the converged free coefficients `x` at load fraction `trial`."""
        self.out_of_balance = max(self.out_of_balance, initial)
        new_free = x.reshape(-1, 2)
        self.previous_increment = (new_free - self.free) / scale
        self.free = new_free
        self.fraction = trial
