"""The forward model of the material calibration (thesis appendix A.2): the static solve of
one experiment for any (lambda, mu), the simulated marker positions q_i = X_i + u(X_i) with
u the RK interpolant (eq. 3.18) of the solution, and their exact sensitivities.

The solver is the one of `stitchplan deform`: each experiment's TissueModel and Assembler
are built once and only `TissueModel.material` changes between solves. Solves after the
first start Newton from the nearest solution already found (falling back to the
load-stepped cold solve of `deform` when that fails), which is where most of the speed
comes from.

The Jacobian dq/d(lambda, mu) is exact, not finite differences: both material models have
a PK2 stress linear in the moduli, S = lambda S_lambda(F) + mu S_mu(F), so differentiating
the equilibrium f_int(d; lambda, mu) = f_ext at fixed loads gives

    K dd/dtheta = -B^T (w F S_theta)                                         (theta = lambda, mu)

one factorisation of the converged tangent K per parameter point. Material regions keep the
moduli they give: the fitted law holds at the other quadrature points, and S_theta is zero
at theirs. A region whose moduli are fitted too (fit.regions) adds its own pair to theta,
its S_theta non-zero at its quadrature points only.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from ..config import Discretization, Load, Material, Scenario, Solver, Tissue
from ..errors import InvertedMaterial, SolverDivergence
from ..tissue.assembly import Assembler
from ..tissue.deform import external_forces, prescribed_displacements, to_free
from ..tissue.material import NeoHookean, PointwiseMaterial, SaintVenantKirchhoff
from ..tissue.model import model_for_scenario
from ..tissue.factorization import factorize
from ..tissue.solver import (
    StaticProblem,
    TangentSolver,
    newton,
    solve_static,
)
from .inputs import Experiment

log = logging.getLogger(__name__)

WARM_START_ITERATIONS = 15  # Newton iterations allowed from a neighbouring solution


class ExperimentModel:
    """The static problem of one experiment, solved for any (lambda, mu).

    The TissueModel, Assembler, load vectors and the RK shape functions at the markers are
    built once; each solve only swaps `model.material`. Experiments that prescribe
    displacements on the same segments can share one TissueModel through `shared`.
    """

    def __init__(self, tissue: Tissue, discretization: Discretization, experiment: Experiment,
                 model_name: str, settings: Solver, shared: dict | None = None,
                 fitted_regions: tuple[int, ...] = ()):
        self.experiment = experiment
        self.fitted_regions = tuple(fitted_regions)  # tissue.regions whose moduli theta holds too
        self.settings = settings
        self.model_name = model_name
        self.scenario = Scenario(tissue=tissue, discretization=discretization, loads=experiment.loads,
                                 load_steps=experiment.load_steps, solver=settings)
        # experiments with the same load segments (of the same kinds) share one discretization:
        # every segment end is a particle, and displacement segments are held
        key = tuple((load.segment, load.displacement is not None) for load in experiment.loads)
        shared = {} if shared is None else shared
        if key not in shared:
            model = model_for_scenario(self.scenario)
            shared[key] = (model, Assembler(model))
        self.model, self.assembler = shared[key]
        # with regions the model holds a material per quadrature point (part 0: the tissue's own)
        built = self.model.material
        self._regions = built if isinstance(built, PointwiseMaterial) else None
        self.external = to_free(self.model, external_forces(self.model, self.scenario))  # (2 n_free,)
        self.prescribed = prescribed_displacements(self.model, self.scenario)  # (Nb, 2)
        # u(X_i) = N(X_i) d (deform.interpolate), with N(X_i) computed once
        self.marker_values = self.model.shape_functions_at(experiment.markers).values  # (n, NP)
        self.marker_free = (self.marker_values @ self.model.boundary.free_map).tocsr()  # (n, n_free)
        self.linear = TangentSolver()
        self.sensitivity_backends: list[str] = []  # the sensitivities' factorizations (the static solves': linear's)
        self._solutions: list[tuple[np.ndarray, np.ndarray]] = []  # (theta, free (n_free, 2))
        self.solves = 0
        self.cold_starts = 0
        self.newton_iterations = 0

    def material(self, theta: np.ndarray, fixed_regions_stressed: bool = True):
        """The constitutive law at the parameters theta: the fitted law at the tissue's own
        (lambda, mu) = theta[:2], and where the tissue has regions theirs, a fitted region's
        at its pair of theta (theta[2 + 2j : 4 + 2j] for fit.regions[j]).
        fixed_regions_stressed=False: the other regions' laws at zero moduli (no stress), for
        the stress per unit of a fitted modulus."""
        # also at the unit directions of theta, which no Material may hold
        law = SaintVenantKirchhoff if self.model_name == "saint-venant-kirchhoff" else NeoHookean
        fitted = law(float(theta[0]), float(theta[1]))
        if self._regions is None:
            return fitted
        parts = list(self._regions.parts)
        parts[0] = fitted
        pair_of = {1 + region: j for j, region in enumerate(self.fitted_regions)}
        for k in range(1, len(parts)):
            if k in pair_of:
                parts[k] = type(parts[k])(*(float(v) for v in theta[2 + 2 * pair_of[k]: 4 + 2 * pair_of[k]]))
            elif not fixed_regions_stressed:
                parts[k] = type(parts[k])(0.0, 0.0)
        return PointwiseMaterial(tuple(parts), self._regions.index)

    def predict(self, theta: np.ndarray, jacobian: bool = False,
                quick: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """Simulated marker positions q_i (n, 2) and, if asked, dq_i/dtheta (n, 2, P)
        indexed [marker, xy, parameter].

        Raises SolverDivergence when the static solve fails (e.g. far too soft a material).
        quick: give up after at most 2 load-step cuts (for a coarse look such as the grid).
        """
        theta = np.asarray(theta, dtype=float)
        settings = self.settings
        if quick:
            settings = replace(settings, max_step_cuts=min(settings.max_step_cuts, 2))
        free = self._solve(theta, settings)
        coefficients = self.model.coefficients(free, self.prescribed)
        positions = self.experiment.markers + self.marker_values @ coefficients
        if not jacobian:
            return positions, None
        return positions, self._sensitivity(coefficients)

    def _solve(self, theta: np.ndarray, settings: Solver) -> np.ndarray:
        """Free coefficients (n_free, 2) of the equilibrium for the moduli theta: a warm start
        from the nearest solution found so far, else the load-stepped cold solve."""
        self.model.material = self.material(theta)
        self.solves += 1
        free = self._warm_solve(theta, settings) if self._solutions else None
        if free is None:
            self.cold_starts += 1
            solution = solve_static(self.model, self.external, self.prescribed,
                                    self.experiment.load_steps, settings, self.assembler,
                                    linear=self.linear)
            self.newton_iterations += solution.report.iterations
            free = solution.free
        self._solutions.append((theta.copy(), free))
        return free

    def _warm_solve(self, theta: np.ndarray, settings: Solver) -> np.ndarray | None:
        """Newton at full load from the solution nearest in log(theta); None if it fails."""
        log_theta = np.log(theta + 1e-9)
        nearest = min(self._solutions,
                      key=lambda s: float(np.sum((np.log(s[0] + 1e-9) - log_theta) ** 2)))
        problem = StaticProblem(self.model, self.assembler, self.external, self.prescribed)
        reference = self._reference_force(problem)
        problem.load_fraction = 1.0
        warm = replace(settings, max_iterations=min(settings.max_iterations, WARM_START_ITERATIONS))
        try:
            x, iterations, *_ = newton(problem, nearest[1].ravel(), warm, reference,
                                       self.model.spacing, self.linear)
        except (SolverDivergence, InvertedMaterial) as failure:
            log.debug("warm start at %s failed (%s); cold solve", theta, failure)
            return None
        self.newton_iterations += iterations
        return x.reshape(-1, 2)

    def _reference_force(self, problem: StaticProblem) -> float:
        """Force scale for Newton's tolerance: |f_ext|, or for displacement control the
        out-of-balance force a cold solve's first load step starts from (scaled to full load)."""
        reference = float(np.linalg.norm(self.external))
        if reference > 0.0:
            return reference
        steps = self.experiment.load_steps
        problem.load_fraction = 1.0 / steps
        try:
            return steps * float(np.linalg.norm(problem.residual(np.zeros(2 * self.model.n_free))))
        except InvertedMaterial:
            return 0.0

    def _sensitivity(self, coefficients: np.ndarray) -> np.ndarray:
        """dq/dtheta (n, 2, P) from K dd/dtheta = -B^T (w F S_theta) at the converged state."""
        model = self.model
        deformation_gradient = model.deformation_gradient(coefficients)  # (nq, 2, 2)
        weights = model.quadrature_weights[:, None, None]
        count = 2 + 2 * len(self.fitted_regions)
        columns = []
        for unit in np.eye(count):  # S_theta: the stress per unit of each fitted modulus
            stress, _ = self.material(unit, fixed_regions_stressed=False).pk2_stress(deformation_gradient)
            first_piola = deformation_gradient @ stress  # (nq, 2, 2)
            columns.append(self.assembler.gradient_t @ (first_piola * weights).reshape(-1))
        # the assembler was last updated at the converged state, so this is K there
        tangent = factorize(self.assembler.tangent_matrix())
        if tangent.backend not in self.sensitivity_backends:
            self.sensitivity_backends.append(tangent.backend)
        dfree = -tangent.solve(np.stack(columns, axis=1))  # (2 n_free, P)
        du = self.marker_free @ dfree.reshape(model.n_free, 2 * count)  # (n, 2 P): (xy, theta)
        return du.reshape(-1, 2, count)


def simulate_markers(tissue: Tissue, discretization: Discretization, loads: tuple[Load, ...],
                     markers: np.ndarray, material: Material, load_steps: int = 10,
                     settings: Solver | None = None) -> np.ndarray:
    """Deformed positions (n, 2) of markers at rest positions (n, 2) under `loads`: the
    forward model of the calibration, used to make synthetic data and in tests."""
    experiment = Experiment("", tuple(loads), load_steps, np.asarray(markers, float),
                            np.asarray(markers, float))
    forward = ExperimentModel(tissue, discretization, experiment, material.model, settings or Solver())
    positions, _ = forward.predict(np.array([material.lame_lambda, material.lame_mu]))
    return positions
