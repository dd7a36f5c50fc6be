"""The resource guard: what a run will cost, estimated before anything heavy is built, and
refused past documented limits.

It sits above needle/ (it needs the needle geometry for the step count and the needle zone
of graded particles) and below planning/ and study/ (the auto discretization asks it for
the finest model allowed); the commands call `check_resources` before any run.

A run's size is known from the scenario alone: the particles (counted from the particle
arrangement without building shape functions, or estimated from the spacing where even the
count would be costly), the kernel's neighbours per point (dilation), the quadrature
points, and the steps (load steps of deform, needle steps until the tip exits). From these
the guard estimates

- memory: the sparse shape-function, gradient and tangent matrices and the LU factor grow
  like particles x neighbours; bytes = MEMORY_PER_PARTICLE x particles^MEMORY_EXPONENT x
  (neighbours / 16) x (quadrature points per particle / 4), plus the interpreter's share,
  plus for a needle run what it keeps of its steps until it ends (_step_memory, counted
  from the arrays the code keeps: each step's state with the saddle-point solver's dense
  (2Q)^2 blocks, 2Q ~ 4 x the steps, in doubling buffers the states share), which passes
  the rest from a few hundred steps on (SH 1/2: 1.26 GB measured at 0.0025 rad, 0.10 GB at
  its 0.08 rad);
- time: the tangent assembly B^T W B costs ~ quadrature points x neighbours^2 per Newton
  iteration and the factorization grows a little faster than the particles; seconds =
  SECONDS_PER_PARTICLE_STEP x particles^TIME_EXPONENT x steps x (neighbours / 16)^2 x
  (quadrature points per particle / 4) x runs, x MINRES_TIME_FACTOR for needle runs whose
  steps MINRES solves.

A shaped tissue (an outline, holes, regions) is not a lattice the spacing alone counts: its
particles and quadrature points are placed as the model places them (a traced contour's
boundary particles, a circular hole's CIRCLE_SEGMENTS, the cut cells' extra Gauss points),
and both costs are multiplied by its `crowding`, the mean square of the particles a
quadrature point sees over a regular lattice's (16^2 at dilation 2), counted on a sample of
the points: boundary particles carry the support of the lattice around them, so around a
small hole a point sees several times the usual particles (measured on the audit's scenes
and the shipped shaped ones, deform: memory 0.52-0.89x of the estimate; time 1.0-1.5x, and
up to 2.4x where the solve of a point-like load on a traced outline needs many Newton
iterations).

The constants come from `python benchmarks/resource_costs.py` (benchmarks/results/
resource_costs.md), measured on the 2-core machine the tool is developed on, which is
shared: the memory model is within 0.93-1.23x of every measured case, the time model within
0.78-1.6x of the dilation-2 cases, and the (neighbours/16)^2 time scaling overestimated the
unfitted dilation-3 case (0.33x there; 0.96x in an earlier run of the same benchmark). What
a needle run keeps of its steps is not fitted: the runs at 0.01 and 0.0025 rad on SH 1/2
peak at 0.79 and 0.80x of the estimate (the slab's and the default steps' at 0.55-0.92x),
and their time per step grows with the steps taken (1.6x the estimate at 0.0025 rad). The
memory limit is what protects the machine; the time is a guide, not a promise.

Limits (Limits; the CLI's --max-particles raises the first, --no-resource-check skips
them all; nothing raises the memory share: a smaller model is the way under it):

- MAX_PARTICLES = 50 000: a deform at 1 mm spacing on the 100 x 100 mm slab (10 447
  particles) took 30 s and 0.77 GB; 50 000 particles are estimated at ~3 min and ~5.6 GB
  per 10-step solve, a plan (several insertions and a verification model of 4x the
  particles) at hours;
- MAX_NEEDLE_STEPS = 2 000: the shipped needles take 15-40 steps; 2 000 steps over a half
  circle advance the SH needle's tip by radius x step ~ 0.014 mm each, 1/130 of the default
  particle spacing at the needle (1.78 mm): nothing the model resolves, while the run time
  grows with every step, and the memory it keeps with their square (~4.6 GB estimated at
  2 000 steps, past the memory share on many machines: then refused naming needle.step);
- MAX_NEIGHBOURS = 400 particles in a kernel support (dilation 10): the RK functions stop
  being local well before (RKPM practice: dilation 1.5-3, 9-36 neighbours), and the
  tangent's cost grows with the square of the neighbours;
- MEMORY_SHARE = 0.5 of the memory the machine has available now, for the runs a command
  has going on at once together (check_resources `alongside`: a plan's passes, its
  verification's replays in a helper process and its replay at twice the spacing; a
  simulate and its estimate's replay; plan --uncertainty and the sampled plans of its local
  Dask workers; the largest of a study's runs, as many as its local workers, and the
  study's own process, which runs none of them, with its interpreter), each helper
  process with its own share of the interpreter (HELPER_BASE_MEMORY), each worker with the
  whole of its own.

The guard also refuses a model too coarse to mean anything (`_coarse_refusal`), the other
side of a spacing typed wrong: a spacing above half the tissue's smaller side (fewer than
three particles across it), or a spacing at the needle above the needle's radius (the
needle's curve then falls between a few particles: on the SH 1/2 block, `--spacing 200`
runs on 4 particles to an exit error of 0.0175 mm, with an estimate of 0 from a second run on
the same 4 particles, against 0.4685 mm at half the default spacing).

A refusal names what drives the estimate past the limit (`_particle_setting`,
`_memory_setting`): the spacing, or the needle zone's refinement or spacing when the
coarse spacing alone would fit, or, when the spacing is the default of a file giving none,
the needle radius or the tissue's size that sets it; past the memory share with a standard
kernel fitting, the dilation or the quadrature points, and the needle step when the run
would fit but for what it keeps of its steps. A field set elsewhere than the scenario file's
`discretization:` block
(an option, a study's spacing, a plan's verification model) is named as the caller's
`Origin` says. Counts are estimated in floating point and held at COUNT_CAP, so any finite
positive input ends in a refusal, never in an overflow.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from .config import DEFAULT_NEEDLE_REFINEMENT, Discretization, Scenario
from .config.blocks import default_spacing_of
from .errors import InputError
from .geometry import PolygonDomain
from .needle.geometry import needle_zone, scenario_needle
from .tissue.particles import graded_particles

log = logging.getLogger(__name__)

MAX_PARTICLES = 50_000
MAX_NEEDLE_STEPS = 2_000
MAX_NEIGHBOURS = 400
MEMORY_SHARE = 0.5
# finest lattice (cells) up to which graded particles are counted exactly (~0.4 s at the
# bound; 0.8 s at 444 000 cells on the development machine); beyond it they are estimated
# from the local spacing (_graded_estimate: 10-17 % below the count on the SH scenes)
COUNT_EXACTLY_UP_TO = 250_000
# a shaped tissue's particles are placed and counted up to this estimate (_shaped_size: the
# default limit), estimated beyond it (placing them would itself be a large run)
COUNT_SHAPED_UP_TO = MAX_PARTICLES
CROWDING_SAMPLE = 500  # quadrature points whose neighbours _shaped_size counts
# particles and steps are held at this count: far beyond any machine (a model of 10^15
# particles needs ~10^14 GB by the memory model below), and small enough that the cost
# formulas stay finite floats
COUNT_CAP = 10**15
# runs estimated longer than this are announced by a warning line before they start (the
# time is a guide: benchmarks/results/resource_costs.md)
LONG_RUN_SECONDS = 600.0

# from benchmarks/results/resource_costs.md (python benchmarks/resource_costs.py): the time
# constants a fit of the code as it is (fits vary with the machine's load: the exponent by
# 1.07-1.19 over two runs; the file's "guard now" columns check these against every run); the
# memory constants an earlier fit's (git history), kept because they bound every measured peak
# from above, where the latest fits' sublinear exponent (the fixed cost of a run's first imports
# spread over few particles) falls below the largest one
SECONDS_PER_PARTICLE_STEP = {"deform": 6.5e-5, "insertion": 1.5e-5}  # at 1 000 particles
TIME_EXPONENT = 1.07  # seconds ~ particles^TIME_EXPONENT
# a needle run with `linear_solver: minres` against the direct solve the constants above were
# fitted on: 3.5-4.6x on SH 1/2 from 324 to 979 particles, 7.4x at 2601 (mortar coupling;
# benchmarks/results/simulate_speed.md, "Where MINRES stagnates")
MINRES_TIME_FACTOR = 5.0
MEMORY_PER_PARTICLE = 3.6e4  # bytes per particle at 1 000 particles
MEMORY_EXPONENT = 1.28
BASE_MEMORY = 94e6  # bytes: the interpreter with numpy, scipy and stitchplan loaded
# a helper process's own share of the interpreter: forked as the command starts
# (stitchplan/early_helper.py), it imports its own modules, but the pages of the libraries
# under them (numpy's, scipy's, OpenBLAS) are shared through the page cache (a helper
# replaying at twice the spacing: 58 MB of proportional set size against ~11 MB its run is
# estimated above BASE_MEMORY; 40-44 MB when it was forked after the imports, sharing their
# pages until written; benchmarks/results/memory_at_once.md)
HELPER_BASE_MEMORY = 0.5 * BASE_MEMORY
# What a command maps after the guard beyond its runs' memory, counted against an address-space
# limit (`ulimit -v`): the libraries its run loads (cvxopt's and SciPy's OpenBLAS, LAPACK, SuperLU),
# their buffers and the allocator's reservations. VmPeak - VmSize at the guard: 310 MB for
# `deform configs/slab_edge_load.yaml` (a run estimated 13 MB above BASE_MEMORY), 158-231 MB for
# simulate and plan on the shipped needle scenes. The address space a run maps grows ~2.3x as fast
# as its memory (1824 MB for deform at spacing 1 mm, estimated 798 MB), which the memory share's
# half covers. Past the limit an allocation fails: SuperLU then spun without end (SIGTERM unheard),
# CHOLMOD crashed.
ADDRESS_SPACE_RESERVE = 320e6
REFERENCE_PARTICLES = 1000.0
REFERENCE_NEIGHBOURS = 16.0  # (2 x dilation)^2 at dilation 2
REFERENCE_POINTS_PER_PARTICLE = 4.0  # 2 x 2 Gauss points per cell, one cell per particle
# what a needle run keeps of its steps until it ends (_step_memory, from the arrays the code
# keeps; checked against measured peaks in benchmarks/results/resource_costs.md)
FLOAT_BYTES = 8.0
# a step's state holds its own copy of the track's arrays (NeedleCoupling.add makes new ones
# each step): per needle point the points (16 bytes), the segments' two Gauss points and the
# load points (32 each), the load magnitudes (16), segment fraction and spacing (8 each), gap (1)
TRACK_BYTES_PER_POINT = 113.0
# each further piece of a segment (track_layout.segment_subintervals) adds two Gauss points,
# two load points and their magnitudes (32 + 32 + 16 bytes) and, with segment ends, two target radii (16)
TRACK_BYTES_PER_PIECE = 96.0
# with `multiplier_ends: arc` also per constraint quadrature point its point (16), segment,
# position, length and target radius (8 each): NeedleCoupling._new_constraint_points
ARC_BYTES_PER_QUADRATURE_POINT = 48.0
# per particle of each step: the state's free coefficients (16, Snapshot.free) and the tip's
# dense shape-function row (8, NeedleCoupling.tip_row), and the particle displacements (16),
# held twice at the end (run_insertion's list and InsertionResult's array)
STEP_BYTES_PER_PARTICLE = 56.0
# a run may take a few more steps than the undeformed circle's (a planned run on SH 1/2:
# 628 for 611 at 0.005 rad): the solver's buffers are counted for this many times the steps,
# so that a run just past a doubling is not estimated at a quarter of its largest buffer
STEP_MARGIN = 1.1

# what lifts each limit: --max-particles raises the particle limit only; nothing but
# skipping the guard passes the memory share
OVERRIDE = "raise --max-particles or pass --no-resource-check to run it anyway"
SKIP_GUARD = "pass --no-resource-check to run it anyway"
# runs of a plan on its model (planner passes; benchmarks/results/plan_speed.md: a planned run
# takes ~2.5 unplanned ones) and replays on the verification model (half the spacing)
PLAN_RUNS = 3
VERIFICATION_RUNS = 2
# runs whose steps' states one process holds at once (_step_memory each), of the `runs` an
# estimate counts: a plan holds its unplanned comparison (--compare), its first pass (later
# passes take its early steps over: planning.planner.PassPrefix), its best pass so far and the
# pass running, 1-4 runs (measured on SH 1/2 at 0.005 rad: 456 MiB for one run, 666 MiB for a
# plan of two passes, 1027 MiB with the comparison, 866 MiB for the 100 x 30 block's two passes;
# tests/test_resource_guard.py MEASURED_PEAKS); a verification its first replay while the second
# runs (run_insertion `start_from`). Two: within 2x of one and of four
HELD_RUNS = 2


@dataclass(frozen=True)
class Limits:
    max_particles: int = MAX_PARTICLES
    max_needle_steps: int = MAX_NEEDLE_STEPS
    max_neighbours: int = MAX_NEIGHBOURS
    memory_share: float = MEMORY_SHARE


@dataclass(frozen=True)
class Origin:
    """What set a run's discretization, so that a refusal names what the user can change.

    A discretization field is named as the scenario file's `discretization.<field>` unless
    `names` maps it to what else set it: an option ({"spacing": "--spacing"}) or another
    block ({"spacing": "study.spacing"}); `given` holds the value as set there where the
    run's differs. A run derived from the given model (a plan's verification) says so in
    `derived` and how to leave it out in `skip`."""

    names: Mapping[str, str] = field(default_factory=dict)
    given: Mapping[str, float] = field(default_factory=dict)
    derived: str = ""  # follows what was expected, e.g. " in the plan's verification at half the spacing"
    skip: str = ""  # advice, e.g. "pass --no-verify to skip the verification"

    def name(self, key: str) -> str:
        return self.names.get(key, f"discretization.{key}")

    def value(self, key: str, run_value: float) -> float:
        return self.given.get(key, run_value)


def replay_origin(scenario: Scenario, names: Mapping[str, str] | None, derived: str, skip: str) -> Origin:
    """The origin of a model rescaled from the scenario's (a replay at another spacing): a
    refusal names the scenario's own spacings (`names` as for the scenario's model), says
    which replay in `derived` and how to leave it out in `skip`."""
    d = scenario.discretization
    given = {"spacing": d.spacing}
    if d.needle_spacing is not None:
        given["needle_spacing"] = d.needle_spacing
    return Origin(dict(names or {}), given, derived=derived, skip=skip)


def verification_origin(scenario: Scenario, names: Mapping[str, str] | None = None) -> Origin:
    """The origin of a plan's verification model (planning.replay_models.replay_scenario):
    replay_origin offering --no-verify."""
    return replay_origin(scenario, names, " in the plan's verification at half the spacing",
                         "pass --no-verify to skip the verification")


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


@dataclass(frozen=True)
class Estimate:
    """The estimated cost of one command's runs, with what a refusal needs to name its cause."""

    label: str  # e.g. "deform", "simulate", "plan verification"
    size: ModelSize
    steps: int  # load steps or needle steps of one run, at most COUNT_CAP
    step_kind: str  # "load steps" or "needle steps"
    runs: float  # runs of that size (plan: planned passes and the comparison)
    memory_bytes: float
    seconds: float
    spacing: float  # the discretization's spacing, mm
    needle_step: float | None  # rad per needle step (insertions)
    discretization: Discretization
    origin: Origin
    # particles of a uniform grid at the spacing when the model is graded toward the needle
    # (what the spacing alone costs), None when the model is that grid
    coarse_particles: float | None
    radius_default: float | None  # the needle radius, when the spacing is the default following it
    tissue_size: tuple[float, float] | None = None  # the tissue's bounding box, mm
    needle_radius: float | None = None  # mm (insertions)
    step_memory: float = 0.0  # bytes of memory_bytes that needle runs keep of their steps (_step_memory)
    # the tissue's field ("tissue.size" or "tissue.outline") when the spacing is the default its
    # size sets (a scenario giving no spacing, and no needle radius setting it: _size_default)
    size_default: str | None = None

    def describe(self) -> str:
        about = "" if self.size.exact else "about "
        runs = f" in each of {self.runs:g} runs" if self.runs != 1 else ""
        # costs of a count held at COUNT_CAP are lower bounds
        memory = "over " if self.size.particles >= COUNT_CAP else "~"
        time = "over " if self.size.particles >= COUNT_CAP or self.steps >= COUNT_CAP else "~"
        return (f"{self.label}: {_count(self.size.particles, about)} particles, {_count(self.steps)} "
                f"{self.step_kind}{runs}, {memory}{_bytes(self.memory_bytes)} memory, {time}{_duration(self.seconds)}")


