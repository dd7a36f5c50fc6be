"""Parameter sets drawn from the uncertainty file's distributions, and the scenarios they
make.

Design: a scrambled Sobol sequence (scipy.stats.qmc.Sobol, seeded with the file's `seed`)
in as many dimensions as uncertain parameters; each point u in (0, 1)^k becomes standard
normal z = Phi^-1(u) (scipy.stats.norm.ppf), correlated as x = m + s * (L z) with L the
Cholesky factor of the correlation matrix, m the scenario's values and s the stds.

Truncation to positive values (every parameter is a modulus, a force, a friction or a
thickness): a point with any x_i <= 0 is rejected and the sequence continues, so the
accepted points follow the jointly normal distribution conditioned on all x > 0 (for the
shipped uncertainties, a few % of the values, no point is ever rejected). The sequence is
drawn in powers of two (Sobol's balance properties hold for 2^m points), doubling until
2 x samples points are accepted; a Sobol sequence of 2^(m+1) points starts with those of
2^m, so the accepted points, and their order, depend on the seed only.

Training and held-out sets: the first `samples` accepted points train the robust plan, the
next `samples` are held out to evaluate it (the same seed's stream, never used to build
the plan).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, replace

import numpy as np
from scipy.stats import norm, qmc

from ..config import Scenario
from ..config.uncertainty import REGION_MODULUS, Uncertainty, scenario_values
from ..errors import InputError

MAX_DOUBLINGS = 12  # at most 2^12 x the wanted points: a distribution mostly below 0 is refused
U_EDGE = 1e-12  # keeps Phi^-1 finite at the unit cube's faces


@dataclass(frozen=True)
class Design:
    """The drawn parameter sets (rows; columns `names`) and how they were drawn."""

    names: tuple[str, ...]
    nominal: np.ndarray  # (k,) the scenario's values
    train: np.ndarray  # (samples, k)
    held_out: np.ndarray  # (samples, k)
    drawn: int  # Sobol points drawn
    rejected: int  # of those before the last accepted one, rejected for a value <= 0

    def as_record(self) -> dict:
        return {"design": "scrambled Sobol (scipy.stats.qmc), normal by inverse CDF, correlated by "
                          "the Cholesky factor; points with a value <= 0 rejected",
                "sobol_points_drawn": self.drawn, "rejected_points": self.rejected,
                "training_samples": len(self.train), "held_out_samples": len(self.held_out),
                "split": "first `samples` accepted points train the robust plan, the next `samples` "
                         "are held out and evaluated"}


def normal_points(uncertainty: Uncertainty, nominal: np.ndarray, count: int) -> np.ndarray:
    """The first `count` points (count, k) of the seeded design, before truncation."""
    k = len(uncertainty.names)
    sobol = qmc.Sobol(d=k, scramble=True, seed=uncertainty.seed)
    with warnings.catch_warnings():  # count is a power of two; scipy warns for others only
        warnings.simplefilter("ignore", UserWarning)
        u = sobol.random_base2(int(math.log2(count)))
    z = norm.ppf(np.clip(u, U_EDGE, 1.0 - U_EDGE))  # (count, k)
    factor = np.linalg.cholesky(uncertainty.correlation)  # (k, k), lower
    return nominal + (z @ factor.T) * uncertainty.std  # (count, k)


def draw(uncertainty: Uncertainty, scenario: Scenario) -> Design:
    """2 x samples parameter sets, positive, reproducible for the seed (module docstring)."""
    nominal = scenario_values(scenario, uncertainty.names)
    wanted = 2 * uncertainty.samples
    count = 1 << max(1, math.ceil(math.log2(wanted)))
    for _ in range(MAX_DOUBLINGS + 1):
        points = normal_points(uncertainty, nominal, count)
        positive = np.all(points > 0.0, axis=1)
        if positive.sum() >= wanted:
            accepted = np.flatnonzero(positive)[:wanted]
            rejected = int(accepted[-1] + 1 - wanted)
            chosen = points[accepted]
            return Design(uncertainty.names, nominal, chosen[:uncertainty.samples], chosen[uncertainty.samples:],
                          count, rejected)
        count *= 2
    stds = ", ".join(f"{name} {std:g}" for name, std in zip(uncertainty.names, uncertainty.std))
    raise InputError(f"{uncertainty.path}: parameters: got stds {stds}, expected distributions mostly above 0 "
                     f"(only {int(positive.sum())} of {count} points drawn had every value positive, "
                     f"{wanted} wanted)")


def with_parameters(scenario: Scenario, names: tuple[str, ...], values: np.ndarray) -> Scenario:
    """The scenario with the parameters `names` set to `values` (a validated copy). The
    moduli lame_lambda and lame_mu replace tissue.material's; a region keeps its own unless
    its `tissue.regions[k].lame_*` are among `names` (a calibration that fitted them: on a
    scenario with regions config.uncertainty.check_against_scenario takes moduli only from a
    calibration fitted around the same regions, the model where that is what they mean)."""
    given = dict(zip(names, (float(v) for v in values)))
    tissue, needle = scenario.tissue, scenario.needle
    moduli = {k: v for k, v in given.items() if k in ("lame_lambda", "lame_mu")}
    material = replace(tissue.material, **moduli)
    regions = list(tissue.regions)
    for name, value in given.items():
        region = REGION_MODULUS.fullmatch(name)
        if region:  # a region's moduli a calibration fitted
            k = int(region.group(1))
            regions[k] = replace(regions[k], material=replace(regions[k].material, **{region.group(2): value}))
    tissue = replace(tissue, material=material, regions=tuple(regions),
                     **({"thickness": given["thickness"]} if "thickness" in given else {}))
    needle_changes = {k: v for k, v in given.items() if k in ("friction", "cutting_force")}
    if needle_changes:
        needle = replace(needle, **needle_changes)
    return replace(scenario, tissue=tissue, needle=needle)
