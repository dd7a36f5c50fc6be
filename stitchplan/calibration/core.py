"""Calibration: Lamé moduli from marker displacements, needle friction and cutting force
from force recordings.

Material (thesis appendix A.2). The moduli minimise the marker misfit

    f(lambda, mu) = sum_i |p_i - q_i(lambda, mu)|^2                          (eq. A.3)

over the markers of all experiments: p_i measured deformed positions, q_i = X_i + u(X_i)
the simulated ones, u the RK interpolant (eq. 3.18) of the static solution at the marker's
rest position X_i. A coarse grid over the search ranges finds the basin; bounded least
squares (scipy's trust-region reflective method) refines it. The forward model is the
solver of `stitchplan deform`: each experiment's TissueModel and Assembler are built once
and only `TissueModel.material` changes between solves. Solves after the first start
Newton from the nearest solution already found (falling back to the load-stepped cold
solve of `deform` when that fails), which is where most of the speed comes from.

The Jacobian dq/d(lambda, mu) is exact, not finite differences: both material models have
a PK2 stress linear in the moduli, S = lambda S_lambda(F) + mu S_mu(F), so differentiating
the equilibrium f_int(d; lambda, mu) = f_ext at fixed loads gives

    K dd/dtheta = -B^T (w F S_theta)                                         (theta = lambda, mu)

one factorisation of the converged tangent K per parameter point. The same linearity
means that scaling both moduli by c is the same as dividing the forces by c: with
displacement-controlled loading alone only lambda/mu can be identified, and the fit says so.

Needle (thesis section 5.2). The force needed to turn the needle in air is fitted by a
line in the angle (bearing friction, cable drag: the background); subtracted from the
recording in tissue it leaves the tissue's share, fitted by a line in the inserted length
radius x angle: slope = friction (N/mm), intercept = cutting force (N).

Layout: input readers (YAML, CSV) -> typed inputs -> numerics on arrays -> result records
-> report dictionaries and writers. The numerics never read files or print.
"""

from __future__ import annotations

import contextlib
import csv
import logging
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..config import (
    MATERIAL_MODELS,
    Discretization,
    Load,
    Material,
    ScenarioError,
    Solver,
    Tissue,
    _choice,
    _fail,
    _integer,
    _mapping,
    _number,
    _required,
    default_spacing,
    parse_discretization,
    parse_loads,
    parse_solver,
    parse_tissue,
    read_yaml,
)

log = logging.getLogger(__name__)

MARKER_COLUMNS = ("x", "y", "x_def", "y_def")
FORCE_COLUMNS = ("angle_rad", "force_N")
MIN_FORCE_SAMPLES = 5
MIN_ANGLE_SPAN = 0.1  # rad: less than ~6 degrees of rotation cannot separate slope and offset
CORRELATION_LIMIT = 0.999  # |corr(lambda, mu)| above this: the data cannot separate them
POORLY_DETERMINED = 0.25  # relative standard uncertainty above which a modulus gets a warning
GRID_SCALES = ("log", "linear")

Progress = Callable[[str, int | None], contextlib.AbstractContextManager]


@contextlib.contextmanager
def no_progress(label: str, total: int | None) -> Iterator[Callable[..., None]]:
    yield lambda *args, **kwargs: None


# --- CSV input ------------------------------------------------------------------------


