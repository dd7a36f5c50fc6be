"""Lamé moduli fitted to marker displacements (thesis appendix A.2). The moduli minimise

    f(lambda, mu) = sum_i |p_i - q_i(lambda, mu)|^2                          (eq. A.3)

over the markers of all experiments: p_i measured deformed positions, q_i the simulated ones
(calibration.forward). A coarse grid over the search ranges finds the basin; bounded least
squares (scipy's trust-region reflective method) refines it with the exact Jacobian; the
statistics at the optimum say how well each modulus is determined.

Both material models have a PK2 stress linear in the moduli, so scaling both moduli by c is
the same as dividing the forces by c: with displacement-controlled loading alone only
lambda/mu can be identified, and the fit says so. Regions of a given material (the
tissue's `regions`, kept as given) break that scaling: against them the tissue's own
moduli show under displacements too. Regions named in fit.regions have their moduli fitted
with the tissue's: the least squares then runs over every fitted pair, starting each region
at the moduli the file gives it (the grid searches the tissue's own pair with the regions
there).
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..config import Solver
from ..config.blocks import coarsest_spacing
from ..errors import InputError, IterationLimit, NumericalFailure
from .fit_statistics import MODULI, fit_warnings, identified, statistics
from .forward import ExperimentModel
from .inputs import FitSettings, MaterialCalibration, load_material_calibration

log = logging.getLogger(__name__)

# a modulus that moves by more than this many of its standard uncertainties when fitted at
# twice the spacing: its discretization error is no longer small beside the noise's (a third
# of sigma adds 5 % to the combined uncertainty)
DISCRETIZATION_SHARE = 1.0 / 3.0

Progress = Callable[[str, int | None], contextlib.AbstractContextManager]


@contextlib.contextmanager
def no_progress(label: str, total: int | None) -> Iterator[Callable[..., None]]:
    yield lambda *args, **kwargs: None


# what a forward solve may fail with: the solver's own failures, and a singular tangent
FORWARD_FAILURES = (NumericalFailure, ArithmeticError, np.linalg.LinAlgError)


def experiment_label(index: int, name: str) -> str:
    """experiments[i] of the calibration file, with its name when it has one."""
    return f"experiments[{index}]" + (f" ({name!r})" if name else "")


def parameter_point(theta: np.ndarray, names: tuple[str, ...] = MODULI) -> str:
    """`lame_lambda 0.19, lame_mu 0.15 MPa`, and each fitted region's moduli after them."""
    return ", ".join(f"{name} {value:.4g}" for name, value in zip(names, theta)) + " MPa"


class ForwardFailure(NumericalFailure):
    """The forward model of one experiment gave no usable markers at a parameter point."""

    def __init__(self, experiment: str, theta: np.ndarray, cause: str, names: tuple[str, ...] = MODULI):
        super().__init__(f"{experiment} at {parameter_point(theta, names)}: {cause}")
        self.experiment = experiment
        self.cause = cause