# --- sizes -------------------------------------------------------------------------------


def model_size(scenario: Scenario) -> ModelSize:
    """Particles, neighbours per kernel support and quadrature points per particle of the
    scenario's discretization, without building its shape functions (a shaped tissue's
    particles and quadrature points are placed and counted: _shaped_size)."""
    d = scenario.discretization
    points = float(d.quadrature_order ** 2 * d.cells_per_spacing ** 2)
    support = 2.0 * d.dilation
    neighbours = support * support  # a product: inf where ** would raise
    tissue = scenario.tissue
    if isinstance(tissue.domain, PolygonDomain) or tissue.regions:
        return _shaped_size(scenario, ModelSize(0, False, neighbours, points))
    particles, exact = _particles(scenario)
    return ModelSize(particles, exact, neighbours, points)


def _particles(scenario: Scenario) -> tuple[int, bool]:
    d, (width, height) = scenario.discretization, scenario.tissue.bounding_size
    zone = needle_zone(scenario)
    if zone is None:  # the uniform grid of tissue.particles.grid_particles
        # load segments add grid lines through their ends and a grading toward them
        # (tissue.particles.end_zones): the grid is then a lower bound (~5-30 % below)
        return _capped(_grid_count(scenario.tissue.bounding_size, d.spacing)), not scenario.loads
    lattice = _per_side(width, d.needle_spacing) * _per_side(height, d.needle_spacing)
    if lattice <= COUNT_EXACTLY_UP_TO:
        graded = graded_particles(scenario.tissue.bounding_size, d.spacing, d.needle_spacing,
                                  np.asarray(zone[0], dtype=float), zone[1], d.needle_grading, points=zone[2])
        return len(graded.particles), True
    return _graded_estimate(scenario.tissue.bounding_size, d.spacing, d.needle_spacing, zone,
                            d.needle_grading), False


