"""Tissue thinner than its particles resolve: a strip between a hole and the outline or
between two holes, a tongue of tissue between notches, a sliver where a hole cuts the
outline at a shallow angle.

A strip under about half a particle spacing thick holds particles on its two walls only,
and fewer still where the particles of one wall merge into the other's
(shapes.fit_particles); a point near a hole's wall may see (visibility) few of the wall's
own particles. The particles a point inside the strip sees then lie nearly on one line: its RK
moment matrix M(X) is singular, or nearly so and the results far off (the measurements at
THIN_TISSUE). The check looks at the geometry and the graded lattice before any particle is
fitted or shape function built (model.shaped_discretization), so every command that builds
a model refuses such a tissue in one line naming the hole (or the outline), the thickness,
where, the particle spacing there and what to do.

Thickness: from points along every boundary edge, SAMPLES_PER_SPACING per local spacing, a
ray along the edge's inward normal to the first boundary edge it meets; and from every
boundary vertex, the nearest boundary edge other than its own two (two tips facing each
other, a pinch no edge's normal crosses). A hit on the same
boundary loop counts where the way round the boundary between the two points is more than
ROUND_TRIP times their distance and passes no sharp convex corner: across a tongue, not
across the corner of a wedge (near its tip any wedge is thinner than any spacing, yet the
corner's particle and its edges' resolve it). A wedge is judged by its angle instead: a
corner sharper than SHARP_CORNER, or SHARP_CIRCLE_CORNER where a circular hole cuts the
outline (its wall bulges into the sliver and hides the particles on it), is refused at
every spacing.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..config import Tissue
from ..errors import InputError
from ..geometry.boundary import nearest_on_edges
from ..geometry.polygon_domain import PolygonDomain
from ..geometry.polygons import CIRCLE_SEGMENTS, turns
from ..geometry.segments import point_segment_foot

# Tissue thinner than this x the local particle spacing is refused. Measured with the check
# off (deform on a 60 x 30 mm block clamped at the bottom, pulled on its right edge; ratios
# to the lattice's local spacing at the strip; spacings 3, 1.5 and 0.75 mm, the hole at 2 to
# 5 positions along the lattice): a strip under the top edge over a 10 mm wide rectangular
# hole, or between two such holes, failed (a singular moment matrix, or SuperLU's zero pivot)
# somewhere at 0.245 and below (some ran down to 0.07 at 0.75 mm) and ran everywhere from
# 0.27 on, its probes within 0.2-0.8 % of a scikit-fem Q2 reference at 1.5 and 0.75 mm from
# 0.4 on, as with thicker strips (1.5 % at 0.3, 8 % at 0.15 where it ran); a strip over a
# circular hole of radius 1.5, 3 or 6 mm, or between two, failed up to 0.40 and ran in all
# 250 runs between 0.45 and 0.6. Half a spacing leaves a margin of 1.25 to the circles'
# failures and 2 to the straight walls'. (Since a round hole's wall no longer blocks the
# pairs too short to reach across it, shape_functions.Visibility, a strip over one of 1.5, 3
# or 6 mm at spacing 1.5 mm ran at all 5 positions at every ratio from 0.2 to 0.45, where 18
# of those 90 runs failed before, all at 0.3 and below: benchmarks/thin_strips.py. The limit
# stays, for the straight walls' accuracy.)
THIN_TISSUE = 0.5
SAMPLES_PER_SPACING = 4  # ray starts per local spacing along an edge
ROUND_TRIP = 6.0  # a same-loop hit counts where the boundary between is longer than this x the gap
# Corners refused at any spacing. A triangular tissue with a corner of 10 degrees failed at
# 3 mm (its tip covered by 2 particles), 15 degrees and more ran at 3 and 1.5 mm; a circular
# hole cutting the top edge of a block at 11.5 to 35 degrees failed at one or more of 3, 1.5
# and 0.75 mm, at 40 and 45 degrees it ran at all three.
SHARP_CORNER = np.radians(12.5)
SHARP_CIRCLE_CORNER = np.radians(40.0)
WEDGE = np.radians(45.0)  # a corner narrower than this on the way round between two walls: a wedge


@dataclass(frozen=True)
class ThinSpot:
    """Where the tissue is thinnest relative to its spacing: the two wall points across it
    (mm), the thickness (mm) and the local spacing (mm); for a sharp corner (`angle`, rad)
    the corner's vertex as both wall points and thickness 0."""

    start: np.ndarray
    end: np.ndarray
    thickness: float
    spacing: float
    angle: float | None = None

    @property
    def middle(self) -> np.ndarray:
        return 0.5 * (self.start + self.end)


