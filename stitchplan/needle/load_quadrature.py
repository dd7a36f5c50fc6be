"""Where the needle's loads sit on its track Gamma_N (needle/coupling.py): the two-point Gauss
rule on each piece of a segment (segment_gauss_points; the mortar coupling's constraint
quadrature is the same points), the cutting force's density behind the tip and its share on
the part inside the tissue (cutting_density, cutting_share; the profile a run uses is
CUTTING_PROFILE), the friction and the cutting force laid out on the track's points
(TrackLoads, eq. 3.58 and 3.64), and the load points with their rows and forces
(LoadQuadrature).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..tissue.quadrature import gauss_legendre
from .constraint_rows import joined_rows

GAUSS_POINTS = 0.5 + np.array([-0.5, 0.5]) / math.sqrt(3.0)  # two-point rule on [0, 1]
UNIFORM, SMOOTH = "uniform", "smooth"
# mortar: the cutting force's density along the last cutting_length l mm of needle, s mm behind
# the tip: "uniform" 1 / l; "smooth" (2 / l) sin^2(pi s / l) (cutting_density), zero at the tip
# and at s = l (the taper's ends). With `needle.cutting_ramp` the force inside is
# cutting_force x the density's integral over the part of [0, l] inside the tissue
# (cutting_share: ~ s^3 at the entry for "smooth"); without, the density on that part is
# scaled to the whole force.
CUTTING_PROFILE = UNIFORM
# smooth profile: Gauss points per cutting_length on a covered segment (its density is not a
# polynomial): at least P on a wholly covered one (its P friction Gauss points while they suffice),
# 4 on the partly covered one at the zone's end; 8 per l keeps the total within 0.5 % of
# cutting_share (tests/test_needle_coupling.py)
SMOOTH_POINTS_PER_LENGTH = 8.0


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


def _covered(zone: float, needle_length: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For segments standing for `needle_length` mm of needle each (tip last, a wound's gaps
    zero): the needle length between each segment's tip end and the tip, and the share of
    each segment within `zone` mm of the tip."""
    behind = np.concatenate([np.cumsum(needle_length[::-1])[::-1][1:], [0.0]])
    with np.errstate(divide="ignore", invalid="ignore"):
        covered = np.where(needle_length > 0, np.clip((zone - behind) / needle_length, 0.0, 1.0), 0.0)
    return behind, covered


def _along_segments(start: np.ndarray, end: np.ndarray, along: np.ndarray) -> np.ndarray:
    """Points at fractions `along` (k, n) of the segments start -> end (k, 2), as (k n, 2)."""
    return (start[:, None, :] + along[..., None] * (end - start)[:, None, :]).reshape(-1, 2)