def _shaped_size(scenario: Scenario, nominal: ModelSize) -> ModelSize:
    """A polygon tissue's, or one with holes or regions: its particles and quadrature points
    as the model places them (tissue.model's shaped discretization: the lattice with the
    shape's lines, fitted to the boundary, and the cut-cell quadrature), and how its
    particles crowd the quadrature points (`crowding`: the particles each of CROWDING_SAMPLE
    evenly spread quadrature points sees through the tissue, as the model's visibility
    criterion lets them). Estimated instead (_shaped_estimate) past COUNT_SHAPED_UP_TO
    particles, where placing them would itself be a large run."""
    from .tissue.model import load_segments, shaped_discretization

    zone = needle_zone(scenario)
    held, pulled = load_segments(scenario)
    segments = held + pulled  # in the model's order
    estimated = _shaped_estimate(scenario, zone, segments)
    if estimated > COUNT_SHAPED_UP_TO:
        return replace(nominal, particles=estimated)
    shaped = shaped_discretization(scenario.tissue, scenario.discretization, segments, zone)
    square = _mean_square_neighbours(scenario.tissue.domain, shaped.points, shaped.particles, shaped.support)
    crowding = square / nominal.neighbours ** 2 if math.isfinite(nominal.neighbours) else 1.0
    return replace(nominal, particles=len(shaped.particles), exact=True,
                   points_per_particle=len(shaped.points) / max(len(shaped.particles), 1), crowding=max(crowding, 1.0))