def refuse_thin_tissue(tissue: Tissue, spacing_at: Callable[[np.ndarray], np.ndarray]) -> None:
    """InputError naming the hole (or the outline) that leaves tissue thinner than
    THIN_TISSUE x the particle spacing there (`spacing_at`: points (n, 2) -> (n,)), or a
    corner sharper than the model resolves, with where and what to do."""
    spot = thinnest_spot(tissue, spacing_at)
    if spot is not None:
        raise InputError(thin_tissue_message(tissue, spot))


def thinnest_spot(tissue: Tissue, spacing_at: Callable[[np.ndarray], np.ndarray],
                  limit: float = THIN_TISSUE) -> ThinSpot | None:
    """The sharpest corner below the corner limits, else the spot where the tissue is
    thinnest relative to the local particle spacing among those thinner than `limit` x it;
    None if there is none (a rectangle has none the resource guard lets through)."""
    domain = tissue.domain
    if not isinstance(domain, PolygonDomain):
        return None
    boundary = _Boundary.of(tissue)
    corner = boundary.sharp_corner()
    if corner is not None:
        return ThinSpot(corner[0], corner[0], 0.0, float(spacing_at(corner[0][None])[0]), corner[1])
    points, edge, normal = _samples(domain, spacing_at)
    spacing = spacing_at(points)
    thickness, hit = _first_hits(domain, points, edge, normal, limit * spacing)
    thin = np.flatnonzero(hit >= 0)
    ends = points[thin] + thickness[thin, None] * normal[thin]
    # the gaps from the vertices: two tips facing each other (a pinch between notches or
    # between two holes' corners) leave a neck no edge's normal crosses
    vertices = domain.segment_starts
    vertex_spacing = spacing_at(vertices)
    gap, nearest, foot = _vertex_gaps(domain, boundary, limit * vertex_spacing)
    close = np.flatnonzero(nearest >= 0)
    spots = [(float(thickness[t] / spacing[t]), int(edge[t]), points[t], int(hit[t]), ends[k], float(thickness[t]),
              float(spacing[t])) for k, t in enumerate(thin)]
    spots += [(float(gap[v] / vertex_spacing[v]), int(v), vertices[v], int(nearest[v]), foot[v], float(gap[v]),
               float(vertex_spacing[v])) for v in close]
    for _, wall, start, other, end, width, local in sorted(spots, key=lambda spot: spot[0]):  # thinnest first
        if boundary.across(wall, start, other, end, width):  # past a wedge's few
            return ThinSpot(start, end, width, local)
    return None