class MarkerMisfit:
    """Residual r = p - q over all markers of all experiments, as a function of theta."""

    def __init__(self, problem: MaterialCalibration):
        shared: dict = {}
        self.experiments = [ExperimentModel(problem.tissue, problem.discretization, e, problem.fit.model,
                                            problem.solver, shared, problem.fit.regions)
                            for e in problem.experiments]
        self.names = problem.fit.parameter_names  # of theta's entries
        self.solver = problem.solver
        self.labels = [experiment_label(i, e.name) for i, e in enumerate(problem.experiments)]
        self.measured = np.concatenate([e.measured for e in problem.experiments])  # (n, 2)
        # the evaluations asked for again: the latest (the least squares' Jacobian after its
        # residual) and the point it last took a Jacobian at (`kept`: its solution, which the fit
        # evaluates at the end); every evaluation kept took ~1.5 kB a marker over a fit's 76
        self._cache: dict[tuple[float, ...], tuple[np.ndarray, np.ndarray | None, list]] = {}
        self.kept: tuple[float, ...] | None = None
        self.evaluations: list[np.ndarray] = []
        self.particles = [e.model.n_particles for e in self.experiments]  # each experiment's model

    @property
    def force_controlled(self) -> bool:
        """Every experiment carries a force load: a softer material deforms more."""
        return all(any(load.force is not None for load in e.experiment.loads) for e in self.experiments)

    def evaluate(self, theta: np.ndarray, jacobian: bool = False, quick: bool = False):
        """(r (2n,), dr/dtheta (2n, P) or None, simulated positions per experiment).

        Raises ForwardFailure, naming the experiment, where a static solve fails or its
        markers (or their sensitivities) are not finite."""
        key = tuple(float(v) for v in theta)
        cached = self._cache.get(key)
        if cached is not None and (cached[1] is not None or not jacobian):
            return cached
        self.evaluations.append(np.array(key))
        iterations = self.newton_iterations
        predictions = [self._predict(k, np.array(key), jacobian, quick) for k in range(len(self.experiments))]
        simulated = [q for q, _ in predictions]
        residual = (self.measured - np.concatenate(simulated)).ravel()
        with np.errstate(over="ignore"):  # an overflowing misfit is the caller's to judge
            log.info("evaluation %d: %s: misfit %.6g mm^2 (%d Newton iterations)", len(self.evaluations),
                     parameter_point(np.array(key), self.names), float(residual @ residual),
                     self.newton_iterations - iterations)
        derivative = -np.concatenate([dq for _, dq in predictions]).reshape(-1, len(key)) if jacobian else None
        self._cache = {kept: entry for kept, entry in self._cache.items() if kept == self.kept}
        self._cache[key] = (residual, derivative, simulated)
        return self._cache[key]

    def _predict(self, k: int, theta: np.ndarray, jacobian: bool, quick: bool):
        """Experiment k's markers and sensitivities; ForwardFailure when there are none usable."""
        try:
            positions, derivative = self.experiments[k].predict(theta, jacobian, quick)
        except FORWARD_FAILURES as failure:
            raise ForwardFailure(self.labels[k], theta, str(failure) or type(failure).__name__,
                                 self.names) from failure
        if not (np.all(np.isfinite(positions)) and (derivative is None or np.all(np.isfinite(derivative)))):
            raise ForwardFailure(self.labels[k], theta, "the simulated markers are not finite", self.names)
        return positions, derivative

    @property
    def solves(self) -> int:
        return sum(e.solves for e in self.experiments)

    @property
    def backends(self) -> list[str]:
        """The sparse factorizations that ran (tissue.factorization's `backend`), in order met."""
        return list(dict.fromkeys(backend for e in self.experiments
                                  for backend in (*e.linear.backends, *e.sensitivity_backends)))

    @property
    def cold_starts(self) -> int:
        return sum(e.cold_starts for e in self.experiments)

    @property
    def newton_iterations(self) -> int:
        return sum(e.newton_iterations for e in self.experiments)


# --- grid search ----------------------------------------------------------------------


@dataclass
class GridSearch:
    lame_lambda: np.ndarray  # (n,)
    lame_mu: np.ndarray  # (m,)
    cost: np.ndarray  # (n, m) f = sum |p - q|^2, mm^2; nan where the forward model failed
    best: tuple[float, float]
    failed: int


def grid_axes(fit: FitSettings) -> tuple[np.ndarray, np.ndarray]:
    space = np.geomspace if fit.grid_scale == "log" else np.linspace
    return space(*fit.lame_lambda, fit.grid_points), space(*fit.lame_mu, fit.grid_points)


