"""How densely the needle coupling (needle/coupling.py) lays its multipliers and constraint
points along the track, and its kinds, as numbers and names only: the resource guard
(stitchplan/resources.py) counts a run's constraints from them before `plan` imports the
numerics (cli.commands.plan hands its helper the refined model meanwhile).
"""

from __future__ import annotations

MULTIPLIER_SPACINGS = 1.0  # mortar multiplier elements span at least this many local spacings
QUADRATURE_PER_ELEMENT = 2.0  # arc element ends: constraint Gauss points per segment >= this x segment / element
POINTS, MORTAR = "points", "mortar"  # `needle.coupling`
SEGMENT_ENDS, ARC_ENDS = "segments", "arc"  # `needle.multiplier_ends`: mortar element ends at needle points or exact arc lengths
