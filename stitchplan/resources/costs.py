"""What a run will cost: its time and memory estimated from its model size (Estimate, estimate)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ..config import Discretization, Scenario
from ..needle.geometry import needle_zone, scenario_needle
from .formatting import bytes_text, count_text, duration_text
from .model_size import COUNT_CAP, ModelSize, grid_count, model_size, needle_steps, per_side
from .origin import Origin, radius_default_of, size_default_of

# from benchmarks/results/resource_costs.md (python benchmarks/resource_costs.py): the time
# constants a fit of the code as it is (fits vary with the machine's load: the exponent by
# 1.07-1.19 over two runs; the file's "guard now" columns check these against every run); the
# memory constants an earlier fit's (git history), kept because they bound every measured peak
# from above, where the latest fits' sublinear exponent (the fixed cost of a run's first imports
# spread over few particles) falls below the largest one
SECONDS_PER_PARTICLE_STEP = {"deform": 6.5e-5, "insertion": 1.5e-5}  # at 1 000 particles
TIME_EXPONENT = 1.07  # seconds ~ particles^TIME_EXPONENT
# a needle run with `linear_solver: minres` against the direct solve the constants above were
# fitted on: 3.0-5.1x on SH 1/2 from 324 to 2601 particles (mortar coupling;
# benchmarks/results/simulate_speed.md, "Where MINRES stagnates"; single runs, which vary)
MINRES_TIME_FACTOR = 5.0
# a needle step's time grows with the steps before it: each Newton solve reads E K^-1, one
# row pair per needle point (needle.saddle_point). The unplanned runs of sh12_100x100 in steps of
# 0.01 and 0.0025 rad (301 and 1 202 steps: 2.4 and 17.8 s, benchmarks/results/resource_costs.md)
# fit a step k taking a + b k with a / b = 381 steps (330 and 345 in two runs before: the middle
# one kept), so N steps take a N (1 + N / (2 x 345)); both terms grow about linearly with the
# particles, their ratio does not
STEP_TIME_DOUBLES_AT = 345.0
# `simulate --condition-numbers`: each needle step forms the saddle matrix, K0^-1, its Cholesky
# factor and the preconditioned matrix densely and takes two sets of eigenvalues
# (needle.saddle_point.condition_numbers), ~unknowns^3 time and ~unknowns^2 memory with
# unknowns = 2 x particles. From benchmarks/results/condition_costs.md (python
# benchmarks/condition_costs.py, two runs on a shared machine): 0.27-0.32 s x (unknowns / 1000)^3
# a step at 972 and 1379 particles, 0.28-0.40 at 642, more below (0.1-0.3 s a step, where the
# dense part is not yet most of it); at the peak 7.2-8.8 arrays of unknowns^2 floats from 642
# particles up, 12 at 265 (5 MB above 9, which the tissue's memory model's margin there covers)
CONDITION_SECONDS = 0.3  # per needle step at 1000 unknowns
CONDITION_MATRICES = 9.0  # dense (unknowns, unknowns) float arrays alive at once
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
REFERENCE_PARTICLES = 1000.0
REFERENCE_NEIGHBOURS = 16.0  # (2 x dilation)^2 at dilation 2
REFERENCE_POINTS_PER_PARTICLE = 4.0  # 2 x 2 Gauss points per cell, one cell per particle
# what a needle run keeps of its steps until it ends (_step_memory, from the arrays the code
# keeps; checked against measured peaks in benchmarks/results/resource_costs.md)
FLOAT_BYTES = 8.0
# a scipy CSR matrix: per entry its value and int32 column, per row its int32 start
SPARSE_ENTRY_BYTES = 12.0
SPARSE_ROW_BYTES = 4.0
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
# runs of a plan on its model (planner passes; benchmarks/results/plan_speed.md: a planned run
# takes ~2.5 unplanned ones) and replays on the verification model (half the spacing)
PLAN_RUNS = 3
VERIFICATION_RUNS = 2
# runs whose steps' states one process holds at once (_step_memory each), of the `runs` an
# estimate counts: a plan holds its unplanned comparison (--compare), its first pass (later
# passes take its early steps over: planning.pass_offsets.PassPrefix), its best pass so far and the
# pass running, 1-4 runs (measured on SH 1/2 at 0.005 rad: 237 MiB for one run, 323 MiB for a
# plan of two passes, 472 MiB with the comparison, 363 MiB for the 100 x 30 block's two passes;
# tests/test_resource_guard.py MEASURED_PEAKS); a verification its first replay while the second
# runs (run_insertion `start_from`). Two: within 2x of one and of four
HELD_RUNS = 2

# calibrate material: what the fit holds a marker beside its experiments' models: the shape
# functions' rows at the markers twice (N(X_i) and its free columns, SPARSE_ENTRY_BYTES a
# neighbour each: MARKER_ROWS), and the rest MARKER_BYTES (the markers read, the residual, its
# Jacobian and the simulated positions of the evaluations the fit keeps, the least squares'
# copies of them). Measured with /usr/bin/time -f %M on the sample calibration's first
# experiment sampled at 1e4 to 1e6 markers (tests/test_resource_guard.py MEASURED_MARKER_PEAKS):
# 1.2-1.4 kB a marker above the models' estimate at dilation 2 (within 1.11-1.35x of the
# estimate), ~1.5 kB at dilation 3 (300 000 markers)
MARKER_BYTES = 1.3e3
MARKER_ROWS = 2.0
# calibrate needle: a row of the force recordings, as read (the text, the parsed columns and
# their line numbers) and fitted (the line fits' design matrices and residuals, the result's
# columns), with the --plot's figure; measured as the markers, on the sample recording in tissue
# sampled at 1e4 to 1e6 rows: 98 bytes a row, 123 with --plot (matplotlib's import: ~40 MB more;
# the estimate 1.31-1.32x and 1.07x the peaks)
MEMORY_PER_RECORDING_ROW = 130.0
PLOT_MEMORY = 25e6  # beyond BASE_MEMORY, which the needle fit's interpreter stays ~20 MB below


def marker_bytes(neighbours: float) -> float:
    """Bytes a marker takes in calibrate material at `neighbours` particles per kernel support."""
    return MARKER_BYTES + MARKER_ROWS * SPARSE_ENTRY_BYTES * neighbours


@dataclass(frozen=True)
class Data:
    """Measured data whose memory grows with its items beside a command's models: a material
    calibration's markers, a needle calibration's recording rows. A refusal names `name`, the
    field and file of most of them."""

    name: str  # e.g. "experiments[0].markers: markers1.csv", "--tissue: tissue.csv"
    count: int  # that file's items
    total: int  # every file's
    unit: str  # "markers", "rows"
    bytes_per_item: float
    others: str = ""  # what `total` counts beside the file, e.g. "in all 2 experiments"
    advice: str = ""  # how to take fewer

    @property
    def memory_bytes(self) -> float:
        return self.bytes_per_item * self.total

    def describe(self) -> str:
        return (f"{self.total} {self.unit}{f' {self.others}' if self.others else ''}, ~{bytes_text(self.memory_bytes)} "
                f"memory (~{bytes_text(self.bytes_per_item)} each)")


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
    # size sets (a scenario giving no spacing, and no needle radius setting it: size_default_of)
    size_default: str | None = None
    # simulate --condition-numbers: seconds and bytes of memory_bytes of its dense condition numbers
    condition_seconds: float = 0.0
    condition_memory: float = 0.0

    def describe(self) -> str:
        about = "" if self.size.exact else "about "
        runs = f" in each of {self.runs:g} runs" if self.runs != 1 else ""
        # costs of a count held at COUNT_CAP are lower bounds
        memory = "over " if self.size.particles >= COUNT_CAP else "~"
        time = "over " if self.size.particles >= COUNT_CAP or self.steps >= COUNT_CAP else "~"
        return (f"{self.label}: {count_text(self.size.particles, about)} particles, {count_text(self.steps)} "
                f"{self.step_kind}{runs}, {memory}{bytes_text(self.memory_bytes)} memory, "
                f"{time}{duration_text(self.seconds)}")


def size_scale(size: ModelSize) -> tuple[float, float]:
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

    - the saddle-point solver's E K^-1 (2Q, 2 n_free) and E K^-1 E^T (2Q, 2Q), the latter while
      2Q <= 2 n_free only (SaddlePointSolver._grow), live in buffers whose capacity doubles from
      the first step's 2Q_1 to at least 2Q_N (E K^-1 E^T's until 2Q passes 2 n_free); every
      state holds a view of the buffer then in use, so every buffer of the doubling stays (sum
      of capacities^2: ~4/3 of the last one's). Counted at their capacity, which the last one's
      resident rows approach (numpy asks for transparent huge pages for large arrays: 2Q_N rows
      written are resident whole), and which covers what the allocator keeps of the steps' freed
      temporaries (SH 1/2 at 0.005 and 0.0025 rad, when each state still held a copy of the load
      rows: peaks ~180 and ~430 MB above the resident bytes of the arrays kept, ~100 MB of them
      the interpreter's and the model's; the peaks are now 0.83-0.88x the estimate there,
      tests/test_resource_guard.py);
    - the coupling's W (Q_k, m_k), new in each step (NeedleCoupling._partition; the point
      coupling's identity, (k + 1)^2), which each step's state keeps sparse (at most two
      entries a row, NeedleCoupling.state): sum over the steps ~ N^2, and the last one dense;
    - the track's arrays, new in each state (TRACK_BYTES_PER_POINT): ~ N^2;
    - STEP_BYTES_PER_PARTICLE per particle and step.

    A renewed factor starts new buffers (SaddlePointSolver._use), which the states then keep
    as well: the measured runs renewed none (the factor of K0 solves their needle steps).
    Sums in floating point, finite for counts up to COUNT_CAP."""
    from ..needle.track_layout import (ARC_ENDS, MULTIPLIER_SPACINGS, POINTS, QUADRATURE_PER_ELEMENT,
                                       segment_subintervals)

    needle, d = scenario.needle, scenario.discretization
    n = float(steps)
    sum_k = n * (n + 1.0) / 2.0
    arc_ends = needle.coupling != POINTS and needle.multiplier_ends == ARC_ENDS
    # Q_k = per_segment k + first, m_k = slope k + offset
    pieces = 1.0
    if needle.coupling == POINTS:
        per_segment, first, slope, offset = 1.0, 1.0, 1.0, 1.0
    else:
        at_needle = d.spacing if d.needle_spacing is None else d.needle_spacing
        element = max(MULTIPLIER_SPACINGS * at_needle, needle.multiplier_length or 0.0)
        step_length = scenario_needle(scenario).insertion_step
        ratio = min(per_side(step_length, element), float(COUNT_CAP))
        pieces = float(segment_subintervals(step_length, at_needle)) if at_needle > 0 else float(COUNT_CAP)
        # arc ends: at least 2 Gauss points per segment, QUADRATURE_PER_ELEMENT per element length;
        # segment ends: the segments' Gauss points, 2 per piece; whole segments of at least an
        # element's length (at most one per segment)
        per_segment = max(2.0, float(math.ceil(QUADRATURE_PER_ELEMENT * ratio))) if arc_ends else 2.0 * pieces
        first, slope, offset = 0.0, ratio if arc_ends else min(ratio, 1.0), 2.0
    entries = 1.0 if needle.coupling == POINTS else 2.0  # of W's rows: the identity's, or two hats'
    quadrature_sum = per_segment * sum_k + first * n  # sum of Q_k
    weights = ((SPARSE_ENTRY_BYTES * entries + SPARSE_ROW_BYTES) * quadrature_sum
               + FLOAT_BYTES * (per_segment * n + first) * (slope * n + offset))
    # the doubling buffers' capacities c_0 2^j, j = 0..J, c_0 = 2 Q_1, c_0 2^J >= 2 Q_N; E K^-1 E^T's
    # up to J' with c_0 2^J' >= min(2 Q_N, 2 particles)
    start, end = 2.0 * (per_segment + first), 2.0 * (per_segment * STEP_MARGIN * n + first)
    capacities = start * (2.0 ** (_doublings(start, end) + 1) - 1.0)  # sum of c_j
    squares = start * start * (4.0 ** (_doublings(start, min(end, 2.0 * particles)) + 1) - 1.0) / 3.0  # c_j^2, j <= J'
    blocks = FLOAT_BYTES * (squares + 2.0 * particles * capacities)
    track = (TRACK_BYTES_PER_POINT + TRACK_BYTES_PER_PIECE * (pieces - 1.0)
             + (ARC_BYTES_PER_QUADRATURE_POINT * per_segment if arc_ends else 0.0)) * sum_k
    return blocks + weights + track + STEP_BYTES_PER_PARTICLE * particles * n