def read_columns(path: str | Path, columns: tuple[str, ...],
                 label: str = "") -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Read a numeric CSV whose header is exactly `columns` (any order).

    Lines starting with '#' and blank lines are skipped (data files may carry a comment
    header). Returns ({column: values (n,)}, file line number of each row (n,)).
    Every problem is a ScenarioError naming the file (and `label`, e.g. the YAML field).
    """
    where = f"{label}: {path}" if label else f"{path}"
    try:
        with open(path, newline="", encoding="utf-8-sig") as handle:
            lines = [(number, line) for number, line in enumerate(handle, start=1)
                     if line.strip() and not line.lstrip().startswith("#")]
    except FileNotFoundError:
        raise ScenarioError(f"{where}: file not found") from None
    except (OSError, UnicodeDecodeError) as error:
        reason = getattr(error, "strerror", None) or type(error).__name__
        raise ScenarioError(f"{where}: cannot be read ({reason})") from None
    if not lines:
        raise ScenarioError(f"{where}: empty, expected a header {','.join(columns)} and data rows")
    rows = list(csv.reader(line for _, line in lines))
    header = [name.strip() for name in rows[0]]
    if sorted(header) != sorted(columns):
        raise ScenarioError(f"{where}: columns {','.join(header)!r}, expected exactly "
                            f"{','.join(columns)!r}")
    values = np.empty((len(rows) - 1, len(header)))
    for r, (row, (number, _)) in enumerate(zip(rows[1:], lines[1:])):
        if len(row) != len(header):
            raise ScenarioError(f"{where} line {number}: {len(row)} values, expected "
                                f"{len(header)} ({','.join(header)})")
        for c, text in enumerate(row):
            try:
                value = float(text)
            except ValueError:
                value = math.nan
            if not math.isfinite(value):
                raise ScenarioError(f"{where} line {number}, column {header[c]}: got "
                                    f"{text.strip()!r}, expected a finite number")
            values[r, c] = value
    line_numbers = np.array([number for number, _ in lines[1:]], dtype=int)
    return {name: values[:, c] for c, name in enumerate(header)}, line_numbers


# --- material calibration input -------------------------------------------------------


@dataclass(frozen=True)
class Experiment:
    """One loading of the slab and the markers measured under it."""

    name: str
    loads: tuple[Load, ...]
    load_steps: int
    markers: np.ndarray  # (n, 2) rest positions X_i, mm
    measured: np.ndarray  # (n, 2) measured deformed positions p_i, mm
    source: str = ""


@dataclass(frozen=True)
class FitSettings:
    model: str
    lame_lambda: tuple[float, float]  # search range, MPa
    lame_mu: tuple[float, float]
    grid_points: int = 6  # per axis
    grid_scale: str = "log"
    max_evaluations: int = 40  # forward evaluations allowed to the least-squares refinement


@dataclass(frozen=True)
class MaterialCalibration:
    tissue: Tissue
    experiments: tuple[Experiment, ...]
    fit: FitSettings
    discretization: Discretization
    solver: Solver = field(default_factory=Solver)
    name: str = ""
    source: str = ""

    @property
    def n_markers(self) -> int:
        return sum(len(e.markers) for e in self.experiments)


CALIBRATION_KEYS = ("name", "tissue", "experiments", "fit", "discretization", "solver")
EXPERIMENT_KEYS = ("name", "loads", "markers", "load_steps")
FIT_KEYS = ("lame_lambda", "lame_mu", "model", "grid", "grid_scale", "max_evaluations")


def _range(value: Any, path: str, positive: bool) -> tuple[float, float]:
    expected = f"[low, high] with {'0 <' if positive else '0 <='} low < high (MPa)"
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise _fail(path, value, expected)
    low = _number(value[0], f"{path}[0]", positive=positive, nonnegative=not positive, unit="MPa")
    high = _number(value[1], f"{path}[1]", positive=True, unit="MPa")
    if not low < high:
        raise _fail(path, list(value), expected)
    return low, high


def parse_fit(raw: Any, path: str = "fit") -> FitSettings:
    block = _mapping(raw, path, FIT_KEYS)
    lame_lambda = _range(_required(block, "lame_lambda", path), f"{path}.lame_lambda", positive=False)
    lame_mu = _range(_required(block, "lame_mu", path), f"{path}.lame_mu", positive=True)
    default_scale = "log" if lame_lambda[0] > 0 else "linear"
    scale = _choice(block.get("grid_scale", default_scale), f"{path}.grid_scale", GRID_SCALES)
    if scale == "log" and lame_lambda[0] <= 0:
        raise _fail(f"{path}.grid_scale", scale,
                    "linear when the lame_lambda range starts at 0 (a log grid needs positive bounds)")
    return FitSettings(
        model=_choice(block.get("model", "saint-venant-kirchhoff"), f"{path}.model", MATERIAL_MODELS),
        lame_lambda=lame_lambda,
        lame_mu=lame_mu,
        grid_points=_integer(block.get("grid", FitSettings.grid_points), f"{path}.grid", 2, 50),
        grid_scale=scale,
        max_evaluations=_integer(block.get("max_evaluations", FitSettings.max_evaluations),
                                 f"{path}.max_evaluations", 2, 1000),
    )


def parse_experiment(raw: Any, tissue: Tissue, folder: Path, path: str) -> Experiment:
    block = _mapping(raw, path, EXPERIMENT_KEYS)
    loads = parse_loads(_required(block, "loads", path), tissue.size, f"{path}.loads")
    if not loads:
        raise _fail(f"{path}.loads", block["loads"], "at least one load (force or displacement)")
    if not tissue.clamped and all(load.displacement is None for load in loads):
        raise ScenarioError(f"{path}.loads: only forces on a tissue with no clamped edge, expected "
                            "tissue.clamped or a displacement load to hold the slab in place")
    markers_name = _required(block, "markers", path)
    if not isinstance(markers_name, str) or not markers_name:
        raise _fail(f"{path}.markers", markers_name, "a CSV file name (relative to the YAML file)")
    markers_path = folder / markers_name
    data, lines = read_columns(markers_path, MARKER_COLUMNS, f"{path}.markers")
    if len(lines) == 0:
        raise ScenarioError(f"{path}.markers: {markers_path}: no marker rows, expected at least one")
    rest = np.stack([data["x"], data["y"]], axis=1)
    outside = np.flatnonzero(~tissue.domain.contains(rest))
    if len(outside):
        k = outside[0]
        raise ScenarioError(
            f"{path}.markers: {markers_path} line {lines[k]}: rest position "
            f"({rest[k, 0]:g}, {rest[k, 1]:g}) mm, expected a point inside "
            f"[0, {tissue.size[0]:g}] x [0, {tissue.size[1]:g}] mm")
    name = block.get("name", "")
    if not isinstance(name, str):
        raise _fail(f"{path}.name", name, "a string")
    return Experiment(
        name=name,
        loads=loads,
        load_steps=_integer(block.get("load_steps", 10), f"{path}.load_steps", 1, 10000),
        markers=rest,
        measured=np.stack([data["x_def"], data["y_def"]], axis=1),
        source=str(markers_path),
    )


def parse_material_calibration(raw: Any, folder: Path, source: str = "") -> MaterialCalibration:
    block = _mapping(raw, "calibration", CALIBRATION_KEYS)
    tissue_raw = _required(block, "tissue", "calibration")
    if isinstance(tissue_raw, dict) and "material" in tissue_raw:
        raise ScenarioError("tissue.material: given, expected no material in a calibration file "
                            "(the moduli are what is fitted; choose the model with fit.model)")
    tissue = parse_tissue(tissue_raw, need_material=False)
    experiments_raw = _required(block, "experiments", "calibration")
    if not isinstance(experiments_raw, (list, tuple)) or not experiments_raw:
        raise _fail("experiments", experiments_raw, "a non-empty list of experiments")
    experiments = tuple(parse_experiment(item, tissue, folder, f"experiments[{i}]")
                        for i, item in enumerate(experiments_raw))
    fit = parse_fit(_required(block, "fit", "calibration"))
    if sum(len(e.markers) for e in experiments) < 2:
        raise ScenarioError("experiments: 1 marker in all, expected at least 2 (4 coordinates "
                            "for 2 parameters and their uncertainty)")
    discretization = parse_discretization(block.get("discretization"))
    if not (isinstance(block.get("discretization"), dict) and "spacing" in block["discretization"]):
        discretization = replace(discretization, spacing=default_spacing(tissue, None))
    name = block.get("name", "")
    if not isinstance(name, str):
        raise _fail("name", name, "a string")
    tissue = replace(tissue, material=Material(fit.model, *_start_point(fit)))
    return MaterialCalibration(tissue, experiments, fit, discretization,
                               parse_solver(block.get("solver")), name, source)


def load_material_calibration(path: str | Path, spacing: float | None = None,
                              dilation: float | None = None) -> MaterialCalibration:
    """Read and validate a calibration YAML; marker files are relative to it."""
    path = Path(path)
    raw, _ = read_yaml(path)
    problem = parse_material_calibration(raw, path.parent, str(path))
    if spacing is not None:
        _number(spacing, "--spacing", positive=True, unit="mm")
    if dilation is not None and not _number(dilation, "--dilation", positive=True) > 1.0:
        raise _fail("--dilation", dilation, "a number > 1 (kernel support / spacing)")
    overrides = {"spacing": spacing, "dilation": dilation}
    if any(v is not None for v in overrides.values()):
        values = {**asdict(problem.discretization),
                  **{k: v for k, v in overrides.items() if v is not None}}
        problem = replace(problem, discretization=parse_discretization(values))
    return problem


def _start_point(fit: FitSettings) -> tuple[float, float]:
    """Geometric (or arithmetic) middle of the search ranges."""
    def mid(low: float, high: float) -> float:
        return math.sqrt(low * high) if fit.grid_scale == "log" else 0.5 * (low + high)

    return mid(*fit.lame_lambda), mid(*fit.lame_mu)


# --- forward model --------------------------------------------------------------------


def material_class(model: str):
    from ..tissue.material import NeoHookean, SaintVenantKirchhoff

    return SaintVenantKirchhoff if model == "saint-venant-kirchhoff" else NeoHookean


class ExperimentModel:
    """The static problem of one experiment, solved for any (lambda, mu).

    The TissueModel, Assembler, load vectors and the RK shape functions at the markers are
    built once; each solve only swaps `model.material`.
    """

    def __init__(self, tissue: Tissue, discretization: Discretization, experiment: Experiment,
                 model_name: str, settings: Solver, shared: dict | None = None):
        from ..tissue.assembly import Assembler
        from ..config import Scenario
        from ..tissue.deform import external_forces, prescribed_displacements, to_free
        from ..tissue.model import model_for_scenario
        from ..tissue.solver import TangentSolver

        self.experiment = experiment
        self.settings = settings
        self.material_class = material_class(model_name)
        self.scenario = Scenario(tissue=tissue, discretization=discretization, loads=experiment.loads,
                                 load_steps=experiment.load_steps, solver=settings)
        # experiments with the same displacement segments share one discretization
        key = tuple(load.segment for load in experiment.loads if load.displacement is not None)
        shared = {} if shared is None else shared
        if key not in shared:
            model = model_for_scenario(self.scenario)
            shared[key] = (model, Assembler(model))
        self.model, self.assembler = shared[key]
        self.external = to_free(self.model, external_forces(self.model, self.scenario))  # (2 n_free,)
        self.prescribed = prescribed_displacements(self.model, self.scenario)  # (Nb, 2)
        # u(X_i) = N(X_i) d (deform.interpolate), with N(X_i) computed once
        self.marker_values = self.model.shape_functions_at(experiment.markers).values  # (n, NP)
        self.marker_free = (self.marker_values @ self.model.boundary.free_map).tocsr()  # (n, n_free)
        self.linear = TangentSolver()
        self._solutions: list[tuple[np.ndarray, np.ndarray]] = []  # (theta, free (n_free, 2))
        self.solves = 0
        self.cold_starts = 0
        self.newton_iterations = 0

    def _reference_force(self, problem) -> float:
        """Force scale for Newton's tolerance: |f_ext|, or for displacement control the
        out-of-balance force a cold solve's first load step starts from (scaled to full load)."""
        reference = float(np.linalg.norm(self.external))
        if reference > 0.0:
            return reference
        from ..tissue.solver import InvertedMaterial

        steps = self.experiment.load_steps
        problem.load_fraction = 1.0 / steps
        try:
            return steps * float(np.linalg.norm(problem.residual(np.zeros(2 * self.model.n_free))))
        except InvertedMaterial:
            return 0.0

    def _solve(self, theta: np.ndarray, settings: Solver) -> np.ndarray:
        """Free coefficients (n_free, 2) of the equilibrium for the moduli theta."""
        from ..tissue.solver import InvertedMaterial, SolverDivergence, StaticProblem, newton, solve_static

        self.model.material = self.material_class(float(theta[0]), float(theta[1]))
        self.solves += 1
        if self._solutions:
            log_theta = np.log(theta + 1e-9)
            nearest = min(self._solutions,
                          key=lambda s: float(np.sum((np.log(s[0] + 1e-9) - log_theta) ** 2)))
            problem = StaticProblem(self.model, self.assembler, self.external, self.prescribed)
            reference = self._reference_force(problem)
            problem.load_fraction = 1.0
            warm = replace(settings, max_iterations=min(settings.max_iterations, 15))
            try:
                x, iterations, *_ = newton(problem, nearest[1].ravel(), warm, reference,
                                             self.model.spacing, self.linear)
                self.newton_iterations += iterations
                free = x.reshape(-1, 2)
                self._solutions.append((theta.copy(), free))
                return free
            except (SolverDivergence, InvertedMaterial) as failure:
                log.debug("warm start at %s failed (%s); cold solve", theta, failure)
        self.cold_starts += 1
        solution = solve_static(self.model, self.external, self.prescribed, self.experiment.load_steps,
                                settings, self.assembler, linear=self.linear)
        self.newton_iterations += solution.report.iterations
        self._solutions.append((theta.copy(), solution.free))
        return solution.free

    def predict(self, theta: np.ndarray, jacobian: bool = False,
                quick: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """Simulated marker positions q_i (n, 2) and, if asked, dq_i/dtheta (n, 2, 2)
        indexed [marker, xy, theta].

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

    def _sensitivity(self, coefficients: np.ndarray) -> np.ndarray:
        """dq/dtheta from K dd/dtheta = -B^T (w F S_theta) at the converged state."""
        from ..tissue.solver import factorize

        model = self.model
        deformation_gradient = model.deformation_gradient(coefficients)  # (nq, 2, 2)
        weights = model.quadrature_weights[:, None, None]
        columns = []
        for unit in ((1.0, 0.0), (0.0, 1.0)):  # S_lambda, S_mu: the stress per unit modulus
            stress, _ = self.material_class(*unit).pk2_stress(deformation_gradient)
            first_piola = deformation_gradient @ stress  # (nq, 2, 2)
            columns.append(self.assembler.gradient_t @ (first_piola * weights).reshape(-1))
        # the assembler was last updated at the converged state, so this is K there
        tangent = factorize(self.assembler.tangent_matrix())
        dfree = -tangent.solve(np.stack(columns, axis=1))  # (2 n_free, 2)
        n_free = model.n_free
        du = self.marker_free @ dfree.reshape(n_free, 4)  # (n, 4): (xy, theta)
        return du.reshape(-1, 2, 2)


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


class MarkerMisfit:
    """Residual r = p - q over all markers of all experiments, as a function of theta."""

    def __init__(self, problem: MaterialCalibration):
        shared: dict = {}
        self.experiments = [ExperimentModel(problem.tissue, problem.discretization, e, problem.fit.model,
                                            problem.solver, shared) for e in problem.experiments]
        self.measured = np.concatenate([e.measured for e in problem.experiments])  # (n, 2)
        self._cache: dict[tuple[float, float], tuple[np.ndarray, np.ndarray | None, list]] = {}
        self.evaluations: list[np.ndarray] = []
        self.particles = self.experiments[0].model.n_particles

    @property
    def force_controlled(self) -> bool:
        """Every experiment carries a force load: a softer material deforms more."""
        return all(any(load.force is not None for load in e.experiment.loads) for e in self.experiments)

    def evaluate(self, theta: np.ndarray, jacobian: bool = False, quick: bool = False):
        """(r (2n,), dr/dtheta (2n, 2) or None, simulated positions per experiment)."""
        key = (float(theta[0]), float(theta[1]))
        cached = self._cache.get(key)
        if cached is not None and (cached[1] is not None or not jacobian):
            return cached
        self.evaluations.append(np.array(key))
        predictions = [e.predict(np.array(key), jacobian, quick) for e in self.experiments]
        simulated = [q for q, _ in predictions]
        residual = (self.measured - np.concatenate(simulated)).ravel()
        derivative = -np.concatenate([dq for _, dq in predictions]).reshape(-1, 2) if jacobian else None
        self._cache[key] = (residual, derivative, simulated)
        return self._cache[key]

    @property
    def solves(self) -> int:
        return sum(e.solves for e in self.experiments)

    @property
    def cold_starts(self) -> int:
        return sum(e.cold_starts for e in self.experiments)

    @property
    def newton_iterations(self) -> int:
        return sum(e.newton_iterations for e in self.experiments)


# --- material fit ---------------------------------------------------------------------


@dataclass
class GridSearch:
    lame_lambda: np.ndarray  # (n,)
    lame_mu: np.ndarray  # (m,)
    cost: np.ndarray  # (n, m) f = sum |p - q|^2, mm^2; nan where the solve failed
    best: tuple[float, float]
    failed: int


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
    path: np.ndarray  # (k, 2) parameter points the refinement evaluated, in order
    cost: float  # f at the optimum, mm^2
    optimizer: dict
    forward_solves: int
    grid_solves: int
    cold_starts: int
    newton_iterations: int
    particles: int
    wall_seconds: float
    warnings: list[str] = field(default_factory=list)

    @property
    def distances(self) -> np.ndarray:
        """|p_i - q_i| over all markers (n,), mm."""
        return np.linalg.norm(np.concatenate(self.residuals), axis=1)


def grid_axes(fit: FitSettings) -> tuple[np.ndarray, np.ndarray]:
    space = np.geomspace if fit.grid_scale == "log" else np.linspace
    return space(*fit.lame_lambda, fit.grid_points), space(*fit.lame_mu, fit.grid_points)


def grid_search(misfit: MarkerMisfit, fit: FitSettings, advance: Callable[..., None]) -> GridSearch:
    """f on the grid, from the stiffest corner towards the softest in a serpentine, so each
    solve warm-starts from a neighbour that deformed less. Under force loads a point softer
    in both moduli than one that failed is not tried: it would deform even more."""
    from ..tissue.solver import SolverDivergence

    lambdas, mus = grid_axes(fit)
    cost = np.full((len(lambdas), len(mus)), np.nan)
    failures: list[tuple[int, int]] = []
    for step, i in enumerate(reversed(range(len(lambdas)))):
        for j in (reversed(range(len(mus))) if step % 2 == 0 else range(len(mus))):
            if misfit.force_controlled and any(i <= a and j <= b for a, b in failures):
                advance()
                continue
            try:
                residual, _, _ = misfit.evaluate(np.array([lambdas[i], mus[j]]), quick=True)
                cost[i, j] = residual @ residual
            except SolverDivergence as failure:
                failures.append((i, j))
                log.info("grid point lambda=%.4g mu=%.4g: no solution (%s)", lambdas[i], mus[j], failure)
            advance()
    failed = int(np.isnan(cost).sum())
    if failed == cost.size:
        raise ScenarioError(
            f"fit: the static solve failed at all {cost.size} grid points of lame_lambda "
            f"{list(fit.lame_lambda)}, lame_mu {list(fit.lame_mu)} MPa; expected ranges where the "
            "tissue can carry the loads (raise the lower bounds or reduce the loads)")
    i, j = np.unravel_index(np.nanargmin(cost), cost.shape)
    if failed:
        log.info("grid: %d of %d points without a static solution (too soft for the loads)",
                 failed, cost.size)
    return GridSearch(lambdas, mus, cost, (float(lambdas[i]), float(mus[j])), failed)


def _statistics(residual: np.ndarray, jacobian: np.ndarray, theta: np.ndarray) -> dict:
    """Standard uncertainties sigma^2 (J^T J)^-1, sigma^2 = |r|^2 / (m - 2), and the
    correlation of the two estimates (= minus the cosine between the Jacobian's columns)."""
    m = len(residual)
    sigma2 = float(residual @ residual) / max(m - 2, 1)
    normal = jacobian.T @ jacobian
    scale = np.sqrt(np.diag(normal))
    if np.any(scale == 0.0):
        return {"uncertainty": (None, None), "correlation": float("nan"), "ratio_uncertainty": None}
    scaled = normal / np.outer(scale, scale)  # unit diagonal
    correlation = float(-scaled[0, 1])
    uncertainty: tuple[float | None, float | None] = (None, None)
    if np.linalg.cond(scaled) < 1e12:
        covariance = sigma2 * np.linalg.inv(scaled) / np.outer(scale, scale)
        uncertainty = tuple(float(math.sqrt(v)) for v in np.diag(covariance))
    # lambda/mu is determined even when the pair is not: its gradient is orthogonal to the
    # scaling direction theta that the data cannot see, so the pseudo-inverse is exact there
    covariance = sigma2 * np.linalg.pinv(scaled, rcond=1e-9) / np.outer(scale, scale)
    gradient = np.array([1.0 / theta[1], -theta[0] / theta[1] ** 2])
    ratio_variance = float(gradient @ covariance @ gradient)
    return {"uncertainty": uncertainty, "correlation": correlation,
            "ratio_uncertainty": math.sqrt(max(ratio_variance, 0.0))}


def fit_material(problem: MaterialCalibration, progress: Progress = no_progress) -> MaterialFit:
    """Grid search then bounded least squares on f(lambda, mu) (eq. A.3).

    `progress(label, total)` is a context manager yielding advance(); pass
    stitchplan.progress.progress_bar for a bar on the terminal.
    """
    from scipy.optimize import least_squares

    from ..tissue.solver import SolverDivergence

    start = time.perf_counter()
    fit = problem.fit
    misfit = MarkerMisfit(problem)
    with progress("grid search", fit.grid_points ** 2) as advance:
        grid = grid_search(misfit, fit, advance)
    grid_solves = misfit.solves
    grid_evaluations = len(misfit.evaluations)
    rest = np.concatenate([e.markers for e in problem.experiments])
    measured_scale = float(np.abs(misfit.measured - rest).max())
    penalty = 10.0 * (measured_scale + 1.0)  # residual returned where a trial point cannot be solved
    failures = 0

    with progress("least squares", None) as advance:
        def residual(theta: np.ndarray) -> np.ndarray:
            nonlocal failures
            advance()
            try:
                return misfit.evaluate(theta, jacobian=True)[0]
            except SolverDivergence:
                failures += 1
                return np.full(2 * len(misfit.measured), penalty)

        def jacobian(theta: np.ndarray, *_: Any) -> np.ndarray:
            return misfit.evaluate(theta, jacobian=True)[1]

        lower = np.array([fit.lame_lambda[0], fit.lame_mu[0]])
        upper = np.array([fit.lame_lambda[1], fit.lame_mu[1]])
        solution = least_squares(residual, np.array(grid.best), jac=jacobian, bounds=(lower, upper),
                                 method="trf", x_scale="jac", ftol=1e-10, xtol=1e-9, gtol=1e-10,
                                 max_nfev=fit.max_evaluations)
    theta = solution.x
    r, jac, simulated = misfit.evaluate(theta, jacobian=True)
    stats = _statistics(r, jac, theta)
    identifiable = abs(stats["correlation"]) < CORRELATION_LIMIT and stats["uncertainty"][0] is not None

    warnings: list[str] = []
    if not identifiable:
        warnings.append(
            f"the data cannot separate lame_lambda and lame_mu (correlation of the estimates "
            f"{stats['correlation']:+.4f}): only lame_lambda/lame_mu = {theta[0] / theta[1]:.4g} is "
            "determined, as when every load is a prescribed displacement (scaling both moduli then "
            "moves no marker); add a force-controlled experiment")
    for k, (name, (lo, hi)) in enumerate((("lame_lambda", fit.lame_lambda), ("lame_mu", fit.lame_mu))):
        margin = 1e-6 * (hi - lo)
        if identifiable and (theta[k] <= lo + margin or theta[k] >= hi - margin):
            warnings.append(f"{name} = {theta[k]:.6g} MPa lies on the bound of its search range "
                            f"[{lo:g}, {hi:g}]: widen fit.{name}")
    if failures:
        warnings.append(f"least squares tried {failures} parameter point(s) where the static solve "
                        "failed (too soft for the loads): the optimum may lie at the edge of the "
                        "solvable materials; check the cost surface plot")
    for k, name in enumerate(("lame_lambda", "lame_mu")):
        u = stats["uncertainty"][k]
        if identifiable and u is not None and u > POORLY_DETERMINED * theta[k]:
            warnings.append(f"{name} is poorly determined: standard uncertainty {u:.3g} MPa is "
                            f"{100 * u / theta[k]:.0f} % of its value; add markers or experiments")
    if solution.status == 0:
        warnings.append(f"least squares stopped after {solution.nfev} evaluations "
                        f"(fit.max_evaluations) before converging")
    for message in warnings:
        log.warning(message)

    sizes = np.cumsum([len(e.markers) for e in problem.experiments])[:-1]
    residuals = np.split(r.reshape(-1, 2), sizes)
    return MaterialFit(
        problem=problem,
        lame_lambda=float(theta[0]),
        lame_mu=float(theta[1]),
        standard_uncertainty=stats["uncertainty"],
        correlation=stats["correlation"],
        lambda_over_mu=float(theta[0] / theta[1]),
        lambda_over_mu_uncertainty=stats["ratio_uncertainty"],
        identifiable=identifiable,
        residuals=residuals,
        simulated=simulated,
        grid=grid,
        path=np.array(misfit.evaluations[grid_evaluations:]).reshape(-1, 2),
        cost=float(r @ r),
        optimizer={"method": "trf", "status": int(solution.status), "message": solution.message,
                   "evaluations": int(solution.nfev),
                   "jacobian_evaluations": int(solution.njev or 0), "failed_solves": failures},
        forward_solves=misfit.solves,
        grid_solves=grid_solves,
        cold_starts=misfit.cold_starts,
        newton_iterations=misfit.newton_iterations,
        particles=misfit.particles,
        wall_seconds=time.perf_counter() - start,
        warnings=warnings,
    )


def calibrate_material(path: str | Path, spacing: float | None = None, dilation: float | None = None,
                       progress: Progress = no_progress) -> MaterialFit:
    """`stitchplan calibrate material`: load, validate and fit."""
    return fit_material(load_material_calibration(path, spacing, dilation), progress)


# --- needle friction and cutting force -----------------------------------------------


@dataclass
class LineFit:
    """y = intercept + slope x by least squares, with standard errors from the residuals."""

    intercept: float
    slope: float
    covariance: np.ndarray  # (2, 2) of (intercept, slope)
    residual_std: float  # sqrt(SSR / (n - 2))
    r_squared: float

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return self.intercept + self.slope * np.asarray(x)


def fit_line(x: np.ndarray, y: np.ndarray) -> LineFit:
    design = np.stack([np.ones_like(x), x], axis=1)  # (n, 2)
    coefficients, *_ = np.linalg.lstsq(design, y, rcond=None)
    residual = y - design @ coefficients
    ssr = float(residual @ residual)
    sigma2 = ssr / max(len(x) - 2, 1)
    sst = float(np.sum((y - y.mean()) ** 2))
    return LineFit(float(coefficients[0]), float(coefficients[1]),
                   sigma2 * np.linalg.inv(design.T @ design), math.sqrt(sigma2),
                   1.0 - ssr / sst if sst > 0 else 1.0)


@dataclass
class NeedleFit:
    radius: float  # mm
    friction: float  # N/mm
    cutting_force: float  # N
    standard_uncertainty: tuple[float, float]  # (friction, cutting_force)
    tissue_fit: LineFit  # corrected force (N) against inserted length (mm)
    background: LineFit  # air force (N) against angle (rad)
    air: np.ndarray  # (n, 2) angle, force
    tissue: np.ndarray  # (n, 2) angle, force
    corrected: np.ndarray  # (n,) tissue force minus background, N
    inserted_length: np.ndarray  # (n,) radius x angle, mm
    warnings: list[str] = field(default_factory=list)
    sources: tuple[str, str] = ("", "")


def fit_needle(air_angle: np.ndarray, air_force: np.ndarray, tissue_angle: np.ndarray,
               tissue_force: np.ndarray, radius: float) -> NeedleFit:
    """Background line in air, subtracted at the tissue angles; line against radius x angle.

    The uncertainties combine the scatter of both recordings: the background's coefficient
    covariance is carried through the linear map from background line to (cutting, friction).
    """
    background = fit_line(air_angle, air_force)
    corrected = tissue_force - background(tissue_angle)
    length = radius * tissue_angle
    tissue_fit = fit_line(length, corrected)
    design = np.stack([np.ones_like(length), length], axis=1)
    projector = np.linalg.solve(design.T @ design, design.T)  # (2, n): data -> (intercept, slope)
    carried = projector @ np.stack([np.ones_like(tissue_angle), tissue_angle], axis=1)  # (2, 2)
    covariance = tissue_fit.covariance + carried @ background.covariance @ carried.T
    friction, cutting = tissue_fit.slope, tissue_fit.intercept
    warnings = []
    span = air_angle[-1] - air_angle[0]
    if tissue_angle[0] < air_angle[0] - 0.01 * span or tissue_angle[-1] > air_angle[-1] + 0.01 * span:
        warnings.append(
            f"the tissue recording ({tissue_angle[0]:.3g} to {tissue_angle[-1]:.3g} rad) reaches beyond "
            f"the air recording ({air_angle[0]:.3g} to {air_angle[-1]:.3g} rad): the background is "
            "extrapolated there")
    if tissue_fit.r_squared < 0.9:
        warnings.append(f"the corrected force is far from linear in the inserted length "
                        f"(R^2 = {tissue_fit.r_squared:.3f}); check the recordings")
    if friction < 0 or cutting < 0:
        warnings.append(f"negative fitted value (friction {friction:.4g} N/mm, cutting force "
                        f"{cutting:.4g} N): a scenario's needle block refuses negative values")
    for message in warnings:
        log.warning(message)
    return NeedleFit(
        radius=radius, friction=friction, cutting_force=cutting,
        standard_uncertainty=(math.sqrt(covariance[1, 1]), math.sqrt(covariance[0, 0])),
        tissue_fit=tissue_fit, background=background,
        air=np.stack([air_angle, air_force], axis=1),
        tissue=np.stack([tissue_angle, tissue_force], axis=1),
        corrected=corrected, inserted_length=length, warnings=warnings,
    )


def read_force_recording(path: str | Path, label: str) -> tuple[np.ndarray, np.ndarray]:
    """angle_rad, force_N of a recording; at least MIN_FORCE_SAMPLES rows, angles strictly
    increasing over at least MIN_ANGLE_SPAN rad."""
    data, lines = read_columns(path, FORCE_COLUMNS, label)
    angle, force = data["angle_rad"], data["force_N"]
    if len(angle) < MIN_FORCE_SAMPLES:
        raise ScenarioError(f"{label}: {path}: {len(angle)} samples, expected at least "
                            f"{MIN_FORCE_SAMPLES}")
    steps = np.diff(angle)
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0)) + 1
        raise ScenarioError(f"{label}: {path} line {lines[k]}: angle_rad {angle[k]:g} after "
                            f"{angle[k - 1]:g}, expected strictly increasing angles")
    span = float(angle[-1] - angle[0])
    if span < MIN_ANGLE_SPAN:
        raise ScenarioError(f"{label}: {path}: angle_rad spans {span:.3g} rad, expected at least "
                            f"{MIN_ANGLE_SPAN:g} rad")
    return angle, force


