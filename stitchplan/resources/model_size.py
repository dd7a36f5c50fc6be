"""A run's size from its scenario alone, before anything is built: particles, neighbours, points, steps."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..config import Scenario
from ..errors import InputError
from ..geometry.polygon_domain import PolygonDomain
from ..needle.geometry import needle_zone, scenario_needle
from .limits import MAX_PARTICLES

# finest lattice (cells) up to which graded particles are counted exactly (~0.4 s at the
# bound; 0.8 s at 444 000 cells on the development machine); beyond it they are estimated
# from the local spacing (_graded_estimate: 10-17 % below the count on the SH scenes)
COUNT_EXACTLY_UP_TO = 250_000
# a shaped tissue's particles are placed and counted up to this estimate (_shaped_size: the
# default limit), estimated beyond it (placing them would itself be a large run)
COUNT_SHAPED_UP_TO = MAX_PARTICLES
CROWDING_SAMPLE = 500  # quadrature points whose neighbours _shaped_size counts
# particles and steps are held at this count: far beyond any machine (a model of 10^15
# particles needs ~10^14 GB by the memory model of costs.py), and small enough that the cost
# formulas stay finite floats
COUNT_CAP = 10**15


@dataclass(frozen=True)
class ModelSize:
    """What the discretization of a scenario will hold, before it is built."""

    particles: int  # at most COUNT_CAP
    exact: bool  # counted (True) or estimated from the local spacing (False)
    neighbours: float  # particles in a kernel support, (2 x dilation)^2 (inf past the float range)
    points_per_particle: float  # quadrature points per particle
    # a shaped tissue's particles per quadrature point, counted: their mean square over the
    # kernel's neighbours^2 (at least 1). Boundary particles crowd the supports (a circular
    # hole's CIRCLE_SEGMENTS, each with the support of the lattice around it), and the tangent's
    # cost and nonzeros grow with the square of a point's particles
    crowding: float = 1.0

    @property
    def effective_neighbours(self) -> float:
        return min(self.neighbours, float(self.particles))


def kernel_neighbours(dilation: float) -> float:
    """Particles in a kernel support on a lattice, (2 x dilation)^2."""
    support = 2.0 * dilation
    return support * support  # a product: inf where ** would raise


def model_size(scenario: Scenario, derived: bool = False) -> ModelSize:
    """Particles, neighbours per kernel support and quadrature points per particle of the
    scenario's discretization, without building its shape functions (a shaped tissue's
    particles and quadrature points are placed and counted: _shaped_size). A `derived` model
    (a replay at another spacing) whose shape its build refuses is estimated instead: that
    replay's failure is an event of the run, not the command's error."""
    d = scenario.discretization
    points = float(d.quadrature_order ** 2 * d.cells_per_spacing ** 2)
    neighbours = kernel_neighbours(d.dilation)
    tissue = scenario.tissue
    if isinstance(tissue.domain, PolygonDomain) or tissue.regions:
        return _shaped_size(scenario, ModelSize(0, False, neighbours, points), derived)
    particles, exact = _particles(scenario)
    return ModelSize(particles, exact, neighbours, points)


def _particles(scenario: Scenario) -> tuple[int, bool]:
    """A rectangle's particles: placed and counted as the model places them (tissue.model's
    rectangle_lattice: graded toward the needle and the load segments' ends, with lines
    through those ends) up to COUNT_EXACTLY_UP_TO cells at the finest lattice step of the
    needle or the spacing, estimated beyond it."""
    from ..tissue.model import load_segments, rectangle_lattice

    d, tissue = scenario.discretization, scenario.tissue
    (width, height), zone = tissue.bounding_size, needle_zone(scenario)
    finest = d.spacing if zone is None else min(d.spacing, d.needle_spacing)
    if per_side(width, finest) * per_side(height, finest) <= COUNT_EXACTLY_UP_TO:
        held, pulled = load_segments(scenario)
        graded = rectangle_lattice(tissue, d, held + pulled, zone)
        if graded is not None:
            return len(graded.particles), True
    if zone is None:  # the uniform grid of tissue.particles.grid_particles
        # load segments add grid lines through their ends and a grading toward them
        # (tissue.particles.end_zones): the grid is then a lower bound (~5-30 % below)
        return capped_count(grid_count(tissue.bounding_size, d.spacing)), not scenario.loads
    return _graded_estimate(tissue.bounding_size, d.spacing, d.needle_spacing, zone, d.needle_grading), False


def _shaped_size(scenario: Scenario, nominal: ModelSize, derived: bool = False) -> ModelSize:
    """A polygon tissue's, or one with holes or regions: its particles and quadrature points
    as the model places them (tissue.model's shaped discretization: the lattice with the
    shape's lines, fitted to the boundary, and the cut-cell quadrature), and how its
    particles crowd the quadrature points (`crowding`: the particles each of CROWDING_SAMPLE
    evenly spread quadrature points sees through the tissue, as the model's visibility
    criterion lets them). Estimated instead (_shaped_estimate) past COUNT_SHAPED_UP_TO
    particles, where placing them would itself be a large run."""
    from ..tissue.model import load_segments, shaped_discretization

    zone = needle_zone(scenario)
    held, pulled = load_segments(scenario)
    segments = held + pulled  # in the model's order
    # the estimate over the whole bounding box bounds the shape's from above: within the
    # limit, the shape's (a point-in-polygon test of its 40 000 grid points) is not needed
    if _shaped_estimate(scenario, zone, segments, whole_box=True) > COUNT_SHAPED_UP_TO:
        estimated = _shaped_estimate(scenario, zone, segments)
        if estimated > COUNT_SHAPED_UP_TO:
            return replace(nominal, particles=estimated)
    try:
        shaped = shaped_discretization(scenario.tissue, scenario.discretization, segments, zone)
    except InputError:  # tissue thinner than the derived model's spacing resolves
        if not derived:
            raise
        return replace(nominal, particles=_shaped_estimate(scenario, zone, segments))
    square = _mean_square_neighbours(scenario.tissue.domain, shaped.points, shaped.particles, shaped.support)
    crowding = square / nominal.neighbours ** 2 if math.isfinite(nominal.neighbours) else 1.0
    return replace(nominal, particles=len(shaped.particles), exact=True,
                   points_per_particle=len(shaped.points) / max(len(shaped.particles), 1), crowding=max(crowding, 1.0))


def _mean_square_neighbours(domain, points: np.ndarray, particles: np.ndarray, support: np.ndarray) -> float:
    """The mean over up to CROWDING_SAMPLE of the quadrature points (every k-th) of the
    squared count of particles whose support holds the point and that see it (the model's
    neighbour search and visibility criterion, tissue.shape_functions)."""
    from ..tissue.shape_functions import Visibility, neighbour_pairs

    sample = points[::max(len(points) // CROWDING_SAMPLE, 1)]
    rows, cols, _ = neighbour_pairs(sample, particles, support)
    visibility = Visibility.of(domain, particles, tested=np.unique(cols))  # the sampled pairs' particles
    if visibility is not None:
        rows = rows[visibility.keep(sample, particles, rows, cols)]
    counts = np.bincount(rows, minlength=len(sample)).astype(float)
    return float(np.mean(counts ** 2)) if len(sample) else 0.0


def _shaped_estimate(scenario: Scenario, zone, segments, samples: int = 200, whole_box: bool = False) -> int:
    """Particles of a shaped tissue without placing them: the lattice as the integral of
    1 / side^2 over the tissue (side: the spacing, graded toward the refinement zones as the
    lattice is: corners, segment ends, material interfaces, round holes, the needle), the boundary's as the
    integral of 1 / side along it, the shape's lattice lines (tissue.shapes.shape_breaks) across the
    bounding box, and a particle at each vertex that keeps one (tissue.shapes.kept_vertices).
    With `whole_box` the lattice's integral runs over the whole bounding box: at least the
    estimate without it."""
    from ..tissue.particles import END_GROWTH, RefinementZone, end_zones
    from ..tissue.shapes import kept_vertices, shape_breaks, shape_zones

    tissue, d = scenario.tissue, scenario.discretization
    domain = tissue.domain
    (width, height), origin = tissue.bounding_size, np.asarray(domain.origin, dtype=float)
    zones = [(z, END_GROWTH) for z in (*end_zones(tissue, segments, d), *shape_zones(tissue, d))]
    if zone is not None:
        zones.append((RefinementZone(np.asarray(zone[0], dtype=float), zone[1], d.needle_spacing), d.needle_grading))
        zones += [(z, d.needle_grading) for z in zone[2]]

    def side(points: np.ndarray) -> np.ndarray:
        result = np.full(len(points), d.spacing)
        for refined, growth in zones:  # a few zones
            distance = np.maximum(refined.distance(points[:, 0], points[:, 1]), 0.0)
            result = np.minimum(result, refined.spacing + growth * distance)
        return result

    t = (np.arange(samples) + 0.5) / samples
    grid = origin + np.stack(np.meshgrid(t * width, t * height, indexing="ij"), axis=-1).reshape(-1, 2)
    inside = grid if whole_box else grid[domain.contains(grid)]
    lines = shape_breaks(tissue, d.spacing)
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):  # a side too small for a float: inf
        lattice = np.sum(width * height / samples**2 / side(inside) ** 2)
        lattice += (len(lines[0]) * height + len(lines[1]) * width) / d.spacing
        if isinstance(domain, PolygonDomain):
            starts, ends = domain.segment_starts, domain.segment_ends
            u = (np.arange(8) + 0.5) / 8  # (8,) points along each edge
            along = starts[:, None] + u[:, None] * (ends - starts)[:, None]  # (E, 8, 2)
            length = np.linalg.norm(ends - starts, axis=1)
            spacing = side(along.reshape(-1, 2)).reshape(len(starts), 8)
            lattice += np.sum(length[:, None] / 8 / spacing) + np.count_nonzero(kept_vertices(tissue))
    return capped_count(float(lattice)) if math.isfinite(lattice) else COUNT_CAP


def per_side(length: float, side: float) -> float:
    """length / side; inf for a side that underflowed to 0 (a spacing over a refinement)."""
    return length / side if side > 0 else math.inf


def grid_count(size: tuple[float, float], spacing: float) -> float:
    """Particles of the uniform grid at `spacing` (tissue.particles.grid_particles), as a
    float: a fine spacing's count passes any integer a float can hold."""
    nx, ny = (max(float(np.rint(per_side(length, spacing))), 1.0) for length in size)
    return (nx + 1.0) * (ny + 1.0)


def capped_count(count: float) -> int:
    return int(min(count, COUNT_CAP))


def _graded_estimate(size, spacing: float, fine: float, zone, growth: float = 0.5, samples: int = 400) -> int:
    """Particles of a graded set (tissue.particles.graded_particles: side `fine` within the zone,
    finer toward the needle's entry and exit zones, growing by `growth` mm per mm beyond them
    up to `spacing`) as the integral of
    1 / side^2 over the slab, on a samples x samples grid."""
    width, height = size
    x = (np.arange(samples) + 0.5) * width / samples
    y = (np.arange(samples) + 0.5) * height / samples
    distance = np.hypot(x[:, None] - zone[0][0], y[None, :] - zone[0][1]) - zone[1]  # (samples, samples)
    side = fine + growth * np.maximum(distance, 0.0)
    for point in zone[2]:  # the needle's entry and exit (needle_end_zones)
        near = np.hypot(x[:, None] - point.center[0], y[None, :] - point.center[1]) - point.radius
        side = np.minimum(side, point.spacing + growth * np.maximum(near, 0.0))
    side = np.clip(side, None, max(spacing, fine))
    with np.errstate(divide="ignore", over="ignore"):  # a side too small for a float: inf, then capped
        return capped_count(float(np.sum(width * height / samples ** 2 / side ** 2)))


def needle_steps(scenario: Scenario) -> int:
    """The needle steps until the tip exits (NeedleGeometry.expected_steps), at most
    COUNT_CAP: a step of a few 1e-324 rad gives more steps than an integer conversion takes."""
    geometry = scenario_needle(scenario)
    if geometry.exit_rotation / geometry.step >= COUNT_CAP:
        return COUNT_CAP
    return geometry.expected_steps