@dataclass(frozen=True)
class TrackLoads:
    """The needle's loads on Gamma_N: friction per mm of needle inside the tissue on every
    segment's Gauss points (eq. 3.58, 3.64) and the cutting force, on the tip segment (the
    point coupling) or over the last `cutting_length` mm of needle (mortar)."""

    step_length: float  # needle length a whole segment stands for, mm
    friction: float  # N per mm of needle inside
    cutting_force: float  # N
    cutting_length: float  # mm of needle behind the tip that cut (mortar)
    cutting_ramp: bool  # cutting_force / cutting_length per mm of cutting edge inside
    on_tip_segment: bool  # the point coupling: the cutting force on the tip segment's points

    def layout(self, points: np.ndarray, segment_fraction: np.ndarray,
               gauss: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple | None]:
        """The loads on the track through `points` (k, 2), its segments standing for
        `segment_fraction` of a needle step each (0 across a wound's gap), with the Gauss points
        `gauss` on each segment: uniformly over the covered part (a partly covered segment's
        covered part: P points of its own; the smooth profile: _smooth_cutting). Returns the
        magnitudes (N) on the segments' Gauss points followed by those of the extra load points
        (a partly covered segment's), those points, (t, 2), and their LoadQuadrature.lumping."""
        segments = len(points) - 1
        no_points = np.zeros((0, 2))
        no_lumping = LoadQuadrature.lumping
        if segments < 1:
            return np.zeros(0), no_points, no_lumping
        step_length = self.step_length
        needle_length = step_length * segment_fraction  # needle length each segment stands for
        count, weight = len(gauss), 1.0 / len(gauss)
        friction = np.repeat(weight * self.friction * needle_length, count)
        cutting = self.cutting_force
        if self.on_tip_segment or cutting == 0.0:
            magnitudes = friction.copy()
            magnitudes[-count:] += weight * cutting
            return magnitudes, no_points, no_lumping
        if CUTTING_PROFILE == SMOOTH:
            return (*self._smooth_cutting(points, friction, needle_length, gauss), None)
        full_steps = bool(np.all(segment_fraction == 1.0))
        zone = min(self.cutting_length, segments * step_length if full_steps else float(needle_length.sum()))
        if full_steps:  # whole steps: in step units
            covered = np.clip(zone / step_length - np.arange(segments)[::-1], 0.0, 1.0)  # tip end of each segment
        else:  # a wound: measured in needle length behind the tip
            _, covered = _covered(zone, needle_length)
        # wholly covered segments carry their share on their friction Gauss points (the same
        # points and direction: the forces add); only partly covered ones (the zone's far end)
        # need points and rows of their own
        whole = np.flatnonzero(covered >= 1.0)
        part = np.flatnonzero((covered > 0.0) & (covered < 1.0))
        per_mm = cutting / (self.cutting_length if self.cutting_ramp else zone)
        share = weight * per_mm * needle_length  # N per Gauss point of a wholly covered segment
        magnitudes = friction.copy()
        magnitudes[(count * whole[:, None] + np.arange(count)).ravel()] += np.repeat(share[whole], count)
        if not len(part):
            return magnitudes, no_points, no_lumping
        fraction = covered[part]
        start, end = points[part], points[part + 1]
        along = 1.0 - fraction[:, None] + fraction[:, None] * gauss[None, :]  # (t, P)
        part_points = _along_segments(start, end, along)
        # each point lumped onto the two of its segment's Gauss points around it (the outer
        # two beyond them), by linear interpolation along the segment
        lower = np.clip(np.searchsorted(gauss, along, side="right") - 1, 0, count - 2)  # (t, P)
        upper = ((along - gauss[lower]) / (gauss[lower + 1] - gauss[lower])).ravel()
        first = (count * part[:, None] + lower).ravel()
        lumping = (np.column_stack([first, first + 1]), np.column_stack([1.0 - upper, upper]))
        return np.concatenate([magnitudes, np.repeat(share[part] * fraction, count)]), part_points, lumping

    def _smooth_cutting(self, points: np.ndarray, friction: np.ndarray, needle_length: np.ndarray,
                        gauss: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """layout's magnitudes and extra points for the smooth cutting profile: the force
        cutting_density(s) ds (x cutting_force with the ramp, else scaled to the whole
        force) at Gauss points of the covered part of each segment, s the needle length
        between the point and the tip (a wound's gaps count zero). A wholly covered segment
        uses its P friction Gauss points while SMOOTH_POINTS_PER_LENGTH asks no more; other
        covered segments get points of their own (at least 4 on a partly covered one)."""
        length, cutting = self.cutting_length, self.cutting_force
        no_points = np.zeros((0, 2))
        behind, covered = _covered(min(length, float(needle_length.sum())), needle_length)
        own_count = len(gauss)
        count = np.maximum(np.where(covered >= 1.0, own_count, 4),
                           np.ceil(SMOOTH_POINTS_PER_LENGTH * covered * needle_length / length - 1e-9)).astype(int)
        reuse = np.flatnonzero((covered >= 1.0) & (count == own_count))
        own = np.flatnonzero((covered > 0.0) & ((covered < 1.0) | (count > own_count)))
        # the friction Gauss points: t = gauss, s = behind + (1 - t) x needle length
        on_segments = np.zeros_like(friction)
        s = behind[reuse, None] + (1.0 - gauss[None, :]) * needle_length[reuse, None]
        on_segments[(own_count * reuse[:, None] + np.arange(own_count)).ravel()] = (
            cutting_density(s, length) * (1.0 / own_count) * needle_length[reuse, None]).ravel()
        extra_points, loads = [no_points], [np.zeros(0)]
        for n in np.unique(count[own]):  # a few distinct counts
            segment = own[count[own] == n]
            a, w = gauss_legendre(int(n))  # on [0, 1] of the covered part
            part = covered[segment, None]
            along = 1.0 - part + part * a[None, :]  # (k, n) along the segment toward its tip end
            s = behind[segment, None] + part * (1.0 - a[None, :]) * needle_length[segment, None]
            loads.append((cutting_density(s, length) * part * w[None, :] * needle_length[segment, None]).ravel())
            start, end = points[segment], points[segment + 1]
            extra_points.append(_along_segments(start, end, along))
        extra = np.concatenate(loads)
        total = on_segments.sum() + extra.sum()  # the covered integral of the density, by quadrature
        if total <= 0.0:
            return friction.copy(), no_points
        scale = cutting if self.cutting_ramp else cutting / total
        return np.concatenate([friction + scale * on_segments, scale * extra]), np.vstack(extra_points)
