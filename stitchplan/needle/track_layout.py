"""How densely the needle coupling (needle/coupling.py) lays its multipliers and constraint
points along the track, and its kinds, as numbers and names only: the resource guard
(stitchplan/resources/costs.py) counts a run's constraints from them before `plan` imports the
numerics (cli.commands.plan hands its helper the refined model meanwhile).
"""

from __future__ import annotations

import math

MULTIPLIER_SPACINGS = 1.0  # mortar multiplier elements span at least this many local spacings
QUADRATURE_PER_ELEMENT = 2.0  # arc element ends: constraint Gauss points per segment >= this x segment / element
POINTS, MORTAR = "points", "mortar"  # `needle.coupling`
MAX_PIECES = 1e15  # a count the resource guard can still refuse (a spacing that underflowed)
SEGMENT_ENDS, ARC_ENDS = "segments", "arc"  # `needle.multiplier_ends`: mortar element ends at needle points or exact arc lengths


def segment_subintervals(segment_length: float, spacing: float) -> int:
    """Equal pieces of a track segment `segment_length` mm long, two Gauss points each, that
    carry the mortar coupling's loads and constraint: enough that the points lie at most one
    particle `spacing` apart on average (one piece while a segment is at most two spacings
    long: the shipped needle scenes at their spacing and at half of it). Two points per segment
    on particles much finer than the segment would act as point forces on them, whose
    log-singular displacement keeps the exit error moving under refinement
    (benchmarks/results/needle_fem_reference.md)."""
    return max(1, math.ceil(min(segment_length / (2.0 * spacing), MAX_PIECES) - 1e-9))