def grid_search(misfit: MarkerMisfit, fit: FitSettings, advance: Callable[..., None],
                source: str = "", held: tuple[float, ...] = ()) -> GridSearch:
    """f on the grid of the tissue's own moduli (the fitted regions' held at `held`, their
    start), from the stiffest corner towards the softest in a serpentine, so each solve
    warm-starts from a neighbour that deformed less. Under force loads a point softer in both
    moduli than one that failed is not tried: it would deform even more. A point whose
    forward model fails, or whose cost is not finite, stays nan and is never the best; none
    left is an InputError naming `source` (the calibration file) and its fit ranges."""
    lambdas, mus = grid_axes(fit)
    cost = np.full((len(lambdas), len(mus)), np.nan)
    failures: list[tuple[int, int]] = []  # where a solve failed: softer points are skipped
    failed_experiments: dict[str, str] = {}  # experiment -> its first failure
    limited = True  # every failure so far Newton's iteration limit
    tried = 0
    for step, i in enumerate(reversed(range(len(lambdas)))):
        for j in (reversed(range(len(mus))) if step % 2 == 0 else range(len(mus))):
            if misfit.force_controlled and any(i <= a and j <= b for a, b in failures):
                advance()
                continue
            tried += 1
            try:
                residual, _, _ = misfit.evaluate(np.array([lambdas[i], mus[j], *held]), quick=True)
            except ForwardFailure as failure:
                failures.append((i, j))
                failed_experiments.setdefault(failure.experiment, failure.cause)
                limited = limited and iteration_limited(failure)
                log.info("grid point: no solution (%s)", failure)
                advance()
                continue
            with np.errstate(over="ignore"):  # checked here
                value = float(residual @ residual)
            if math.isfinite(value):
                cost[i, j] = value
            else:  # markers finite, yet their squares overflow: no sign of a too soft material
                failed_experiments.setdefault(" and ".join(misfit.labels), f"the misfit f = {value} overflows")
                limited = False
            advance()
    failed = int(np.isnan(cost).sum())
    if failed == cost.size:
        where = (f"all {cost.size} grid points" if tried == cost.size else
                 f"the {tried} stiffest grid point{'s' if tried > 1 else ''} tried, the {cost.size - tried} "
                 f"others softer still (not tried)")
        causes = "; ".join(f"in {label}: {cause}" for label, cause in failed_experiments.items())
        prefix = f"{source}: " if source else ""
        iterations, default = misfit.solver.max_iterations, Solver().max_iterations
        if limited and iterations < default:  # the solver's settings, not the moduli, stop it
            raise InputError(
                f"{prefix}solver.max_iterations: got {iterations}, expected enough Newton iterations for the "
                f"forward model to converge (the default is {default}): every solve the fit's grid tried stopped at "
                f"Newton's iteration limit ({where}); {causes}")
        raise InputError(
            prefix + f"fit: could not evaluate any moduli in lame_lambda {list(fit.lame_lambda)}, lame_mu "
            f"{list(fit.lame_mu)} MPa: the forward model failed at {where}, {causes}"
            + "; expected ranges where the tissue can carry the loads (raise the lower bounds or reduce the loads)")
    i, j = np.unravel_index(np.nanargmin(cost), cost.shape)
    if failed:
        log.info("grid: %d of %d points without a static solution (too soft for the loads)",
                 failed, cost.size)
    return GridSearch(lambdas, mus, cost, (float(lambdas[i]), float(mus[j])), failed)


def iteration_limited(failure: ForwardFailure) -> bool:
    """Whether a forward solve failed on Newton's iteration limit (solver.max_iterations): the
    last try of the load step that failed, after its step cuts, ran out of iterations with a
    finite residual (IterationLimit; not an inverted material, a non-finite residual or a
    failed linear solve)."""
    return isinstance(getattr(failure.__cause__, "last_try", None), IterationLimit)


# --- least-squares refinement ---------------------------------------------------------


@dataclass
class Refinement:
    """The bounded least-squares run from the grid's best point."""

    solution: object  # scipy.optimize.OptimizeResult
    failed_solves: int  # trial points where the static solve failed

    @property
    def optimizer(self) -> dict:
        s = self.solution
        return {"method": "trf", "status": int(s.status), "message": s.message,
                "evaluations": int(s.nfev), "jacobian_evaluations": int(s.njev or 0),
                "failed_solves": self.failed_solves}