def calibrate_needle(air: str | Path, tissue: str | Path, radius: float) -> NeedleFit:
    """`stitchplan calibrate needle`: read both recordings, validate and fit."""
    radius = _number(radius, "--radius", positive=True, unit="mm")
    air_angle, air_force = read_force_recording(air, "--air")
    tissue_angle, tissue_force = read_force_recording(tissue, "--tissue")
    if tissue_angle[0] < 0:
        raise ScenarioError(f"--tissue: {tissue}: first angle_rad {tissue_angle[0]:g}, expected "
                            "angles >= 0 rad (rotation since the tip touched the tissue)")
    result = fit_needle(air_angle, air_force, tissue_angle, tissue_force, radius)
    result.sources = (str(air), str(tissue))
    return result


# --- reports and writers --------------------------------------------------------------


def _round(value: float | None, digits: int = 6) -> float | None:
    return None if value is None or not math.isfinite(value) else float(f"{value:.{digits}g}")


def _created() -> str:
    import datetime as _dt

    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def material_report(result: MaterialFit) -> dict:
    """fitted.yaml: `material:` pastes into a scenario's tissue block; `fit:` says how well
    the moduli are determined; `diagnostics:` how the fit ran."""
    problem, grid = result.problem, result.grid
    distances = result.distances
    d = problem.discretization
    per_experiment = []
    for k, (experiment, residual) in enumerate(zip(problem.experiments, result.residuals)):
        e = np.linalg.norm(residual, axis=1)
        per_experiment.append({
            "name": experiment.name or f"experiments[{k}]",
            "markers": len(e),
            "residual_mean_mm": _round(float(e.mean())),
            "residual_std_mm": _round(float(e.std(ddof=1)) if len(e) > 1 else 0.0),
            "residual_max_mm": _round(float(e.max())),
        })
    from .. import __version__

    return {
        "material": {
            "model": problem.fit.model,
            "lame_lambda": _round(result.lame_lambda),
            "lame_mu": _round(result.lame_mu),
        },
        # the same figures at the top level, as SCENARIO.md names them
        "lame_lambda": _round(result.lame_lambda),
        "lame_mu": _round(result.lame_mu),
        "residual_mean_mm": _round(float(distances.mean())),
        "residual_std_mm": _round(float(distances.std(ddof=1)) if len(distances) > 1 else 0.0),
        "fit": {
            "residual_mean_mm": _round(float(distances.mean())),
            "residual_std_mm": _round(float(distances.std(ddof=1)) if len(distances) > 1 else 0.0),
            "residual_max_mm": _round(float(distances.max())),
            "residual_rms_mm": _round(math.sqrt(result.cost / len(distances))),
            "cost_mm2": _round(result.cost),
            "standard_uncertainty": {
                "lame_lambda": _round(result.standard_uncertainty[0], 3),
                "lame_mu": _round(result.standard_uncertainty[1], 3),
            },
            "correlation": _round(result.correlation, 4),
            "lambda_over_mu": _round(result.lambda_over_mu),
            "lambda_over_mu_uncertainty": _round(result.lambda_over_mu_uncertainty, 3),
            "identifiable": result.identifiable,
            "warnings": list(result.warnings),
            "markers": int(len(distances)),
            "experiments": per_experiment,
        },
        "diagnostics": {
            "forward_solves": result.forward_solves,
            "grid_forward_solves": result.grid_solves,
            "refinement_forward_solves": result.forward_solves - result.grid_solves,
            "cold_starts": result.cold_starts,
            "newton_iterations": result.newton_iterations,
            "wall_seconds": round(result.wall_seconds, 3),
            "search_range": {"lame_lambda": list(problem.fit.lame_lambda),
                             "lame_mu": list(problem.fit.lame_mu)},
            "grid": {
                "points_per_axis": problem.fit.grid_points,
                "scale": problem.fit.grid_scale,
                "best": {"lame_lambda": _round(grid.best[0]), "lame_mu": _round(grid.best[1]),
                         "cost_mm2": _round(float(np.nanmin(grid.cost)))},
                "failed_points": grid.failed,
            },
            "least_squares": {**result.optimizer, "start": [_round(v) for v in grid.best]},
            "discretization": {"particles": result.particles, "spacing_mm": d.spacing,
                               "dilation": d.dilation, "quadrature_order": d.quadrature_order,
                               "basis_order": d.basis_order},
            "source": problem.source,
            "stitchplan_version": __version__,
            "created_utc": _created(),
        },
    }


