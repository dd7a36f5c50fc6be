"""What every insertion into one scenario's tissue at one discretization starts from
(PreparedTissue: the tissue model and K0, the tangent at rest, with its factor), and the
refusal of a discretization whose K0 is nearly singular (refuse_singular_stiffness).
"""

from __future__ import annotations

import math
import time

import numpy as np
import scipy.sparse as sp

from ..config import Scenario
from ..config.boundary_points import shown_point
from ..errors import InputError
from ..tissue.assembly import stiffness_at_rest
from ..tissue.factorization import Factor, condition_estimate, factorize
from ..tissue.model import TissueModel, build_tissue_model
from .geometry import needle_zone, orthogonal

# K0's condition number (condition_estimate) above which a discretization is refused as
# nearly singular: its solves then keep fewer than 4 of double precision's 16 digits. 1e4 at
# dilation 2 on SH 1/2, 4e6 at 3, 2e10 at 3.5 and 5e15 at 4 (benchmarks/results/dilation_conditioning.md)
STIFFNESS_CONDITION = 1e12


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
                                      self.model.particles, self.model.support / self.scenario.discretization.dilation,
                                      tissue=self.scenario.tissue)
            self._factor = factor
        return self._factor


def refuse_singular_stiffness(condition: float, discretization, particles: np.ndarray | None = None,
                              local_spacing: np.ndarray | None = None, tissue=None) -> None:
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
    (n,), the line names the pair closest for their spacing, where to look. A material of the
    `tissue` (config.Tissue) nearly incompressible multiplies the number by its
    (lambda + 2 mu) / mu (~9e12 at lame_lambda 1e10 MPa and lame_mu 1 MPa where the discretization
    alone makes ~1e3): where that ratio alone takes it past the bound, the line names the
    material, not the discretization."""
    if not condition > STIFFNESS_CONDITION:
        return
    estimate = f"~{condition:.0e}" if math.isfinite(condition) else "infinite to rounding"
    stiffest = None if tissue is None else _least_compressible(tissue)
    if stiffest is not None and (not math.isfinite(condition) or condition / stiffest[2] <= STIFFNESS_CONDITION):
        field, material, ratio = stiffest
        raise InputError(f"{field}: got lame_lambda {material.lame_lambda:g} MPa with lame_mu {material.lame_mu:g} "
                         f"MPa, (lambda + 2 mu) / mu = {ratio:.2g}, a material so nearly incompressible that the "
                         f"tissue's stiffness is nearly singular (condition number {estimate}, estimated; above "
                         f"{STIFFNESS_CONDITION:.0e} its solves keep fewer than 4 of 16 digits); expected moduli "
                         f"whose ratio keeps it below that: check their units (MPa), or lower lame_lambda")
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


def _least_compressible(tissue) -> tuple[str, object, float] | None:
    """(field, material, (lambda + 2 mu) / mu) of the tissue's material or region material
    with the largest ratio, where that ratio is above 100 (None below: the shipped moduli's
    is 3-11)."""
    materials = [("tissue.material", tissue.material)]
    materials += [(f"tissue.regions[{k}].material", region.material) for k, region in enumerate(tissue.regions)]
    ratio, field, material = max(((m.lame_lambda + 2.0 * m.lame_mu) / m.lame_mu, field, m) for field, m in materials)
    return (field, material, ratio) if ratio > 100.0 else None


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