def _vertex_gaps(domain: PolygonDomain, boundary: _Boundary,
                 reach: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each boundary vertex (domain.segment_starts), the distance to the nearest boundary
    edge other than its own two within `reach` (n,), that edge (-1: none) and the nearest point
    on it (n, 2)."""
    a, b = domain.segment_starts, domain.segment_ends
    before = boundary.previous(np.arange(len(a)))
    gap = np.full(len(a), np.inf)
    nearest = np.full(len(a), -1)
    foot = a.copy()
    for q, e in domain.candidates(a - reach[:, None], a + reach[:, None]):
        keep = (e != q) & (e != before[q])
        q, e = q[keep], e[keep]
        points = point_segment_foot(a[q], a[e], b[e])
        d = np.linalg.norm(points - a[q], axis=1)
        met = (d > domain.tolerance) & (d <= reach[q])
        q, e, d, points = q[met], e[met], d[met], points[met]
        # a gap through tissue only: across a slit or a wound's gap (the walls' lips facing
        # each other) the way leaves the tissue, which is no neck
        inside = ~domain.blocked(a[q], points)
        q, e, d, points = q[inside], e[inside], d[inside], points[inside]
        order = np.lexsort((d, q))  # by vertex, the nearest first
        q, e, d, points = q[order], e[order], d[order], points[order]
        first = np.concatenate([[True], q[1:] != q[:-1]]) if len(q) else np.zeros(0, dtype=bool)
        q, e, d, points = q[first], e[first], d[first], points[first]
        better = d < gap[q]
        gap[q[better]], nearest[q[better]], foot[q[better]] = d[better], e[better], points[better]
    return gap, nearest, foot


@dataclass(frozen=True)
class _Boundary:
    """Per boundary edge (domain.segment_starts order): its loop, the arc length from its
    loop's first vertex to its start, its length, the turn at its start vertex
    (geometry.polygons.turns, tissue on the left: > 0 convex), whether it lies on a circular hole's
    wall; per loop its perimeter and first edge."""

    domain: PolygonDomain
    loop: np.ndarray
    arc: np.ndarray
    length: np.ndarray
    turn: np.ndarray
    on_circle: np.ndarray
    perimeter: np.ndarray
    first: np.ndarray

    @classmethod
    def of(cls, tissue: Tissue) -> _Boundary:
        domain = tissue.domain
        loops = [domain.outline] + [hole[::-1] for hole in domain.holes]
        sizes = np.array([len(vertices) for vertices in loops])
        loop = np.repeat(np.arange(len(loops)), sizes)
        a, b = domain.segment_starts, domain.segment_ends
        length = np.linalg.norm(b - a, axis=1)
        perimeter = np.bincount(loop, weights=length, minlength=len(loops))
        first = np.cumsum(sizes) - sizes
        arc = np.cumsum(length) - length - np.repeat(np.cumsum(perimeter) - perimeter, sizes)
        on_circle = np.zeros(len(a), dtype=bool)
        for hole in tissue.holes:  # a piece of a circle's 96-gon (cut where it crosses the outline)
            if hole.circle is not None:
                center, radius = np.asarray(hole.circle.center, dtype=float), float(hole.circle.radius)
                tol = 10.0 * domain.tolerance
                sag = radius * (1.0 - np.cos(np.pi / CIRCLE_SEGMENTS)) + tol  # a chord's points lie this far in
                chord = 2.0 * radius * np.sin(np.pi / CIRCLE_SEGMENTS) + tol
                on_circle |= ((np.abs(np.linalg.norm(a - center, axis=1) - radius) <= sag)
                              & (np.abs(np.linalg.norm(b - center, axis=1) - radius) <= sag) & (length <= chord))
        return cls(domain, loop, arc, length, np.concatenate([turns(vertices) for vertices in loops]), on_circle,
                   perimeter, first)

    def previous(self, edge: np.ndarray) -> np.ndarray:
        """The edge before each of `edge` in its loop (the one ending at its start)."""
        sizes = np.bincount(self.loop)
        first = self.first[self.loop[edge]]
        return first + (edge - first - 1) % sizes[self.loop[edge]]

    def sharp_corner(self) -> tuple[np.ndarray, float] | None:
        """The sharpest convex corner below SHARP_CORNER, or SHARP_CIRCLE_CORNER where one of
        its edges lies on a circular hole: (vertex, interior angle in rad), or None."""
        angle = np.pi - self.turn  # interior angle at each edge's start vertex
        circle = self.on_circle | self.on_circle[self.previous(np.arange(len(self.turn)))]
        sharp = np.flatnonzero(angle < np.where(circle, SHARP_CIRCLE_CORNER, SHARP_CORNER))
        if len(sharp) == 0:
            return None
        k = sharp[np.argmin(angle[sharp])]
        return self.domain.segment_starts[k].copy(), float(angle[k])

    def across(self, edge: int, point: np.ndarray, hit: int, end: np.ndarray, gap: float) -> bool:
        """Whether the ray from `point` on `edge` to `end` on `hit` crosses a strip of tissue:
        the two walls on different loops, or on one loop with more than ROUND_TRIP x `gap` of
        boundary between them the short way round and no wedge's corner on it."""
        if self.loop[edge] != self.loop[hit]:
            return True
        a = self.domain.segment_starts
        here = self.arc[edge] + float(np.linalg.norm(point - a[edge]))
        there = self.arc[hit] + min(float(np.linalg.norm(end - a[hit])), float(self.length[hit]))
        perimeter = float(self.perimeter[self.loop[edge]])
        ahead = (there - here) % perimeter  # along the loop's direction
        if min(ahead, perimeter - ahead) <= ROUND_TRIP * gap:
            return False
        return not self._wedge_between(edge, hit, ahead <= 0.5 * perimeter)

    def _wedge_between(self, i: int, j: int, ahead: bool) -> bool:
        """Whether the way round from edge i to edge j (`ahead`: along the loop's direction,
        else from j to i) turns at one convex corner narrower than WEDGE and by less than
        WEDGE elsewhere: the two walls of a wedge, not of a tongue."""
        first = int(self.first[self.loop[i]])
        size = int(np.count_nonzero(self.loop == self.loop[i]))
        p, q = (i - first, j - first) if ahead else (j - first, i - first)
        between = (p + 1 + np.arange((q - p) % size)) % size  # the vertices from edge p's end to edge q's start
        if len(between) == 0:
            return False
        turn = self.turn[first + between]
        tip = int(np.argmax(turn))
        return bool(turn[tip] > np.pi - WEDGE and np.sum(np.abs(turn)) - abs(turn[tip]) < WEDGE)


def _samples(domain: PolygonDomain, spacing_at: Callable[[np.ndarray], np.ndarray]):
    """Points (n, 2) along every boundary edge, SAMPLES_PER_SPACING per local spacing (at
    least one per edge, at the middles of equal pieces), their edge (n,) and inward normal
    (n, 2)."""
    a, b = domain.segment_starts, domain.segment_ends
    length = np.linalg.norm(b - a, axis=1)
    spacing = np.min([spacing_at(a), spacing_at(0.5 * (a + b)), spacing_at(b)], axis=0)  # (E,)
    pieces = np.maximum(np.ceil(SAMPLES_PER_SPACING * length / spacing), 1).astype(int)
    edge = np.repeat(np.arange(len(a)), pieces)
    start = np.cumsum(pieces) - pieces
    fraction = (np.arange(len(edge)) - start[edge] + 0.5) / pieces[edge]
    points = a[edge] + fraction[:, None] * (b - a)[edge]
    direction = (b - a) / length[:, None]
    normal = np.stack([-direction[:, 1], direction[:, 0]], axis=1)  # the tissue lies on each edge's left
    return points, edge, normal[edge]


def _first_hits(domain: PolygonDomain, points: np.ndarray, edge: np.ndarray, normal: np.ndarray,
                reach: np.ndarray, other: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """For rays points + s normal, 0 < s <= reach (n,), from points on the boundary edges
    `edge` (n,; and `other`, for a vertex): the distance to the first other boundary edge
    met (inf: none within reach) and that edge (-1: none)."""
    a, b = domain.segment_starts, domain.segment_ends
    ends = points + reach[:, None] * normal
    distance = np.full(len(points), np.inf)
    hit = np.full(len(points), -1)
    tol = domain.tolerance
    own = edge if other is None else other
    for q, e in domain.candidates(np.minimum(points, ends) - tol, np.maximum(points, ends) + tol):
        d, side, w = normal[q], b[e] - a[e], a[e] - points[q]
        denominator = d[:, 0] * side[:, 1] - d[:, 1] * side[:, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (w[:, 0] * side[:, 1] - w[:, 1] * side[:, 0]) / denominator
            u = (w[:, 0] * d[:, 1] - w[:, 1] * d[:, 0]) / denominator
        met = ((e != edge[q]) & (e != own[q]) & (np.abs(denominator) > 1e-12) & (u >= -1e-9) & (u <= 1 + 1e-9)
               & (s > tol) & (s <= reach[q]))
        q, e, s = q[met], e[met], s[met]
        order = np.lexsort((s, q))  # by point, the nearest first
        q, e, s = q[order], e[order], s[order]
        first = np.concatenate([[True], q[1:] != q[:-1]]) if len(q) else np.zeros(0, dtype=bool)
        q, e, s = q[first], e[first], s[first]
        better = s < distance[q]
        distance[q[better]], hit[q[better]] = s[better], e[better]
    return distance, hit


def wall_thickness(tissue: Tissue, vertices: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """The tissue's thickness beyond boundary vertices (indices into domain.segment_starts):
    along the wall's inward normal there (the mean of its two edges'), the distance to the
    first boundary edge met; inf beyond `reach` (n,)."""
    domain = tissue.domain
    a, b = domain.segment_starts, domain.segment_ends
    before = _Boundary.of(tissue).previous(vertices)
    normal = np.zeros((len(vertices), 2))
    for edges in (vertices, before):
        direction = (b[edges] - a[edges]) / np.linalg.norm(b[edges] - a[edges], axis=1)[:, None]
        normal += np.stack([-direction[:, 1], direction[:, 0]], axis=1)
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    thickness, _ = _first_hits(domain, a[vertices], vertices, normal, np.asarray(reach, dtype=float), before)
    return thickness


DIRECTIONS = 36  # chords through a point, 5 degrees apart


def chord_through(domain: PolygonDomain, point: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The shortest chord of the tissue through `point` (inside or on the boundary) among
    DIRECTIONS directions: its length (mm) and its ends (2,), (2,)."""
    angle = np.pi * np.arange(2 * DIRECTIONS) / DIRECTIONS  # both ways along each direction
    ray = np.stack([np.cos(angle), np.sin(angle)], axis=1)  # (2 D, 2)
    x = np.asarray(point, dtype=float)
    a, b = domain.segment_starts, domain.segment_ends
    side, w = b - a, a - x  # (E, 2)
    denominator = ray[:, None, 0] * side[None, :, 1] - ray[:, None, 1] * side[None, :, 0]  # (2 D, E)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (w[None, :, 0] * side[None, :, 1] - w[None, :, 1] * side[None, :, 0]) / denominator
        u = (w[None, :, 0] * ray[:, None, 1] - w[None, :, 1] * ray[:, None, 0]) / denominator
    step = 1e3 * domain.tolerance
    met = (np.abs(denominator) > 1e-12) & (u >= -1e-9) & (u <= 1 + 1e-9) & (s > step)
    reach = np.where(met, s, np.inf).min(axis=1)  # (2 D,)
    reach[~domain._inside_strict(x + step * ray)] = 0.0  # from a boundary point that way leaves at once
    width = reach[:DIRECTIONS] + reach[DIRECTIONS:]
    width[width == 0.0] = np.inf  # along the boundary through a boundary point: no chord
    k = int(np.argmin(width))
    return float(width[k]), x + reach[k] * ray[k], x + reach[k + DIRECTIONS] * ray[k + DIRECTIONS]


def wall_field(tissue: Tissue, point: np.ndarray) -> str | None:
    """The `holes[k]` whose boundary passes through `point` (a wall of a thin spot), or None
    (the outline's)."""
    tol = 10.0 * tissue.domain.tolerance
    x = np.asarray(point, dtype=float)
    for k, hole in enumerate(tissue.holes):
        a = hole.vertices()
        if nearest_on_edges(a, np.roll(a, -1, axis=0), x)[3] <= tol:
            return f"holes[{k}]"
    return None


def _at(point: np.ndarray) -> str:
    return f"({point[0]:.4g}, {point[1]:.4g}) mm"


def thin_tissue_message(tissue: Tissue, spot: ThinSpot) -> str:
    """One line: the field (the hole, else the outline), what it leaves and where, what was
    expected and what to do."""
    outline = "tissue.outline" if tissue.outline is not None else "tissue.size"
    if spot.angle is not None:
        return _corner_message(tissue, spot, outline)
    walls = [wall_field(tissue, spot.start), wall_field(tissue, spot.end)]
    holes = list(dict.fromkeys(wall for wall in walls if wall is not None))
    if len(holes) == 2:
        field, between, change = f"tissue.{holes[0]}", f"between it and {holes[1]}", "move or shrink either hole"
    elif holes:
        other = "itself" if walls[0] == walls[1] else "the outline"
        field, between, change = f"tissue.{holes[0]}", f"between it and {other}", "move or shrink the hole"
    else:
        field, between, change = outline, "between two of its edges", "widen the tissue there"
    what = "the hole" if holes else "the outline"
    return (f"{field}: {what} leaves tissue {spot.thickness:.3g} mm thin at {_at(spot.middle)} {between}, "
            f"below what the particle spacing there ({spot.spacing:.3g} mm) resolves; expected tissue at least "
            f"{THIN_TISSUE:g} x the local spacing thick: refine the spacing there to "
            f"{spot.thickness / THIN_TISSUE:.3g} mm or less (discretization.spacing, or needle_spacing near the "
            f"needle), or {change}")


def _corner_message(tissue: Tissue, spot: ThinSpot, outline: str) -> str:
    """A corner sharper than the model resolves at any spacing."""
    domain = tissue.domain
    vertex = spot.start
    at = np.flatnonzero(np.linalg.norm(domain.segment_starts - vertex, axis=1) <= domain.tolerance)
    holes = []
    for k in at:  # the corner's two edges: from it, and (its midpoint) the one ending at it
        for edge in (k, int(_Boundary.of(tissue).previous(np.array([k]))[0])):
            middle = 0.5 * (domain.segment_starts[edge] + domain.segment_ends[edge])
            field = wall_field(tissue, middle)
            if field is not None and field not in holes:
                holes.append(field)
    degrees = np.degrees(spot.angle)
    circle = any(tissue.holes[int(field[6:-1])].circle is not None for field in holes)
    limit = np.degrees(SHARP_CIRCLE_CORNER if circle else SHARP_CORNER)
    # a build failure next to a corner above the limit (singular_moment_message): no number
    expected = f"a corner of at least {limit:.3g} degrees" if degrees < limit else "a wider corner"
    if holes:
        return (f"tissue.{holes[0]}: the hole meets the tissue's edge at a corner of {degrees:.3g} degrees at "
                f"{_at(vertex)}, a sliver of tissue that no particle spacing resolves (the spacing there is "
                f"{spot.spacing:.3g} mm); expected {expected}: move or shrink the hole so that it crosses the edge "
                "more steeply or stays clear of it")
    return (f"{outline}: the outline has a corner of {degrees:.3g} degrees at {_at(vertex)}, a sliver of tissue "
            f"that no particle spacing resolves (the spacing there is {spot.spacing:.3g} mm); expected {expected}: "
            "widen it")


def singular_moment_message(tissue: Tissue, discretization, local_spacing: float, error) -> str:
    """The build's line for a singular RK moment matrix (a SingularMomentMatrix `error`, with
    the `point` it was met at where it has one; `local_spacing` there, mm): where the tissue
    through the point is thinner than THIN_TISSUE x the spacing, that (the hole or outline
    that leaves it and what to do: a wider kernel does not help, the particles on the strip's
    two walls stay on one line); else the discretization and the error's own advice."""
    described = (f"discretization: dilation {discretization.dilation:g} with spacing {discretization.spacing:g} mm "
                 f"(basis order {discretization.basis_order}, quadrature order {discretization.quadrature_order}) "
                 f"gives a singular RK moment matrix ({error})")
    point = getattr(error, "point", None)
    if point is None or not isinstance(tissue.domain, PolygonDomain):
        return described
    width, one, other = chord_through(tissue.domain, point)
    if not width < THIN_TISSUE * local_spacing:
        return described
    spot = ThinSpot(one, other, width, local_spacing)
    corner = _wedge_corner(tissue, point, local_spacing)
    if corner is not None:
        spot = ThinSpot(corner[0], corner[0], 0.0, local_spacing, corner[1])
    return f"{thin_tissue_message(tissue, spot)} (the RK moment matrix M(X) is singular at {_at(point)})"


def _wedge_corner(tissue: Tissue, point: np.ndarray, spacing: float) -> tuple[np.ndarray, float] | None:
    """A convex corner narrower than WEDGE within two spacings of `point`: (vertex, interior
    angle), or None. Refining does not resolve the tissue near its tip."""
    boundary = _Boundary.of(tissue)
    angle = np.pi - boundary.turn
    vertices = tissue.domain.segment_starts
    near = np.flatnonzero((angle < WEDGE) & (np.linalg.norm(vertices - point, axis=1) <= 2.0 * spacing))
    if len(near) == 0:
        return None
    k = near[np.argmin(angle[near])]
    return vertices[k].copy(), float(angle[k])