def _mean_square_neighbours(domain, points: np.ndarray, particles: np.ndarray, support: np.ndarray) -> float:
    """The mean over up to CROWDING_SAMPLE of the quadrature points (every k-th) of the
    squared count of particles whose support holds the point and that see it (the model's
    neighbour search and visibility criterion, tissue.shape_functions)."""
    from .tissue.shape_functions import Visibility, neighbour_pairs

    sample = points[::max(len(points) // CROWDING_SAMPLE, 1)]
    rows, cols, _ = neighbour_pairs(sample, particles, support)
    if isinstance(domain, PolygonDomain) and not domain.convex:
        clearance = np.zeros(len(particles))  # only the sampled pairs' particles: 0 tests a pair
        seen = np.unique(cols)
        clearance[seen] = domain.distance(particles[seen])
        rows = rows[Visibility(domain, clearance).keep(sample, particles, rows, cols)]
    counts = np.bincount(rows, minlength=len(sample)).astype(float)
    return float(np.mean(counts ** 2)) if len(sample) else 0.0


def _shaped_estimate(scenario: Scenario, zone, segments, samples: int = 200) -> int:
    """Particles of a shaped tissue without placing them: the lattice as the integral of
    1 / side^2 over the tissue (side: the spacing, graded toward the refinement zones as the
    lattice is: corners, segment ends, the needle), the boundary's as the integral of
    1 / side along it, the shape's lattice lines (tissue.shapes.shape_breaks) across the
    bounding box, and a particle at each vertex that keeps one (tissue.shapes.kept_vertices)."""
    from .tissue.particles import END_GROWTH, end_zones
    from .tissue.shapes import corner_zones, kept_vertices, shape_breaks

    tissue, d = scenario.tissue, scenario.discretization
    domain = tissue.domain
    (width, height), origin = tissue.bounding_size, np.asarray(domain.origin, dtype=float)
    zones = [(z.center, z.radius, z.spacing, END_GROWTH)
             for z in (*end_zones(tissue, segments, d), *corner_zones(tissue, d))]
    if zone is not None:
        zones.append((np.asarray(zone[0], dtype=float), zone[1], d.needle_spacing, d.needle_grading))
        zones += [(z.center, z.radius, z.spacing, d.needle_grading) for z in zone[2]]

    def side(points: np.ndarray) -> np.ndarray:
        result = np.full(len(points), d.spacing)
        for center, radius, spacing, growth in zones:  # a few zones
            distance = np.maximum(np.hypot(*(points - center).T) - radius, 0.0)
            result = np.minimum(result, spacing + growth * distance)
        return result

    t = (np.arange(samples) + 0.5) / samples
    grid = origin + np.stack(np.meshgrid(t * width, t * height, indexing="ij"), axis=-1).reshape(-1, 2)
    inside = grid[domain.contains(grid)]
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
    return _capped(float(lattice)) if math.isfinite(lattice) else COUNT_CAP


def _per_side(length: float, side: float) -> float:
    """length / side; inf for a side that underflowed to 0 (a spacing over a refinement)."""
    return length / side if side > 0 else math.inf


def _grid_count(size: tuple[float, float], spacing: float) -> float:
    """Particles of the uniform grid at `spacing` (tissue.particles.grid_particles), as a
    float: a fine spacing's count passes any integer a float can hold."""
    nx, ny = (max(float(np.rint(_per_side(length, spacing))), 1.0) for length in size)
    return (nx + 1.0) * (ny + 1.0)


def _capped(count: float) -> int:
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
        return _capped(float(np.sum(width * height / samples ** 2 / side ** 2)))


def _needle_steps(scenario: Scenario) -> int:
    """The needle steps until the tip exits (NeedleGeometry.expected_steps), at most
    COUNT_CAP: a step of a few 1e-324 rad gives more steps than an integer conversion takes."""
    geometry = scenario_needle(scenario)
    if geometry.exit_rotation / geometry.step >= COUNT_CAP:
        return COUNT_CAP
    return geometry.expected_steps


def _radius_default(scenario: Scenario, origin: Origin) -> float | None:
    """The needle radius when the run's spacing is the default that follows it (a scenario
    giving no spacing: config.blocks.default_spacing_of), else None."""
    if scenario.needle is None or "spacing" in origin.names:
        return None
    size, radius = scenario.tissue.bounding_size, scenario.needle.radius
    default = default_spacing_of(size, radius)
    follows_radius = default < default_spacing_of(size, math.inf)  # not held by the tissue's size
    spacing = origin.value("spacing", scenario.discretization.spacing)
    return radius if follows_radius and math.isclose(spacing, default, rel_tol=1e-9) else None


def _size_default(scenario: Scenario, origin: Origin) -> str | None:
    """The tissue's field setting the run's spacing ("tissue.size", or "tissue.outline" for a
    polygon) when the spacing is the default of a scenario giving none that the tissue's size
    sets (config.blocks.default_spacing_of: a twentieth of the smaller side without a needle,
    a share of a side where that is below 2/5 of the needle's radius), else None."""
    if "spacing" in origin.names:
        return None
    radius = None if scenario.needle is None else scenario.needle.radius
    default = default_spacing_of(scenario.tissue.bounding_size, radius)
    if not math.isclose(origin.value("spacing", scenario.discretization.spacing), default, rel_tol=1e-9):
        return None
    return "tissue.outline" if scenario.tissue.size is None else "tissue.size"


# --- costs -------------------------------------------------------------------------------


def _scale(size: ModelSize) -> tuple[float, float]:
    """(memory, time) factors of a model relative to one reference particle; a crowded shaped
    tissue's by its `crowding` (the tangent's nonzeros and its assembly both)."""
    particles = max(size.particles, 1)
    neighbours = size.effective_neighbours / REFERENCE_NEIGHBOURS
    points = size.points_per_particle / REFERENCE_POINTS_PER_PARTICLE
    relative = particles / REFERENCE_PARTICLES
    memory = (MEMORY_PER_PARTICLE * REFERENCE_PARTICLES * relative ** MEMORY_EXPONENT * neighbours * points
              * size.crowding)
    time = REFERENCE_PARTICLES * relative ** TIME_EXPONENT * neighbours ** 2 * points * size.crowding
    return memory, time


def _step_memory(scenario: Scenario, particles: float, steps: float) -> float:
    """Bytes a needle run of `steps` steps keeps of them until it ends: run_insertion keeps
    every step's state (its Snapshot with the needle coupling's and the saddle-point
    solver's) and particle displacements. With Q_k constraint quadrature points and m_k
    multipliers after step k (2k and ~k x step length / element length + 2 with the mortar
    coupling, k + 1 and k + 1 with the point coupling), and P particles (bounding the free ones):

    - the saddle-point solver's E K^-1 E^T (2Q, 2Q) and K^-1 E^T (2 n_free, 2Q)
      (SaddlePointSolver._grow) live in buffers whose capacity doubles from the first step's
      2Q_1 to at least 2Q_N; every state holds a view of the buffer then in use, so every buffer
      of the doubling stays (sum of capacities^2: ~4/3 of the last one's). Counted at their
      capacity, which the last one's resident rows approach (numpy asks for transparent huge
      pages for large arrays: 2Q_N rows written are resident whole), and which covers what the
      allocator keeps of the steps' freed temporaries (SH 1/2 at 0.005 and 0.0025 rad, when
      each state still held a copy of the load rows: peaks ~180 and ~430 MB above the
      resident bytes of the arrays kept, ~100 MB of them the interpreter's and the model's;
      the peaks are now 0.8x the estimate there, benchmarks/results/resource_costs.md);
    - the coupling's dense W and P (Q_k, m_k), new in each step's state (NeedleCoupling._partition;
      the point coupling's identity is both, (k + 1)^2): sum over the steps ~ N^3;
    - the track's arrays, new in each state (TRACK_BYTES_PER_POINT): ~ N^2;
    - STEP_BYTES_PER_PARTICLE per particle and step.

    A renewed factor starts new buffers (SaddlePointSolver._use), which the states then keep
    as well: the measured runs renewed none (the factor of K0 solves their needle steps).
    Sums in floating point, finite for counts up to COUNT_CAP."""
    from .needle.track_layout import ARC_ENDS, MULTIPLIER_SPACINGS, POINTS, QUADRATURE_PER_ELEMENT, segment_subintervals

    needle, d = scenario.needle, scenario.discretization
    n = float(steps)
    sum_k, sum_k2 = n * (n + 1.0) / 2.0, n * (n + 1.0) * (2.0 * n + 1.0) / 6.0
    arc_ends = needle.coupling != POINTS and needle.multiplier_ends == ARC_ENDS
    # Q_k = per_segment k + first, m_k = slope k + offset; `arrays`: W and P, or one for both
    pieces = 1.0
    if needle.coupling == POINTS:
        per_segment, first, slope, offset, arrays = 1.0, 1.0, 1.0, 1.0, 1.0
    else:
        at_needle = d.spacing if d.needle_spacing is None else d.needle_spacing
        element = max(MULTIPLIER_SPACINGS * at_needle, needle.multiplier_length or 0.0)
        step_length = scenario_needle(scenario).insertion_step
        ratio = min(_per_side(step_length, element), float(COUNT_CAP))
        pieces = float(segment_subintervals(step_length, at_needle)) if at_needle > 0 else float(COUNT_CAP)
        # arc ends: at least 2 Gauss points per segment, QUADRATURE_PER_ELEMENT per element length;
        # segment ends: the segments' Gauss points, 2 per piece; whole segments of at least an
        # element's length (at most one per segment)
        per_segment = max(2.0, float(math.ceil(QUADRATURE_PER_ELEMENT * ratio))) if arc_ends else 2.0 * pieces
        first, slope, offset, arrays = 0.0, ratio if arc_ends else min(ratio, 1.0), 2.0, 2.0
    weights = arrays * FLOAT_BYTES * (per_segment * slope * sum_k2 + (per_segment * offset + first * slope) * sum_k
                                      + first * offset * n)
    # the doubling buffers' capacities c_0 2^j, j = 0..J, c_0 = 2 Q_1, c_0 2^J >= 2 Q_N
    start, end = 2.0 * (per_segment + first), 2.0 * (per_segment * STEP_MARGIN * n + first)
    doublings = max(math.ceil(math.log2(end / start) - 1e-9), 0)
    capacities = start * (2.0 ** (doublings + 1) - 1.0)  # sum of c_j
    squares = start * start * (4.0 ** (doublings + 1) - 1.0) / 3.0  # sum of c_j^2
    blocks = FLOAT_BYTES * (squares + 2.0 * particles * capacities)
    track = (TRACK_BYTES_PER_POINT + TRACK_BYTES_PER_PIECE * (pieces - 1.0)
             + (ARC_BYTES_PER_QUADRATURE_POINT * per_segment if arc_ends else 0.0)) * sum_k
    return blocks + weights + track + STEP_BYTES_PER_PARTICLE * particles * n


def estimate(scenario: Scenario, kind: str, label: str | None = None, runs: float = 1.0,
             origin: Origin | None = None, linear_solver: str | None = None) -> Estimate:
    """The cost of `runs` runs of `kind` ("deform" or "insertion") on the scenario; `origin`:
    what set its discretization, when not (all of) the scenario file's `discretization:`;
    `linear_solver`: the needle steps' where an option overrides the scenario's."""
    size = model_size(scenario)
    if kind == "deform":
        steps, step_kind = scenario.load_steps, "load steps"
    else:
        steps, step_kind = _needle_steps(scenario), "needle steps"
    memory, time = _scale(size)
    kept = 0.0 if kind == "deform" else min(runs, HELD_RUNS) * _step_memory(scenario, size.particles, steps)
    seconds = SECONDS_PER_PARTICLE_STEP[kind] * time * steps * runs
    if kind != "deform" and (linear_solver or scenario.needle.linear_solver) == "minres":
        seconds *= MINRES_TIME_FACTOR
    d, origin = scenario.discretization, origin or Origin()
    graded = needle_zone(scenario) is not None
    radius_default = _radius_default(scenario, origin)
    return Estimate(label or kind, size, steps, step_kind, runs, BASE_MEMORY + memory + kept, seconds,
                    d.spacing, None if kind == "deform" else scenario.needle.step, d, origin,
                    _grid_count(scenario.tissue.bounding_size, d.spacing) if graded else None,
                    radius_default, tuple(scenario.tissue.bounding_size),
                    None if kind == "deform" else scenario.needle.radius, kept,
                    None if radius_default is not None else _size_default(scenario, origin))


def available_memory() -> float | None:
    """Bytes of memory available now (MemAvailable of /proc/meminfo, else the physical
    memory), and no more than the process's address-space limit leaves (`ulimit -v`) after
    ADDRESS_SPACE_RESERVE; None when unknown."""
    memory = _system_memory()
    room = _address_space_left()
    if room is None:
        return memory
    return room if memory is None else min(memory, room)


def _system_memory() -> float | None:
    try:
        with open("/proc/meminfo") as handle:
            for line in handle:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024.0
    except OSError:
        pass
    try:
        return float(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def _address_space_left() -> float | None:
    """Bytes the address-space limit (RLIMIT_AS) leaves above what the process maps now
    (VmSize) and ADDRESS_SPACE_RESERVE, None without a limit."""
    try:
        import resource

        limit, _ = resource.getrlimit(resource.RLIMIT_AS)
        if limit == resource.RLIM_INFINITY:
            return None
        with open("/proc/self/status") as handle:
            mapped = next((float(line.split()[1]) * 1024.0 for line in handle if line.startswith("VmSize:")), 0.0)
    except (ImportError, OSError, ValueError):
        return None
    return max(float(limit) - mapped - ADDRESS_SPACE_RESERVE, 0.0)


# --- the guard ---------------------------------------------------------------------------


def check_resources(estimates: list[Estimate], limits: Limits = Limits(),
                    memory: float | None = None, alongside: list[Estimate] | None = None,
                    forked: bool = True, workers: int | None = None) -> None:
    """Refuse (InputError, one line per limit passed) runs beyond the limits; log the
    estimates otherwise. `memory`: bytes available (default: available_memory()).

    `alongside`: runs that go on at the same time as `estimates`, in other processes but for
    the predicted aim's (a command's replays at twice the spacing: the exit error estimate's
    in a helper process, the predicted aim's in this one, counted as a helper's; the sampled
    plans on local Dask workers), counted only in the memory all of them hold at once.
    Given (even empty), the runs of `estimates` are taken to
    go on at once too, and their memory together must stay within the share
    (_together_refusal): each within it alone still leaves the machine short when two or
    three hold as much (a plan at a small needle step: its own passes, its verification's
    replays and the predicted aim's each keep their steps' states). `forked`: the processes
    of `alongside` are this command's helpers (HELPER_BASE_MEMORY of an interpreter each: the
    libraries' pages shared), not Dask workers (a whole interpreter each). `workers`: the runs of `estimates` go on in
    this many worker processes, one each at a time and none in this process (a study's on a
    local cluster): the largest `workers` of them are counted together, beside this process's
    interpreter (BASE_MEMORY)."""
    memory = available_memory() if memory is None else memory
    lines = []
    for item in estimates:
        size, what = item.size, f"estimated {item.describe()}"
        too_many_steps = item.needle_step is not None and item.steps > limits.max_needle_steps
        if size.neighbours > limits.max_neighbours:
            most = math.sqrt(limits.max_neighbours) / 2.0
            lines.append(f"{item.origin.name('dilation')}: got {item.discretization.dilation:g}, expected at "
                         f"most {most:g} (a kernel support of {_amount(size.neighbours)} particles per point, "
                         f"at most {limits.max_neighbours}; RKPM uses 1.5-3)")
        elif size.particles > limits.max_particles:
            lines.append(_particles_refusal(item, limits.max_particles))
        elif memory is not None and item.memory_bytes > limits.memory_share * memory:
            setting = _memory_setting(item, limits.memory_share * memory)
            if not (setting.name == "needle.step" and too_many_steps):  # the step limit's line below names it
                lines.append(_memory_refusal(item, setting, limits.memory_share, memory))
        coarse = _coarse_refusal(item)
        if coarse is not None:
            lines.append(coarse)
        if too_many_steps:
            lines.append(f"needle.step: got {item.needle_step:g} rad, expected a step giving at most "
                         f"{limits.max_needle_steps} needle steps ({what}); take a larger step, or pass "
                         "--no-resource-check")
    together = estimates if workers is None else sorted(estimates, key=lambda item: -item.memory_bytes)[:workers]
    held = [*together, *(alongside or [])]
    here = 0.0 if workers is None else BASE_MEMORY
    if not lines and alongside is not None and memory is not None and (len(held) > 1 or workers is not None) \
            and here + held_at_once([item.memory_bytes for item in held], forked) > limits.memory_share * memory:
        lines.append(_together_refusal(held, limits.memory_share, memory, forked, here))
    if lines:
        error = InputError("\n".join(lines))
        error.lines = lines
        raise error
    for item in estimates:
        log.info("resources: %s", item.describe())
        if item.seconds > LONG_RUN_SECONDS:  # a run this long should not start in silence
            log.warning("a long run: estimated %s; -v shows its progress", item.describe())
    for item in alongside or []:  # they take no longer than the runs they go with: no warning of their own
        log.info("resources: %s", item.describe())


@dataclass(frozen=True)
class Setting:
    """What a refusal names: the field or option, the value it got, what it should give
    (completed by "at most N particles"), how to lower the cost by it, and how it reaches
    the model (ends in "; " when given)."""

    name: str
    got: str
    expected: str
    advice: str
    note: str = ""


def _particles_refusal(item: Estimate, limit: int) -> str:
    setting = _particle_setting(item, lambda particles: particles <= limit)
    return (f"{setting.name}: got {setting.got}, expected {setting.expected} at most {limit} particles"
            f"{item.origin.derived} ({setting.note}estimated {item.describe()}); {setting.advice}, "
            f"{_skip(item)}or {OVERRIDE}")


def _memory_refusal(item: Estimate, setting: Setting, share: float, memory: float) -> str:
    return (f"{setting.name}: got {setting.got}, expected a model within {share:.0%} of the {_bytes(memory)} of "
            f"memory available{_limited()}{item.origin.derived} ({setting.note}estimated {item.describe()}); "
            f"{setting.advice}, {_skip(item)}or {SKIP_GUARD}")


def _limited() -> str:
    """Where the address-space limit sets the memory available, a note saying so (the field a
    refusal names is what lowers the cost; the limit is what makes it too high)."""
    room, system = _address_space_left(), _system_memory()
    if room is None or (system is not None and room > system):
        return ""
    return f" under the address-space limit (ulimit -v; {_bytes(ADDRESS_SPACE_RESERVE)} of it kept for libraries)"


def held_at_once(memory_bytes: list[float], forked: bool = True) -> float:
    """Bytes of runs going on at once, each in its own process, from their estimates'
    `memory_bytes`: the interpreter's BASE_MEMORY in them counted once for the command and,
    when the others are `forked` helpers (the libraries' pages shared with the command),
    HELPER_BASE_MEMORY for each of them; a Dask worker has the whole of its own."""
    if not forked:
        return sum(memory_bytes)
    helpers = len(memory_bytes) - 1
    return BASE_MEMORY + sum(amount - BASE_MEMORY for amount in memory_bytes) + helpers * HELPER_BASE_MEMORY


def _together_refusal(held: list[Estimate], share: float, memory: float, forked: bool = True,
                      here: float = 0.0) -> str:
    """The line refusing runs that each fit the memory share but not all at once: it names
    what drives the largest (what it could take, with the others' models left out of the
    share) and lists every run's estimate, and `here`, the bytes this process holds beside
    them when it runs none of them. The others follow the same fields (a spacing, a needle
    step), so what lowers the largest lowers them too."""
    largest = max(held, key=lambda item: item.memory_bytes)
    total = here + held_at_once([item.memory_bytes for item in held], forked)
    # what the largest may take with the others' models beside it: a larger needle step
    # lowers what every run keeps of its steps, so theirs count without it
    others_kept = sum(item.step_memory for item in held) - largest.step_memory
    setting = _memory_setting(largest, share * memory - (total - largest.memory_bytes - others_kept))
    skips = list(dict.fromkeys(item.origin.skip for item in held if item.origin.skip))
    skip = "".join(f"{advice}, " for advice in skips)
    runs = "; ".join([item.describe() for item in held] + ([f"this process: {_bytes(here)}"] if here else []))
    return (f"{setting.name}: got {setting.got}, expected runs within {share:.0%} of the {_bytes(memory)} of memory "
            f"available{_limited()} when they run at once ({setting.note}estimated ~{_bytes(total)} together: {runs}); "
            f"{setting.advice}, {skip}or {SKIP_GUARD}")


def _coarse_refusal(item: Estimate) -> str | None:
    """The line refusing a model too coarse for its tissue or needle (module docstring), or
    None. A needle spacing that follows the spacing (needle_refinement, or no grading) is
    named as the spacing."""
    d, origin = item.discretization, item.origin
    spacing = origin.value("spacing", d.spacing)
    width, height = item.tissue_size
    if d.spacing > min(width, height) / 2.0:
        # the spacing as set (a study's at the needle) may differ from the model's coarse one
        coarse = "" if math.isclose(spacing, d.spacing) else f" (a coarse spacing of {d.spacing:.3g} mm)"
        return (f"{origin.name('spacing')}: got {spacing:g} mm{coarse}, expected at most half the tissue's smaller side "
                f"({width:g} x {height:g} mm), so that at least three particles span it{item.origin.derived}; "
                f"refine it, {_skip(item)}or {SKIP_GUARD}")
    at_needle = d.spacing if d.needle_spacing is None else d.needle_spacing
    if item.needle_radius is None or at_needle <= item.needle_radius:
        return None
    if d.needle_spacing is not None and d.needle_refinement is None:
        name, got = origin.name("needle_spacing"), f"{origin.value('needle_spacing', d.needle_spacing):g} mm"
    else:
        name, got = origin.name("spacing"), f"{spacing:g} mm"
        if d.needle_spacing is not None:
            got += f" (a needle spacing of {at_needle:.3g} mm)"
    return (f"{name}: got {got}, expected a spacing at the needle of at most its radius, {item.needle_radius:g} mm, "
            f"so that the particles follow the needle's curve{item.origin.derived}; refine it, {_skip(item)}or "
            f"{SKIP_GUARD}")


def _skip(item: Estimate) -> str:
    return f"{item.origin.skip}, " if item.origin.skip else ""


def _particle_setting(item: Estimate, fits: Callable[[float], bool]) -> Setting:
    """What makes the particles too many for `fits`: the spacing, unless a uniform grid at
    the spacing would fit and the needle zone is refined past the default; then the needle
    zone's refinement or its own spacing."""
    d, origin = item.discretization, item.origin
    if item.coarse_particles is None or not fits(item.coarse_particles):
        return _spacing_setting(item)
    derived = d.needle_refinement is not None and math.isclose(d.needle_spacing, d.spacing / d.needle_refinement)
    if derived and d.needle_refinement <= DEFAULT_NEEDLE_REFINEMENT:
        return _spacing_setting(item)  # the default grading follows the spacing: coarsening it coarsens both
    if derived:
        spacing = origin.value("spacing", d.spacing)
        return Setting(origin.name("needle_refinement"), f"{d.needle_refinement:g}", "a refinement giving",
                       "lower it", f"a needle spacing of {spacing:g} mm / {d.needle_refinement:g} = "
                       f"{spacing / d.needle_refinement:.3g} mm; ")
    return Setting(origin.name("needle_spacing"), f"{origin.value('needle_spacing', d.needle_spacing):g} mm",
                   "a needle spacing giving", "coarsen it")


def _spacing_setting(item: Estimate) -> Setting:
    d, origin = item.discretization, item.origin
    spacing = origin.value("spacing", d.spacing)
    if item.radius_default is not None:  # the file gives no spacing: the radius sets it
        width, height = item.tissue_size
        return Setting("needle.radius", f"{item.radius_default:g} mm",
                       f"a radius whose default particle spacing (here {spacing:.3g} mm) gives",
                       f"check that it and the tissue's size ({width:g} x {height:g} mm) are in mm, "
                       "or give discretization.spacing")
    if item.size_default is not None:  # the file gives no spacing: the tissue's size sets it
        width, height = item.tissue_size
        shape = "size" if item.size_default == "tissue.size" else "outline"
        got = f"[{width:g}, {height:g}] mm" if shape == "size" else f"an outline of {width:g} x {height:g} mm"
        return Setting(item.size_default, got,
                       f"a {shape} whose default particle spacing (here {spacing:.3g} mm) gives",
                       "check that it is in mm, or give discretization.spacing")
    return Setting(origin.name("spacing"), f"{spacing:g} mm", "a spacing giving", "coarsen it")


def _memory_setting(item: Estimate, budget: float) -> Setting:
    """What takes the memory past `budget`: the needle step when the run would fit without
    what it keeps of its steps (_step_memory); else the particles (as _particle_setting) when
    even a standard kernel (dilation 2, 2 x 2 Gauss points per particle) would pass it, else
    the larger of the kernel's two factors, its support (dilation) or its quadrature points."""
    size, d, origin = item.size, item.discretization, item.origin
    if item.needle_step is not None and item.memory_bytes - item.step_memory <= budget:
        held = min(item.runs, HELD_RUNS)
        both = f", {_bytes(item.step_memory)} for the {held:g} runs held at once" if held > 1 else ""
        return Setting("needle.step", f"{item.needle_step:g} rad", "", "take a larger step",
                       f"{_count(item.steps)} needle steps keep ~{_bytes(item.step_memory / held)} of states and "
                       f"solver blocks until the run ends{both}; ")

    def fits_with_a_standard_kernel(particles: float) -> bool:
        standard = replace(size, particles=_capped(particles), neighbours=min(size.neighbours, REFERENCE_NEIGHBOURS),
                           points_per_particle=min(size.points_per_particle, REFERENCE_POINTS_PER_PARTICLE))
        return BASE_MEMORY + _scale(standard)[0] <= budget

    if not fits_with_a_standard_kernel(size.particles):
        return _particle_setting(item, fits_with_a_standard_kernel)
    neighbours = size.effective_neighbours / REFERENCE_NEIGHBOURS
    points = size.points_per_particle / REFERENCE_POINTS_PER_PARTICLE
    if neighbours >= points:
        return Setting(origin.name("dilation"), f"{d.dilation:g}", "", "lower it (RKPM uses 1.5-3)",
                       f"a kernel support of {_amount(size.effective_neighbours)} particles per point takes "
                       f"{neighbours:.3g} times the memory of dilation 2's {REFERENCE_NEIGHBOURS:g}; ")
    order, cells = d.quadrature_order, d.cells_per_spacing
    key, got = ("quadrature_order", order) if order * order / 4 >= cells * cells else ("cells_per_spacing", cells)
    return Setting(origin.name(key), f"{got}", "", "lower it",
                   f"{order} x {order} Gauss points in each of {cells} x {cells} cells per particle take "
                   f"{points:.3g} times the memory of the default 2 x 2 in one; ")


def _count(value: int, about: str = "") -> str:
    return f"over {COUNT_CAP:.0e}" if value >= COUNT_CAP else f"{about}{value}"


def _amount(value: float) -> str:
    return f"~{value:.3g}" if math.isfinite(value) else "more than 1e+308"


def _bytes(value: float) -> str:
    for unit, size in (("GB", 1e9), ("MB", 1e6)):
        if value >= size:
            return f"{value / size:.3g} {unit}"
    return f"{value / 1e3:.3g} kB"


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.2g} s"
    if seconds < 7200:
        return f"{seconds / 60:.3g} min"
    if seconds < 172800:
        return f"{seconds / 3600:.3g} h"
    return f"{seconds / 86400:.3g} days"
