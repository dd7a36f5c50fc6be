"""Where the needle's loads sit on its track Gamma_N (needle/coupling.py): the two-point Gauss
rule on each piece of a segment (segment_gauss_points; the mortar coupling's constraint
quadrature is the same points), the cutting force's density behind the tip and its share on
the part inside the tissue (cutting_density, cutting_share; the profile a run uses is
needle/coupling.py's CUTTING_PROFILE), and the load points with their rows and forces
(LoadQuadrature).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .constraint_rows import joined_rows

GAUSS_POINTS = 0.5 + np.array([-0.5, 0.5]) / math.sqrt(3.0)  # two-point rule on [0, 1]
UNIFORM, SMOOTH = "uniform", "smooth"


def segment_gauss_points(pieces: int) -> np.ndarray:
    """The two-point rule on each of `pieces` equal pieces of [0, 1], ascending, (2 pieces,);
    every point weighs 1 / (2 pieces)."""
    return ((np.arange(pieces)[:, None] + GAUSS_POINTS[None, :]) / pieces).ravel()


def cutting_density(s: np.ndarray, length: float) -> np.ndarray:
    """The smooth cutting profile's density (1/mm) at s mm of needle behind the tip:
    (2 / l) sin^2(pi s / l) on [0, l], zero beyond; its integral over [0, l] is one."""
    s = np.asarray(s, dtype=float)
    return np.where((s >= 0.0) & (s <= length), 2.0 / length * np.sin(math.pi * s / length) ** 2, 0.0)


def cutting_share(inside: float, length: float, profile: str = SMOOTH) -> float:
    """The share of the cutting force on the first `inside` mm of [0, l] behind the tip: the
    density's integral, z / l - sin(2 pi z / l) / (2 pi) for the smooth profile (z = min(inside, l)),
    z / l for the uniform one."""
    z = min(max(inside, 0.0), length)
    if profile == UNIFORM:
        return z / length
    return z / length - math.sin(2.0 * math.pi * z / length) / (2.0 * math.pi)

@dataclass(frozen=True)
class LoadQuadrature:
    """Points of Gamma_N carrying needle loads: reference points, their rows and forces (N)."""

    points: np.ndarray  # (L, 2)
    # N(X_l) T, (L, n_free), in parts one under the other: the segments' Gauss points' rows
    # (the track's, shared with every step's state) and those of the extra points. A state is
    # kept per needle step: one matrix of all the rows, new in each, would make a long
    # insertion's states grow with the square of its steps
    row_parts: tuple[sp.csr_matrix, ...]
    magnitudes: np.ndarray  # (L,)
    # the points after the segments' Gauss points (a partly covered segment's), each as a
    # linear combination of two of its segment's Gauss points: their indices and weights (P, 2)
    # each; None where the layout has other points (the smooth cutting profile)
    lumping: tuple[np.ndarray, np.ndarray] | None = (np.zeros((0, 2), dtype=np.int64), np.zeros((0, 2)))

    @property
    def rows(self) -> sp.csr_matrix:
        """N(X_l) T, (L, n_free), as one new matrix."""
        return joined_rows(*self.row_parts)