def _doublings(start: float, end: float) -> int:
    """J: the doublings from a buffer's first capacity `start` to one of at least `end`."""
    return max(math.ceil(math.log2(end / start) - 1e-9), 0)


def condition_costs(particles: float, steps: float) -> tuple[float, float]:
    """(seconds, bytes) of a needle run's dense condition numbers over `steps` steps of a model
    of `particles` (CONDITION_SECONDS, CONDITION_MATRICES); finite up to COUNT_CAP."""
    unknowns = 2.0 * float(particles)
    return (CONDITION_SECONDS * (unknowns / 1000.0) ** 3 * float(steps),
            CONDITION_MATRICES * FLOAT_BYTES * unknowns * unknowns)


def condition_particles_within(seconds: float, steps: float) -> float:
    """The particles whose condition numbers over `steps` steps take `seconds` (condition_costs's
    time, inverted)."""
    return 0.5 * 1000.0 * (seconds / (CONDITION_SECONDS * float(steps))) ** (1.0 / 3.0)


def estimate(scenario: Scenario, kind: str, label: str | None = None, runs: float = 1.0,
             origin: Origin | None = None, linear_solver: str | None = None,
             condition_numbers: bool = False) -> Estimate:
    """The cost of `runs` runs of `kind` ("deform" or "insertion") on the scenario; `origin`:
    what set its discretization, when not (all of) the scenario file's `discretization:`;
    `linear_solver`: the needle steps' where an option overrides the scenario's;
    `condition_numbers`: each needle step takes its dense condition numbers (condition_costs)."""
    size = model_size(scenario, derived=bool(origin and origin.derived))
    if kind == "deform":
        steps, step_kind = scenario.load_steps, "load steps"
    else:
        steps, step_kind = needle_steps(scenario), "needle steps"
    memory, time = size_scale(size)
    kept = 0.0 if kind == "deform" else min(runs, HELD_RUNS) * _step_memory(scenario, size.particles, steps)
    seconds = SECONDS_PER_PARTICLE_STEP[kind] * time * steps * runs
    if kind != "deform":
        seconds *= 1.0 + float(steps) / (2.0 * STEP_TIME_DOUBLES_AT)
        if (linear_solver or scenario.needle.linear_solver) == "minres":
            seconds *= MINRES_TIME_FACTOR
    condition_seconds, condition_memory = (condition_costs(size.particles, steps)
                                           if condition_numbers and kind != "deform" else (0.0, 0.0))
    condition_seconds *= runs
    seconds += condition_seconds
    d, origin = scenario.discretization, origin or Origin()
    graded = needle_zone(scenario) is not None
    radius_default = radius_default_of(scenario, origin)
    return Estimate(label or kind, size, steps, step_kind, runs, BASE_MEMORY + memory + kept + condition_memory,
                    seconds,
                    d.spacing, None if kind == "deform" else scenario.needle.step, d, origin,
                    grid_count(scenario.tissue.bounding_size, d.spacing) if graded else None,
                    radius_default, tuple(scenario.tissue.bounding_size),
                    None if kind == "deform" else scenario.needle.radius, kept,
                    None if radius_default is not None else size_default_of(scenario, origin),
                    condition_seconds, condition_memory)


