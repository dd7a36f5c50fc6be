"""Polygons as vertex arrays: area, turns, circles as polygons, the simple-polygon check, cutting an outline."""

from __future__ import annotations

import numpy as np

from .edge_grid import EdgeGrid
from .segments import point_segment_distance, segments_touch


def signed_area(vertices: np.ndarray) -> float:
    """Shoelace area: positive for a counter-clockwise polygon."""
    x, y = vertices[:, 0], vertices[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


CIRCLE_SEGMENTS = 96  # chord error R (1 - cos(pi/96)) = 5.4e-4 R: microns for mm-sized holes


def circle_polygon(center, radius: float, segments: int = CIRCLE_SEGMENTS) -> np.ndarray:
    """A circle as a counter-clockwise regular polygon with vertices on it, (segments, 2)."""
    angles = 2.0 * np.pi * np.arange(segments) / segments
    return np.asarray(center, dtype=float) + radius * np.stack([np.cos(angles), np.sin(angles)], axis=1)


CORNER_TURN = 0.35  # rad (20 deg): a vertex turning more is a corner (a 40-gon's turn 9 deg, a circle's 3.75)


def turns(loop: np.ndarray) -> np.ndarray:
    """Signed turn (rad) of the boundary at each vertex of a closed loop (k, 2): > 0 a left
    turn (a convex corner when the tissue is on the left), 0 straight on."""
    before = loop - np.roll(loop, 1, axis=0)
    after = np.roll(loop, -1, axis=0) - loop
    return np.arctan2(before[:, 0] * after[:, 1] - before[:, 1] * after[:, 0], np.sum(before * after, axis=1))


def is_round(loop: np.ndarray) -> bool:
    """Whether a counter-clockwise polygon (k, 2) is round: convex and without corners, every
    vertex turning left by less than CORNER_TURN (a circle's, an ellipse's, a traced round
    contour's). The visibility criterion weighs the pairs through a round hole by the way
    round it (tissue.shape_functions.Visibility) and blocks those through any other: at a
    corner blocking was measured the closer (benchmarks/results/cornered_holes.md)."""
    turn = turns(loop)
    return bool(np.all(turn >= -1e-9) and np.all(turn < CORNER_TURN))


def round_extent(loop: np.ndarray) -> tuple[np.ndarray, float, float]:
    """A convex polygon's (k, 2) centre (its vertices' mean), the distance from it to the
    farthest vertex and to the nearest edge's line (circumradius and inradius about it)."""
    center = loop.mean(axis=0)
    along = np.roll(loop, -1, axis=0) - loop
    to_center = center - loop
    inradius = np.abs(along[:, 0] * to_center[:, 1] - along[:, 1] * to_center[:, 0]) / np.linalg.norm(along, axis=1)
    return center, float(np.linalg.norm(loop - center, axis=1).max()), float(inradius.min())


def segments_enter_convex(starts: np.ndarray, ends: np.ndarray, loop: np.ndarray, tol: float) -> np.ndarray:
    """Mask (n,) of the segments starts-ends (n, 2) that pass through the interior of the
    convex counter-clockwise polygon `loop` (k, 2) shrunk by `tol` (touching or grazing its
    boundary is not entering): the parameter range inside every edge's half-plane
    (Cyrus-Beck clipping) is not empty."""
    along = np.roll(loop, -1, axis=0) - loop
    outward = np.stack([along[:, 1], -along[:, 0]], axis=1) / np.linalg.norm(along, axis=1)[:, None]
    limit = np.einsum("kd,kd->k", outward, loop) - tol  # n . x <= limit inside
    direction = ends - starts
    room = limit[None, :] - starts @ outward.T  # (n, k): n . (x(t) - start) <= room
    rate = direction @ outward.T
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = room / rate
    low = np.max(np.where(rate < 0.0, bound, 0.0), axis=1, initial=0.0)
    high = np.min(np.where(rate > 0.0, bound, 1.0), axis=1, initial=1.0)
    parallel_outside = np.any((rate == 0.0) & (room < 0.0), axis=1)
    return (low < high) & ~parallel_outside


def polygon_problem(vertices: np.ndarray, tol: float) -> str | None:
    """Why `vertices` (k, 2) is not a simple polygon (None when it is): fewer than three
    vertices, a repeated vertex, no area, or two edges that cross or touch."""
    k = len(vertices)
    if k < 3:
        return "at least three vertices"
    starts, ends = vertices, np.roll(vertices, -1, axis=0)
    short = np.flatnonzero(np.linalg.norm(ends - starts, axis=1) <= tol)
    if len(short) and short[-1] == k - 1:  # the last vertex is the first: a closed ring, as GeoJSON writes it
        return ("a polygon without repeated consecutive vertices (the last vertex repeats the first: the polygon "
                "closes by itself, leave the last one out)")
    if len(short):
        return (f"a polygon without repeated consecutive vertices (vertices {short[0]} and {(short[0] + 1) % k} "
                "coincide: an edge of zero length)")
    # the pairs of edges (i < j) whose boxes, grown by tol, meet: the others cannot touch
    grid = EdgeGrid.of(starts, ends)
    low, high = np.minimum(starts, ends) - 2 * tol, np.maximum(starts, ends) + 2 * tol
    found = [(i, j) for i, j in grid.pairs(low, high) if len(i)]
    i, j = (np.concatenate(parts) for parts in zip(*found)) if found else (np.zeros(0, int),) * 2
    i, j = i[i < j], j[i < j]
    adjacent = (j == i + 1) | ((i == 0) & (j == k - 1))
    touch = segments_touch(starts[i], ends[i], starts[j], ends[j], tol)
    # adjacent edges share their common vertex; they must not fold back onto each other
    forward = (j == i + 1)[:, None]
    other_i = np.where(forward, starts[i], ends[i])
    other_j = np.where(forward, ends[j], starts[j])
    folded = (point_segment_distance(other_i, starts[j], ends[j]) <= tol) | \
        (point_segment_distance(other_j, starts[i], ends[i]) <= tol)
    bad = np.flatnonzero(np.where(adjacent, folded, touch))
    if len(bad):
        first = bad[np.lexsort((j[bad], i[bad]))[0]]  # the first pair in (i, j) order
        a, b = int(i[first]), int(j[first])
        return f"a simple polygon (its edges from vertex {a} and from vertex {b} cross or touch)"
    if abs(signed_area(vertices)) <= tol * tol:
        return "a polygon enclosing an area"
    return None


def cut_outline(outline: np.ndarray, cuts: list[np.ndarray],
                tol: float) -> tuple[np.ndarray | None, str, list[int]]:
    """The outline (k, 2) with the polygons `cuts` (holes that reach or cross it) cut out:
    its vertices counter-clockwise, or None and why the rest is not one simple polygon
    (nothing left, several pieces, a pinch where a cut only touches the outline); and the
    indices of the cuts that hold no tissue (none of their area inside the outline).
    Slivers thinner than `tol` are dropped. Shapely (GEOS) does the polygon difference,
    whose degenerate cases (a cut's edge along the outline's, a vertex on an edge) it
    handles."""
    import shapely

    tissue, pieces = shapely.Polygon(outline), [shapely.Polygon(cut) for cut in cuts]
    idle = [i for i, piece in enumerate(pieces) if tissue.intersection(piece).area <= tol * tol]
    rest = shapely.simplify(tissue.difference(shapely.union_all(pieces)), tol, preserve_topology=True)
    if rest.is_empty or rest.area <= tol * tol:
        return None, "no tissue", idle
    if rest.geom_type != "Polygon":
        return None, f"{len(rest.geoms)} separate pieces of tissue", idle
    if len(rest.interiors):
        return None, "an outline pinched where a cut touches it at a point", idle
    vertices = np.asarray(rest.exterior.coords, dtype=float)[:-1]
    why = polygon_problem(vertices, tol)
    if why:
        return None, f"an outline that is not {why}", idle
    return (vertices if signed_area(vertices) > 0 else vertices[::-1].copy()), "", idle


def around_convex(starts: np.ndarray, ends: np.ndarray, loop: np.ndarray, center: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The shortest way (n,) from each start to its end (n, 2) round the convex
    counter-clockwise polygon `loop` (k, 2) that the straight segment crosses: a tangent from
    the start to the polygon, the boundary between the two tangent points, a tangent to the
    end, on the shorter side; and its gradient (n, 2) with respect to the start, the unit
    vector from the start's tangent point to the start. `center` is a point inside the polygon."""
    perimeter = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.roll(loop, -1, axis=0) - loop, axis=1))])
    total, position = perimeter[-1], perimeter[:-1]

    def angles(origin):  # (n, k): each vertex's angle seen from origin, from the centre's direction
        # the polygon is seen within less than a half-turn holding that direction, so the angles
        # lie in (-pi, pi); sign(sin) (1 - cos) orders them as they are, without arctan2
        toward = center - origin
        toward = toward / np.maximum(np.linalg.norm(toward, axis=1), 1e-300)[:, None]
        to_vertex = loop[None, :, :] - origin[:, None, :]
        cross = toward[:, None, 0] * to_vertex[..., 1] - toward[:, None, 1] * to_vertex[..., 0]
        dot = np.einsum("nd,nkd->nk", toward, to_vertex)
        return np.copysign(1.0 - dot / np.maximum(np.sqrt(np.einsum("nkd,nkd->nk", to_vertex, to_vertex)), 1e-300),
                           cross)

    from_start, from_end = angles(starts), angles(ends)
    best = np.full(len(starts), np.inf)
    gradient = np.zeros_like(starts)
    # the start's counter-clockwise tangent and the end's clockwise one lie on one side, the
    # boundary between them running clockwise from the start's; the other side the reverse
    for start_vertex, end_vertex, clockwise in ((np.argmax(from_start, axis=1), np.argmin(from_end, axis=1), True),
                                                (np.argmin(from_start, axis=1), np.argmax(from_end, axis=1), False)):
        leg_start = starts - loop[start_vertex]
        leg_length = np.linalg.norm(leg_start, axis=1)
        arc = position[start_vertex] - position[end_vertex] if clockwise else position[end_vertex] - position[start_vertex]
        length = leg_length + np.mod(arc, total) + np.linalg.norm(ends - loop[end_vertex], axis=1)
        shorter = length < best
        best[shorter] = length[shorter]
        gradient[shorter] = leg_start[shorter] / np.maximum(leg_length[shorter], 1e-300)[:, None]
    return best, gradient