def refine(misfit: MarkerMisfit, problem: MaterialCalibration, start: np.ndarray,
           start_cost: float, advance: Callable[..., None]) -> Refinement:
    """Bounded trust-region least squares on r(theta) with the exact Jacobian, from `start`
    (every fitted modulus; its cost f is `start_cost`). A trial point whose forward model
    fails gets a large constant residual, costlier than the start, so the method steps back
    from it and never ends there."""
    from scipy.optimize import least_squares

    fit = problem.fit
    rest = np.concatenate([e.markers for e in problem.experiments])
    measured_scale = float(np.abs(misfit.measured - rest).max())
    count = 2 * len(misfit.measured)
    # residual returned where a trial point cannot be solved: its cost is at least 100 times
    # the start's, so a failed point is never accepted as a step
    penalty = 10.0 * max(measured_scale + 1.0, math.sqrt(start_cost / count))
    failures = 0

    def residual(theta: np.ndarray) -> np.ndarray:
        nonlocal failures
        advance()
        try:
            return misfit.evaluate(theta, jacobian=True)[0]
        except ForwardFailure as failure:
            failures += 1
            log.info("least squares: no solution (%s)", failure)
            return np.full(count, penalty)

    def jacobian(theta: np.ndarray, *_: object) -> np.ndarray:
        misfit.kept = tuple(float(v) for v in theta)  # an accepted point: the solution, if none follows
        try:
            return misfit.evaluate(theta, jacobian=True)[1]
        except ForwardFailure:  # the constant penalty residual there does not change
            return np.zeros((count, len(start)))

    solution = least_squares(residual, np.array(start, dtype=float), jac=jacobian, bounds=fit.bounds(),
                             method="trf", x_scale="jac", ftol=1e-10, xtol=1e-9, gtol=1e-10,
                             max_nfev=fit.max_evaluations)
    return Refinement(solution, failures)


# --- discretization estimate ----------------------------------------------------------


@dataclass
class DiscretizationEstimate:
    """The fit repeated at twice the spacing, from the fitted moduli: how far each modulus
    moves is its discretization error's estimate (the exit_error_estimate_mm of `simulate`
    and `plan` for a calibration). At first order in the spacing the error at the fit's own
    spacing is that change; converging faster, less."""

    spacing: float  # mm, the coarser fit's
    moduli: np.ndarray | None  # (P,) fitted there; None where it could not be fitted
    change: np.ndarray | None  # (P,) |theta(h) - theta(2 h)|
    forward_solves: int
    failure: str | None = None


def discretization_estimate(problem: MaterialCalibration, theta: np.ndarray,
                            advance: Callable[..., None]) -> DiscretizationEstimate:
    """The least squares of the fit at twice its spacing, started at the fitted moduli; not
    made (its `failure` says why) where that spacing is too coarse for the tissue, a model the
    resource guard would refuse on its own (it lets the fit's finer model run)."""
    spacing = problem.estimate_spacing
    size = problem.tissue.bounding_size
    if spacing > coarsest_spacing(size):
        failure = (f"its model at {spacing:g} mm would be too coarse for the tissue ({size[0]:g} x {size[1]:g} mm): "
                   f"a spacing may be at most half the smaller side, {coarsest_spacing(size):g} mm, so that three "
                   "particles span it")
        log.info("discretization estimate: not made (%s)", failure)
        return DiscretizationEstimate(spacing, None, None, 0, failure)
    try:
        coarse = replace(problem, discretization=problem.discretization.replaced(spacing=spacing))
        misfit = MarkerMisfit(coarse)
        residual, _, _ = misfit.evaluate(theta, jacobian=True)
        refinement = refine(misfit, coarse, theta, float(residual @ residual), advance)
    except (InputError, ForwardFailure, *FORWARD_FAILURES) as failure:
        log.info("discretization estimate at spacing %g mm: no fit (%s)", spacing, failure)
        return DiscretizationEstimate(spacing, None, None, 0, str(failure) or type(failure).__name__)
    moduli = refinement.solution.x
    return DiscretizationEstimate(spacing, moduli, np.abs(moduli - theta), misfit.solves)


