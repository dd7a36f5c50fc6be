"""The limits a run is held within: particles, needle steps, neighbours per point and the memory share."""

from __future__ import annotations

from dataclasses import dataclass

MAX_PARTICLES = 50_000
MAX_NEEDLE_STEPS = 2_000
MAX_NEIGHBOURS = 400
MEMORY_SHARE = 0.5
# seconds of a run's dense condition numbers (simulate --condition-numbers): the diagnostics
# of small models, which past this take longer than the run they diagnose by far
MAX_CONDITION_SECONDS = 600.0


@dataclass(frozen=True)
class Limits:
    max_particles: int = MAX_PARTICLES
    max_needle_steps: int = MAX_NEEDLE_STEPS
    max_neighbours: int = MAX_NEIGHBOURS
    memory_share: float = MEMORY_SHARE
    max_condition_seconds: float = MAX_CONDITION_SECONDS