def held_in_one_process(memory_bytes: list[float]) -> float:
    """Bytes of runs held at once in one process, from their estimates' `memory_bytes`: a
    material calibration's experiments, each keeping its model and tangent factor between the
    fit's evaluations, with one more run's worth beside them for the sensitivity's factor of
    the experiment at hand (SuperLU maps ~1 kB of address space per stored entry of the
    matrix it factors, a factor as large as the experiment's own); the interpreter's
    BASE_MEMORY once."""
    arrays = [max(amount - BASE_MEMORY, 0.0) for amount in memory_bytes]
    return BASE_MEMORY + sum(arrays) + max(arrays, default=0.0)


def held_at_once(memory_bytes: list[float], forked: bool = True) -> float:
    """Bytes of runs going on at once, each in its own process, from their estimates'
    `memory_bytes`: the interpreter's BASE_MEMORY in them counted once for the command and,
    when the others are `forked` helpers (the libraries' pages shared with the command),
    HELPER_BASE_MEMORY for each of them; a Dask worker has the whole of its own."""
    if not forked:
        return sum(memory_bytes)
    helpers = len(memory_bytes) - 1
    return BASE_MEMORY + sum(amount - BASE_MEMORY for amount in memory_bytes) + helpers * HELPER_BASE_MEMORY
