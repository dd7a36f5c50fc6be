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
  (neighbours / 16) x (quadrature points per particle / 4), plus the interpreter's share;
- time: the tangent assembly B^T W B costs ~ quadrature points x neighbours^2 per Newton
  iteration and the factorization grows a little faster than the particles; seconds =
  SECONDS_PER_PARTICLE_STEP x particles^TIME_EXPONENT x steps x (neighbours / 16)^2 x
  (quadrature points per particle / 4) x runs.

The constants come from `python benchmarks/resource_costs.py` (benchmarks/results/
resource_costs.md), measured on the 2-core machine the tool is developed on, which is
shared: the memory model is within 0.93-1.23x of every measured case, the time model within
0.78-1.6x of the dilation-2 cases, and the (neighbours/16)^2 time scaling overestimated the
unfitted dilation-3 case (0.33x there; 0.96x in an earlier run of the same benchmark). The
memory limit is what protects the machine; the time is a guide, not a promise.

Limits (Limits; the CLI's --max-particles raises the first, --no-resource-check skips
them all):

- MAX_PARTICLES = 50 000: a deform at 1 mm spacing on the 100 x 100 mm slab (10 447
  particles) took 30 s and 0.77 GB; 50 000 particles are estimated at ~3 min and ~5.6 GB
  per 10-step solve, a plan (several insertions and a verification model of 4x the
  particles) at hours;
- MAX_NEEDLE_STEPS = 2 000: the shipped needles take 15-40 steps; 2 000 steps over a half
  circle advance the SH needle's tip by radius x step ~ 0.014 mm each, 1/130 of the default
  particle spacing at the needle (1.78 mm): nothing the model resolves, while the run time
  grows with every step;
- MAX_NEIGHBOURS = 400 particles in a kernel support (dilation 10): the RK functions stop
  being local well before (RKPM practice: dilation 1.5-3, 9-36 neighbours), and the
  tangent's cost grows with the square of the neighbours;
- MEMORY_SHARE = 0.5 of the memory the machine has available now.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass, replace

import numpy as np

from .config import Scenario
from .errors import InputError
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

# from benchmarks/results/resource_costs.md (python benchmarks/resource_costs.py)
SECONDS_PER_PARTICLE_STEP = {"deform": 2.4e-4, "insertion": 1.3e-4}  # at 1 000 particles
TIME_EXPONENT = 1.11  # seconds ~ particles^TIME_EXPONENT
MEMORY_PER_PARTICLE = 3.6e4  # bytes per particle at 1 000 particles
MEMORY_EXPONENT = 1.28
BASE_MEMORY = 94e6  # bytes: the interpreter with numpy, scipy and stitchplan loaded
REFERENCE_PARTICLES = 1000.0
REFERENCE_NEIGHBOURS = 16.0  # (2 x dilation)^2 at dilation 2
REFERENCE_POINTS_PER_PARTICLE = 4.0  # 2 x 2 Gauss points per cell, one cell per particle

OVERRIDE = "raise --max-particles or pass --no-resource-check to run it anyway"
# runs of a plan on its model (planner passes; benchmarks/results/plan_speed.md: a planned run
# takes ~2.5 unplanned ones) and replays on the verification model (half the spacing)
PLAN_RUNS = 3
VERIFICATION_RUNS = 2


@dataclass(frozen=True)
class Limits:
    max_particles: int = MAX_PARTICLES
    max_needle_steps: int = MAX_NEEDLE_STEPS
    max_neighbours: int = MAX_NEIGHBOURS
    memory_share: float = MEMORY_SHARE


@dataclass(frozen=True)
class ModelSize:
    """What the discretization of a scenario will hold, before it is built."""

    particles: int
    exact: bool  # counted (True) or estimated from the local spacing (False)
    neighbours: float  # particles in a kernel support, (2 x dilation)^2
    points_per_particle: float  # quadrature points per particle

    @property
    def effective_neighbours(self) -> float:
        return min(self.neighbours, float(self.particles))


@dataclass(frozen=True)
class Estimate:
    """The estimated cost of one command's runs."""

    label: str  # e.g. "deform", "simulate", "plan verification"
    size: ModelSize
    steps: int  # load steps or needle steps of one run
    step_kind: str  # "load steps" or "needle steps"
    runs: float  # runs of that size (plan: planned passes and the comparison)
    memory_bytes: float
    seconds: float
    spacing: float  # the discretization's spacing, mm
    needle_step: float | None  # rad per needle step (insertions)

    def describe(self) -> str:
        about = "" if self.size.exact else "about "
        runs = f" in each of {self.runs:g} runs" if self.runs != 1 else ""
        return (f"{self.label}: {about}{self.size.particles} particles, {self.steps} {self.step_kind}{runs}, "
                f"~{_bytes(self.memory_bytes)} memory, ~{_duration(self.seconds)}")


# --- sizes -------------------------------------------------------------------------------


def model_size(scenario: Scenario) -> ModelSize:
    """Particles, neighbours per kernel support and quadrature points per particle of the
    scenario's discretization, without building it."""
    d = scenario.discretization
    particles, exact = _particles(scenario)
    points = float(d.quadrature_order ** 2 * d.cells_per_spacing ** 2)
    return ModelSize(particles, exact, (2.0 * d.dilation) ** 2, points)