def discretization_warnings(estimate: DiscretizationEstimate, theta: np.ndarray,
                            uncertainty: tuple[float | None, ...], names: tuple[str, ...]) -> list[str]:
    """A modulus whose estimate is a sizable share of its standard uncertainty, or none."""
    if estimate.change is None:
        return [f"no discretization estimate: the fit at twice the spacing ({estimate.spacing:g} mm) failed "
                f"({estimate.failure}); refit at a finer --spacing to see how far the moduli move"]
    warnings = []
    for name, value, change, sigma in zip(names, theta, estimate.change, uncertainty):
        if sigma is not None and change > DISCRETIZATION_SHARE * sigma:
            warnings.append(f"{name} = {value:.6g} MPa moves by {change:.3g} MPa ({change / sigma:.2g} of its "
                            f"standard uncertainty) when fitted at twice the spacing ({estimate.spacing:g} mm): its "
                            "discretization error is not small beside the markers' noise; refit at a finer "
                            "--spacing and compare")
    return warnings


# --- the fit --------------------------------------------------------------------------


@dataclass
class MaterialFit:
    problem: MaterialCalibration
    lame_lambda: float
    lame_mu: float
    standard_uncertainty: tuple[float | None, float | None]  # MPa
    correlation: float  # of the two estimates
    lambda_over_mu: float
    lambda_over_mu_uncertainty: float | None
    identifiable: bool
    residuals: list[np.ndarray]  # per experiment (n_e, 2): p - q, mm
    simulated: list[np.ndarray]  # per experiment (n_e, 2): q at the optimum
    grid: GridSearch
    path: np.ndarray  # (k, P) parameter points the refinement evaluated, in order
    cost: float  # f at the optimum, mm^2
    optimizer: dict
    forward_solves: int
    grid_solves: int
    cold_starts: int
    newton_iterations: int
    particles: list[int]  # each experiment's model
    linear_solver_backends: list[str]  # the sparse factorizations that ran, static solves and sensitivities
    wall_seconds: float
    warnings: list[str] = field(default_factory=list)
    # every fitted modulus (the tissue's pair, then each fitted region's; fit.parameter_names),
    # their standard uncertainties (None where not identified) and correlations
    parameters: np.ndarray = field(default_factory=lambda: np.zeros(0))
    parameter_uncertainty: tuple[float | None, ...] = ()
    correlations: np.ndarray | None = None
    estimate: DiscretizationEstimate | None = None  # None: not asked for

    @property
    def fitted_regions(self) -> list[tuple[int, float, float, float | None, float | None]]:
        """(region index, lame_lambda, lame_mu and their standard uncertainties) of each
        region whose moduli were fitted, in fit.regions' order."""
        return [(index, float(self.parameters[2 + 2 * j]), float(self.parameters[3 + 2 * j]),
                 *self.parameter_uncertainty[2 + 2 * j: 4 + 2 * j])
                for j, index in enumerate(self.problem.fit.regions)]

    @property
    def fitted_tissue(self):
        """The calibration's tissue at the fitted moduli: its own material and the fitted
        regions' (the others as given)."""
        tissue = self.problem.tissue
        regions = list(tissue.regions)
        for index, lame_lambda, lame_mu, *_ in self.fitted_regions:
            regions[index] = replace(regions[index], material=replace(regions[index].material, lame_lambda=lame_lambda,
                                                                      lame_mu=lame_mu))
        material = replace(tissue.material, lame_lambda=self.lame_lambda, lame_mu=self.lame_mu)
        return replace(tissue, material=material, regions=tuple(regions))

    @property
    def distances(self) -> np.ndarray:
        """|p_i - q_i| over all markers (n,), mm."""
        return np.linalg.norm(np.concatenate(self.residuals), axis=1)