def material_plots(result: MaterialFit, folder: str | Path) -> list[Path]:
    from ..io.plots import plot_cost_surface, plot_marker_residuals

    folder = Path(folder)
    grid, problem = result.grid, result.problem
    paths = [folder / "cost_surface.png", folder / "marker_residuals.png"]
    plot_cost_surface(paths[0], grid.lame_lambda, grid.lame_mu, grid.cost, grid.best,
                      (result.lame_lambda, result.lame_mu), result.path,
                      log_axes=problem.fit.grid_scale == "log")
    plot_marker_residuals(
        paths[1], problem.tissue.size,
        [e.markers for e in problem.experiments], [e.measured for e in problem.experiments],
        result.simulated, [[load.segment for load in e.loads] for e in problem.experiments],
        [e.name or f"experiments[{k}]" for k, e in enumerate(problem.experiments)])
    return paths


def write_material_outputs(result: MaterialFit, out: str | Path,
                           plot_dir: str | Path | None = None) -> None:
    """Plots first, then the fitted YAML (atomically), so fitted.yaml appears only on success."""
    from ..io.files import write_yaml

    if plot_dir is not None:
        material_plots(result, plot_dir)
    header = ("# stitchplan calibrate material: Lame moduli fitted to marker displacements\n"
              "# (thesis eq. A.3). Paste the `material:` block into a scenario's `tissue:` block.\n")
    write_yaml(out, material_report(result), header)