def _particles(scenario: Scenario) -> tuple[int, bool]:
    d, (width, height) = scenario.discretization, scenario.tissue.bounding_size
    zone = needle_zone(scenario)
    if zone is None:  # the uniform grid of tissue.particles.grid_particles
        nx, ny = max(round(width / d.spacing), 1), max(round(height / d.spacing), 1)
        # load segments add grid lines through their ends and a grading toward them
        # (tissue.particles.end_zones): the grid is then a lower bound (~5-30 % below)
        return (nx + 1) * (ny + 1), not scenario.loads
    lattice = (width / d.needle_spacing) * (height / d.needle_spacing)
    if lattice <= COUNT_EXACTLY_UP_TO:
        graded = graded_particles(scenario.tissue.bounding_size, d.spacing, d.needle_spacing,
                                  np.asarray(zone[0], dtype=float), zone[1], points=zone[2])
        return len(graded.particles), True
    return _graded_estimate(scenario.tissue.bounding_size, d.spacing, d.needle_spacing, zone), False


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
    return int(np.sum(width * height / samples ** 2 / side ** 2))


# --- costs -------------------------------------------------------------------------------


def _scale(size: ModelSize) -> tuple[float, float]:
    """(memory, time) factors of a model relative to one reference particle."""
    particles = max(size.particles, 1)
    neighbours = size.effective_neighbours / REFERENCE_NEIGHBOURS
    points = size.points_per_particle / REFERENCE_POINTS_PER_PARTICLE
    relative = particles / REFERENCE_PARTICLES
    memory = MEMORY_PER_PARTICLE * REFERENCE_PARTICLES * relative ** MEMORY_EXPONENT * neighbours * points
    time = REFERENCE_PARTICLES * relative ** TIME_EXPONENT * neighbours ** 2 * points
    return memory, time


def estimate(scenario: Scenario, kind: str, label: str | None = None, runs: float = 1.0) -> Estimate:
    """The cost of `runs` runs of `kind` ("deform" or "insertion") on the scenario."""
    size = model_size(scenario)
    if kind == "deform":
        steps, step_kind = scenario.load_steps, "load steps"
    else:
        steps, step_kind = scenario_needle(scenario).expected_steps, "needle steps"
    memory, time = _scale(size)
    seconds = SECONDS_PER_PARTICLE_STEP[kind] * time * steps * runs
    return Estimate(label or kind, size, steps, step_kind, runs, BASE_MEMORY + memory, seconds,
                    scenario.discretization.spacing, None if kind == "deform" else scenario.needle.step)


def rescaled(scenario: Scenario, factor: float) -> Scenario:
    """The scenario with its particle spacings scaled by `factor` (a plan's verification
    model: half the spacing)."""
    d = scenario.discretization
    changes = {"spacing": d.spacing * factor, "accuracy": None}
    if d.needle_spacing is not None and d.needle_refinement is None:
        changes["needle_spacing"] = d.needle_spacing * factor
    return replace(scenario, discretization=d.replaced(**changes))


def available_memory() -> float | None:
    """Bytes of memory available now (MemAvailable of /proc/meminfo, else the physical
    memory), None when unknown."""
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


# --- the guard ---------------------------------------------------------------------------


def check_resources(estimates: list[Estimate], limits: Limits = Limits(),
                    memory: float | None = None) -> None:
    """Refuse (InputError, one line per limit passed) runs beyond the limits; log the
    estimates otherwise. `memory`: bytes available (default: available_memory())."""
    memory = available_memory() if memory is None else memory
    lines = []
    for item in estimates:
        size, what = item.size, f"estimated {item.describe()}"
        if size.neighbours > limits.max_neighbours:
            dilation = math.sqrt(size.neighbours) / 2.0
            most = math.sqrt(limits.max_neighbours) / 2.0
            lines.append(f"discretization.dilation: got {dilation:g}, expected at most {most:g} "
                         f"(a kernel support of ~{size.neighbours:.3g} particles per point, at most "
                         f"{limits.max_neighbours}; RKPM uses 1.5-3)")
        elif size.particles > limits.max_particles:
            lines.append(f"discretization.spacing: got {item.spacing:g} mm, expected a spacing giving at most "
                         f"{limits.max_particles} particles ({what}); coarsen it, or {OVERRIDE}")
        elif memory is not None and item.memory_bytes > limits.memory_share * memory:
            lines.append(f"discretization.spacing: got {item.spacing:g} mm, expected a model within "
                         f"{limits.memory_share:.0%} of the {_bytes(memory)} of memory available "
                         f"({what}); coarsen it, or {OVERRIDE}")
        if item.needle_step is not None and item.steps > limits.max_needle_steps:
            lines.append(f"needle.step: got {item.needle_step:g} rad, expected a step giving at most "
                         f"{limits.max_needle_steps} needle steps ({what}); take a larger step, or pass "
                         "--no-resource-check")
    if lines:
        error = InputError("\n".join(lines))
        error.lines = lines
        raise error
    for item in estimates:
        log.info("resources: %s", item.describe())


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
