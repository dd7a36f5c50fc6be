"""Static deformation of the slab under boundary loads: the problem behind `stitchplan deform`."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .assembly import Assembler
from ..config import Scenario
from ..geometry.segments import on_segment
from .model import TissueModel, model_for_scenario
from .quadrature import gauss_legendre
from .solver import NewtonReport, StepRecord, solve_static

log = logging.getLogger(__name__)


@dataclass
class DeformResult:
    scenario: Scenario
    model: TissueModel
    coefficients: np.ndarray  # (NP, 2) RK coefficients d
    particle_displacements: np.ndarray  # (NP, 2) u(X_I), the RK interpolant at the particles
    probes: np.ndarray  # (n_probes, 2) reference points
    probe_displacements: np.ndarray  # (n_probes, 2)
    reactions: np.ndarray  # (n_loads, 2) force the tissue exerts back on each loaded segment, N
    report: NewtonReport
    wall_seconds: float
    timings: dict[str, float]


def external_forces(model: TissueModel, scenario: Scenario) -> np.ndarray:
    """Dead loads on the reference segments, as full particle forces (NP, 2):
    f_I = int_seg N_I(X) h0 dGamma with h0 = total force / segment length (eq. 3.57).

    The integral runs over exactly the segment (its ends are particles), split at the
    particles on it, where the RK functions change their form."""
    forces = np.zeros((model.n_particles, 2))
    for load in scenario.loads:
        if load.force is None:
            continue
        start, end = np.asarray(load.segment[0]), np.asarray(load.segment[1])
        length = float(np.linalg.norm(end - start))
        points, weights = load_quadrature(model, start, end)
        values = model.shape_functions_at(points).values  # (nqs, NP)
        forces += np.outer(values.T @ weights, np.asarray(load.force) / length)
    return forces


def load_quadrature(model: TissueModel, start: np.ndarray, end: np.ndarray,
                    order: int = 4, per_interval: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Gauss rule on the segment start-end with breaks at the particles lying on it: `order`
    points on each of `per_interval` pieces of every interval. Points (n, 2), lengths (n,)."""
    length = float(np.linalg.norm(end - start))
    tol = model.tissue.domain.tolerance
    on = on_segment(model.particles, start, end, tol)
    along = (model.particles[on] - start) @ (end - start) / length**2  # in [0, 1]
    cuts = np.unique(np.clip(np.concatenate([[0.0, 1.0], along]), 0.0, 1.0))
    cuts = cuts[np.concatenate([[True], np.diff(cuts) > tol / length])]
    s, w = gauss_legendre(order)
    sub = (np.arange(per_interval)[:, None] + s[None, :]).ravel() / per_interval  # (m,) in [0, 1]
    sub_w = np.tile(w, per_interval) / per_interval
    left, width = cuts[:-1], np.diff(cuts)
    t = (left[:, None] + width[:, None] * sub[None, :]).ravel()
    weights = (width[:, None] * sub_w[None, :]).ravel() * length
    return start + t[:, None] * (end - start), weights


def prescribed_displacements(model: TissueModel, scenario: Scenario) -> np.ndarray:
    """g (Nb, 2): zero on clamped edges, the segment's displacement on its particles."""
    boundary = model.boundary
    values = np.zeros((len(boundary.indices), 2))
    displacement_loads = [load for load in scenario.loads if load.displacement is not None]
    for k, load in enumerate(displacement_loads):
        values[boundary.group == k] = load.displacement
    return values


def to_free(model: TissueModel, full_forces: np.ndarray) -> np.ndarray:
    """Forces on particle coefficients -> forces on free coefficients, interleaved (2 n_free,)."""
    return (model.boundary.free_map.T @ full_forces).ravel()


def interpolate(model: TissueModel, coefficients: np.ndarray, points: np.ndarray) -> np.ndarray:
    """u(X) = sum_I N_I(X) d_I (eq. 3.18) at reference points (n, 2)."""
    if len(points) == 0:
        return np.zeros((0, 2))
    return model.shape_functions_at(points).values @ coefficients


def reactions(model: TissueModel, scenario: Scenario, coefficients: np.ndarray,
              full_external: np.ndarray) -> np.ndarray:
    """Total force the tissue exerts back on each loaded segment (N), in file order.

    For a prescribed segment it is minus the virtual work of the out-of-balance particle
    forces in a unit translation of that segment's boundary particles (via T_g); for a
    force-loaded segment at equilibrium it is minus the applied force.
    """
    deformation_gradient = model.deformation_gradient(coefficients)
    from .material import first_piola_and_tangent

    first_piola, _ = first_piola_and_tangent(model.material, deformation_gradient)
    weighted = first_piola * model.quadrature_weights[:, None, None]  # (nq, i, J)
    internal = model.shape.grad_x.T @ weighted[:, :, 0] + model.shape.grad_y.T @ weighted[:, :, 1]
    unbalanced = model.boundary.prescribed_map.T @ (internal - full_external)  # (Nb, 2)
    result = np.zeros((len(scenario.loads), 2))
    k = 0
    for i, load in enumerate(scenario.loads):
        if load.force is not None:
            result[i] = -np.asarray(load.force)
        else:
            result[i] = -unbalanced[model.boundary.group == k].sum(axis=0)
            k += 1
    return result


def run_deform(
    scenario: Scenario,
    on_step: Callable[[int, StepRecord], None] | None = None,
    needle_zone: tuple[tuple[float, float], float] | None = None,
) -> DeformResult:
    """Discretize, load and solve; `wall_seconds` covers everything from the loaded scenario.
    `needle_zone` (centre, radius) grades the particles of a scene with a needle as simulate
    does (stitchplan.needle.geometry.needle_zone)."""
    timings: dict[str, float] = {}
    start = time.perf_counter()
    model = model_for_scenario(scenario, needle_zone)
    timings["discretization"] = time.perf_counter() - start
    full_external = external_forces(model, scenario)
    prescribed = prescribed_displacements(model, scenario)
    assembler = Assembler(model)
    log.info("deform: %d particles, %d load steps", model.n_particles, scenario.load_steps)

    def step_done(step: int, record: StepRecord) -> None:
        log.info("load step %d/%d: load fraction %.3f, %d Newton iterations, %d step cuts, residual %.2e N",
                 step, scenario.load_steps, record.load_fraction, record.iterations, record.cuts,
                 record.residual)
        if on_step is not None:
            on_step(step, record)

    solve_start = time.perf_counter()
    solution = solve_static(model, to_free(model, full_external), prescribed, scenario.load_steps,
                            scenario.solver, assembler, step_done)
    timings["solve"] = time.perf_counter() - solve_start
    probes = np.asarray(scenario.probes, dtype=float).reshape(-1, 2)
    probe_displacements = interpolate(model, solution.coefficients, probes)
    particle_displacements = model.particle_shape_values() @ solution.coefficients
    segment_reactions = reactions(model, scenario, solution.coefficients, full_external)
    wall = time.perf_counter() - start
    return DeformResult(scenario, model, solution.coefficients, particle_displacements, probes,
                        probe_displacements, segment_reactions, solution.report, wall, timings)
