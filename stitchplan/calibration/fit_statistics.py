"""What the fit of the Lame moduli says about them (thesis appendix A.2): the standard
uncertainties and correlations of the estimates from the Jacobian at the optimum
(sigma^2 (J^T J)^-1), whether the data identify every fitted modulus, and the warnings a user
should read: moduli the data cannot separate, a modulus on a bound of its search range, one
poorly determined, a least squares that stopped early or stepped where the forward model
failed."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from ..config.calibration import MAX_SEARCH_MODULUS, MIN_SEARCH_MODULUS
from .inputs import FitSettings

CORRELATION_LIMIT = 0.999  # |corr(lambda, mu)| above this: the data cannot separate them
POORLY_DETERMINED = 0.25  # relative standard uncertainty above which a modulus gets a warning
# a 95 % interval wider than 1.1 x 1.96 standard uncertainties (Student's t for the residual's
# degrees of freedom, 13 or fewer): sigma^2 from so few residuals is itself poorly known, and
# +-1.96 sigma covers far less than 95 % (2 markers for 2 moduli: 81 %, Student's t)
FEW_DEGREES_WIDENING = 1.1
MODULI = ("lame_lambda", "lame_mu")


class LeastSquaresRun(Protocol):
    """What the warnings read of the least-squares run (material_fit.Refinement)."""

    solution: Any  # scipy.optimize.OptimizeResult: its status and nfev
    failed_solves: int


def moduli_on_bound(theta: np.ndarray, fit: FitSettings) -> list[tuple[int, int]]:
    """(parameter index, 0 for the low bound or 1 for the high) of each fitted modulus on a
    bound of its search range. The margin is relative to the value, not the range: ranges
    span decades, and a fit of 0.2 MPa in [0.01, 1e6] is not on its bound. On a low bound
    of 0 (lambda's) a relative margin is none: there a value below the smallest non-zero
    bound a range may have (1 Pa, softer than any tissue) is 0; the least squares ends
    such fits at 1e-14 MPa and less, not at 0."""
    found = []
    for k, bounds in enumerate(zip(*fit.bounds())):
        for side, bound in enumerate(bounds):
            margin = 1e-6 * max(abs(bound), abs(theta[k])) if bound else MIN_SEARCH_MODULUS
            if abs(theta[k] - bound) <= margin:
                found.append((k, side))
    return found


def identified(theta: np.ndarray, stats: Statistics, fit: FitSettings) -> bool:
    """Every modulus estimated: the data separate them and none ends on a bound of its search
    range (where the best fit may lie beyond and (J^T J)^-1 does not describe the estimate)."""
    return stats.separable and not moduli_on_bound(theta, fit)


def bound_advice(name: str, side: int, bounds: tuple[float, float]) -> str:
    """How to let the fit past a bound, within the moduli a search range may reach
    (stitchplan.config.calibration); at their limits, what to check in the data instead."""
    low, high = bounds
    smallest = 0.0 if name == "lame_lambda" else MIN_SEARCH_MODULUS  # lambda may start at 0
    if side == 1 and high < MAX_SEARCH_MODULUS:
        return f"raise fit.{name}[1] (up to {MAX_SEARCH_MODULUS:g} MPa)"
    if side == 0 and low > smallest:
        return f"lower fit.{name}[0] (down to {smallest:g} MPa)"
    if side == 0 and name == "lame_lambda":
        return ("a negative lame_lambda (Poisson's ratio below 0) is no tissue's: it is 0 within the "
                "markers' scatter, or their change of area is off (check that they are in mm)")
    limit = f"past {MAX_SEARCH_MODULUS:g}" if side == 1 else f"below {smallest:g}"
    return (f"no search may go {limit} MPa, so no material it allows fits the markers: check that they "
            "are in mm, and the loads in N and in their directions")


@dataclass
class Statistics:
    uncertainty: tuple[float | None, ...]  # standard uncertainties, MPa, per parameter
    correlation: float  # of the tissue's two estimates
    ratio_uncertainty: float | None  # of lambda/mu
    correlations: np.ndarray | None = None  # (P, P) of every estimate, where (J^T J) inverts
    # indices of the parameters no marker moves with (a zero column of the Jacobian): there no
    # correlation can be computed (it is nan)
    insensitive: tuple[int, ...] = ()
    degrees_of_freedom: int = 0  # residuals less fitted moduli, m - P, behind sigma^2

    @property
    def separable(self) -> bool:
        """The data tell the moduli apart (the fit also needs them inside their ranges)."""
        if self.uncertainty[0] is None:
            return False
        if self.correlations is None:
            return abs(self.correlation) < CORRELATION_LIMIT
        return bool(np.abs(self.correlations - np.eye(len(self.correlations))).max() < CORRELATION_LIMIT)


def statistics(residual: np.ndarray, jacobian: np.ndarray, theta: np.ndarray) -> Statistics:
    """Standard uncertainties sigma^2 (J^T J)^-1, sigma^2 = |r|^2 / (m - P), and the
    correlations of the P estimates (for two, minus the cosine between the Jacobian's
    columns)."""
    m, count = jacobian.shape
    sigma2 = float(residual @ residual) / max(m - count, 1)
    normal = jacobian.T @ jacobian
    scale = np.sqrt(np.diag(normal))
    if np.any(scale == 0.0):
        return Statistics((None,) * count, float("nan"), None, insensitive=tuple(np.flatnonzero(scale == 0.0).tolist()),
                          degrees_of_freedom=m - count)
    scaled = normal / np.outer(scale, scale)  # unit diagonal
    uncertainty: tuple[float | None, ...] = (None,) * count
    correlations = None
    if np.linalg.cond(scaled) < 1e12:
        inverse = np.linalg.inv(scaled)
        covariance = sigma2 * inverse / np.outer(scale, scale)
        uncertainty = tuple(float(math.sqrt(v)) for v in np.diag(covariance))
        spread = np.sqrt(np.diag(inverse))
        correlations = inverse / np.outer(spread, spread)
    if count == 2 or correlations is None:
        correlation = float(-scaled[0, 1]) if count == 2 else float("nan")
    else:
        correlation = float(correlations[0, 1])
    # lambda/mu is determined even when the pair is not: its gradient is orthogonal to the
    # scaling direction theta that the data cannot see, so the pseudo-inverse is exact there
    covariance = sigma2 * np.linalg.pinv(scaled, rcond=1e-9) / np.outer(scale, scale)
    gradient = np.zeros(count)
    gradient[:2] = [1.0 / theta[1], -theta[0] / theta[1] ** 2]
    ratio_variance = float(gradient @ covariance @ gradient)
    return Statistics(uncertainty, correlation, math.sqrt(max(ratio_variance, 0.0)), correlations,
                      degrees_of_freedom=m - count)


def few_degrees_warning(stats: Statistics) -> str | None:
    """A warning where the residuals leave so few degrees of freedom that a 95 % interval is
    more than FEW_DEGREES_WIDENING times +-1.96 standard uncertainties; None otherwise."""
    from scipy.stats import t as student  # scipy is loaded by the fit already

    dof = stats.degrees_of_freedom
    if dof < 1:
        return None
    factor = float(student.ppf(0.975, dof))
    if factor <= FEW_DEGREES_WIDENING * 1.959964:
        return None
    return (f"the standard uncertainties rest on {dof} degree(s) of freedom only (2 x markers less fitted "
            f"moduli): the noise they are scaled by is itself poorly known, and a 95 % interval is "
            f"+-{factor:.3g} standard uncertainties, not +-1.96 (Student's t); add markers")


def least_separated(stats: Statistics, names: tuple[str, ...]) -> tuple[str, str, float] | None:
    """The two moduli the data tell apart least and the correlation of their estimates; None
    where (J^T J) does not invert."""
    if stats.correlations is None:
        return None
    off = np.abs(stats.correlations - np.eye(len(names)))
    i, j = sorted(int(k) for k in np.unravel_index(np.argmax(off), off.shape))
    return names[i], names[j], float(stats.correlations[i, j])


def _correlation_text(value: float) -> str:
    """A correlation as a warning writes it; one that could not be computed said so."""
    return f"{value:+.4f}" if math.isfinite(value) else "not computable: the markers' sensitivities are not finite"


def fit_warnings(theta: np.ndarray, stats: Statistics, fit: FitSettings,
                 refinement: LeastSquaresRun, displacements_only: bool = True) -> list[str]:
    """What a user should know about the fitted moduli, most serious first.
    `displacements_only`: every load of every experiment is a prescribed displacement, on a
    tissue of one material (the case where scaling both moduli moves no marker)."""
    identifiable = identified(theta, stats, fit)
    names = fit.parameter_names
    warnings: list[str] = []
    if not stats.separable:
        scaled = "both moduli" if len(names) == 2 else "every modulus"
        why = (f"as when every load is a prescribed displacement (scaling {scaled} then moves no "
               "marker, as here); add a force-controlled experiment" if displacements_only else
               "the markers' motion does not tell them apart (too little of it, or markers where the "
               "tissue hardly deforms: check their units, mm); add markers where the tissue deforms "
               "or another experiment")
        if stats.insensitive:
            still = " and ".join(names[k] for k in stats.insensitive)
            warnings.append(
                f"the data cannot separate the fitted moduli: the correlation of their estimates could not be "
                f"computed, as no marker moves with {still} at the fitted moduli (a zero sensitivity: markers "
                "where the tissue is held, or a model that did not deform under the loads); add markers where "
                "the tissue deforms, and check the loads and the solver settings")
        elif len(names) == 2:
            warnings.append(
                f"the data cannot separate lame_lambda and lame_mu (correlation of the estimates "
                f"{_correlation_text(stats.correlation)}): only lame_lambda/lame_mu = {theta[0] / theta[1]:.4g} is "
                f"determined, {why}")
        else:
            pair = least_separated(stats, names)
            which = (f"{pair[0]} and {pair[1]} (correlation of the estimates {pair[2]:+.4f})" if pair else
                     f"the {len(names)} fitted moduli (the markers' sensitivities to them are linearly dependent)")
            warnings.append(f"the data cannot separate {which}, {why}; or fit fewer regions (fit.regions)")
    for k, side in moduli_on_bound(theta, fit):
        modulus = MODULI[k % 2]
        bounds = (fit.lame_lambda, fit.lame_mu)[k % 2]
        warnings.append(f"{names[k]} = {theta[k]:.6g} MPa lies on the {('low', 'high')[side]} bound of its search "
                        f"range [{bounds[0]:g}, {bounds[1]:g}], so it is not identified (the best fit may lie "
                        f"beyond): {bound_advice(modulus, side, bounds)}")
    if refinement.failed_solves:
        warnings.append(f"least squares tried {refinement.failed_solves} parameter point(s) where "
                        "the forward model failed (too soft for the loads): the optimum may lie at "
                        "the edge of the solvable materials; check the cost surface plot")
    for k, name in enumerate(names):
        u = stats.uncertainty[k]
        if identifiable and u is not None and u > POORLY_DETERMINED * theta[k]:
            warnings.append(f"{name} is poorly determined: standard uncertainty {u:.3g} MPa is "
                            f"{100 * u / theta[k]:.0f} % of its value; add markers or experiments")
    few = few_degrees_warning(stats) if identifiable else None
    if few:
        warnings.append(few)
    if refinement.solution.status == 0:
        warnings.append(f"least squares stopped after {refinement.solution.nfev} evaluations "
                        f"(fit.max_evaluations) before converging")
    return warnings