def fit_material(problem: MaterialCalibration, progress: Progress = no_progress,
                 estimate: bool = True) -> MaterialFit:
    """Grid search then bounded least squares on f(lambda, mu) (eq. A.3); with `estimate`,
    the least squares again at twice the spacing for the moduli's discretization error.

    `progress(label, total)` is a context manager yielding advance(); pass
    stitchplan.io.progress.progress_bar for a bar on the terminal.
    """
    start = time.perf_counter()
    misfit = MarkerMisfit(problem)
    with progress("grid search", problem.fit.grid_points ** 2) as advance:
        grid = grid_search(misfit, problem.fit, advance, problem.source, tuple(problem.region_start))
    grid_solves, grid_evaluations = misfit.solves, len(misfit.evaluations)
    with progress("least squares", None) as advance:
        refinement = refine(misfit, problem, np.array([*grid.best, *problem.region_start]),
                            float(np.nanmin(grid.cost)), advance)
    theta = refinement.solution.x
    try:
        r, jac, simulated = misfit.evaluate(theta, jacobian=True)
    except ForwardFailure as failure:  # only where even the grid's best point fails when refined
        raise NumericalFailure(f"fit: the forward model failed at the fitted moduli: {failure}") from None
    stats = statistics(r, jac, theta)
    identifiable = identified(theta, stats, problem.fit)
    # with every region's moduli fitted (or none), scaling them all is dividing the forces
    displacements_only = (len(problem.fit.regions) == len(problem.tissue.regions)
                          and all(load.displacement is not None for e in problem.experiments for load in e.loads))
    warnings = fit_warnings(theta, stats, problem.fit, refinement, displacements_only)
    uncertainty = stats.uncertainty if identifiable else (None,) * len(theta)
    counts = dict(path=np.array(misfit.evaluations[grid_evaluations:]).reshape(-1, len(theta)),
                  forward_solves=misfit.solves, grid_solves=grid_solves, cold_starts=misfit.cold_starts,
                  newton_iterations=misfit.newton_iterations, particles=misfit.particles,
                  linear_solver_backends=misfit.backends)
    del misfit  # its models and factors, before the estimate's at twice the spacing are built
    coarse = None
    if estimate:
        with progress("discretization estimate", None) as advance:
            coarse = discretization_estimate(problem, theta, advance)
        warnings += discretization_warnings(coarse, theta, uncertainty, problem.fit.parameter_names)
    for message in warnings:
        log.warning(message)
    warnings = problem.warnings + warnings  # the inputs' first, said when they were read
    sizes = np.cumsum([len(e.markers) for e in problem.experiments])[:-1]
    return MaterialFit(
        problem=problem,
        lame_lambda=float(theta[0]),
        lame_mu=float(theta[1]),
        # not identifiable: no usable uncertainties (the pair is only known along lambda/mu, or
        # a modulus is on a bound)
        standard_uncertainty=stats.uncertainty[:2] if identifiable else (None, None),
        correlation=stats.correlation,
        lambda_over_mu=float(theta[0] / theta[1]),
        lambda_over_mu_uncertainty=stats.ratio_uncertainty,
        identifiable=identifiable,
        residuals=np.split(r.reshape(-1, 2), sizes),
        simulated=simulated,
        grid=grid,
        cost=float(r @ r),
        optimizer=refinement.optimizer,
        **counts,
        wall_seconds=time.perf_counter() - start,
        warnings=warnings,
        parameters=np.array(theta, dtype=float),
        parameter_uncertainty=uncertainty,
        correlations=stats.correlations,
        estimate=coarse,
    )


def calibrate_material(path: str | Path, spacing: float | None = None, dilation: float | None = None,
                       progress: Progress = no_progress, estimate: bool = True) -> MaterialFit:
    """`stitchplan calibrate material`: load, validate and fit."""
    return fit_material(load_material_calibration(path, spacing, dilation), progress, estimate)