def material_summary_line(result: MaterialFit) -> str:
    u = result.standard_uncertainty
    spread = [f" +- {value:.2g}" if value is not None else "" for value in u]
    flag = "" if result.identifiable else " (NOT identifiable: see warnings)"
    spread_mm = float(result.distances.std(ddof=1)) if len(result.distances) > 1 else 0.0
    return (f"calibrate material: lame_lambda {result.lame_lambda:.6g}{spread[0]} MPa, lame_mu "
            f"{result.lame_mu:.6g}{spread[1]} MPa{flag}; marker residual "
            f"{result.distances.mean():.4g} +- {spread_mm:.2g} mm; "
            f"{result.forward_solves} forward solves, {result.wall_seconds:.2f} s")


def needle_report(result: NeedleFit) -> dict:
    """needle.yaml: `friction` and `cutting_force` paste into a scenario's needle block."""
    fit, background = result.tissue_fit, result.background
    from .. import __version__

    return {
        "friction": _round(result.friction),
        "cutting_force": _round(result.cutting_force),
        "diagnostics": {
            "radius_mm": result.radius,
            "standard_uncertainty": {"friction": _round(result.standard_uncertainty[0], 3),
                                     "cutting_force": _round(result.standard_uncertainty[1], 3)},
            "r_squared": _round(fit.r_squared),
            "residual_std_N": _round(fit.residual_std, 4),
            "samples": {"air": len(result.air), "tissue": len(result.tissue)},
            "inserted_length_mm": [_round(float(result.inserted_length.min())),
                                   _round(float(result.inserted_length.max()))],
            "background": {"offset_N": _round(background.intercept),
                           "slope_N_per_rad": _round(background.slope),
                           "residual_std_N": _round(background.residual_std, 4),
                           "angle_range_rad": [_round(float(result.air[0, 0])),
                                               _round(float(result.air[-1, 0]))]},
            "warnings": list(result.warnings),
            "air": result.sources[0],
            "tissue": result.sources[1],
            "stitchplan_version": __version__,
            "created_utc": _created(),
        },
    }


def write_needle_outputs(result: NeedleFit, out: str | Path, plot: str | Path | None = None) -> None:
    from ..io.files import write_yaml

    if plot is not None:
        from ..io.plots import plot_needle_forces

        plot_needle_forces(plot, result.air, result.tissue, result.background.intercept,
                           result.background.slope, result.inserted_length, result.corrected,
                           result.friction, result.cutting_force)
    header = ("# stitchplan calibrate needle: friction (N/mm) and cutting force (N) from force\n"
              "# recordings (thesis section 5.2). Paste both into a scenario's `needle:` block.\n")
    write_yaml(out, needle_report(result), header)


def needle_summary_line(result: NeedleFit) -> str:
    u = result.standard_uncertainty
    return (f"calibrate needle: friction {result.friction:.6g} +- {u[0]:.2g} N/mm, cutting_force "
            f"{result.cutting_force:.6g} +- {u[1]:.2g} N (R^2 {result.tissue_fit.r_squared:.4f})")
