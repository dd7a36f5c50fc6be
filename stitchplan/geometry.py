"""The tissue domain in the reference configuration: outline, edges, normals, inside tests,
distances and boundary segments.

Every layer asks the domain these questions instead of comparing coordinates with 0, W
and H itself, so another shape (a polygon, holes) is another domain class with the same
methods, not a change to the numerics. Points are (..., 2) arrays in mm.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

EDGE_NAMES = ("left", "right", "bottom", "top")


def on_segment(points: np.ndarray, start, end, tol: float) -> np.ndarray:
    """Mask of points within `tol` of the straight segment start-end; points (n, 2)."""
    start, end = np.asarray(start, dtype=float), np.asarray(end, dtype=float)
    direction = end - start
    length = float(np.linalg.norm(direction))
    relative = np.asarray(points, dtype=float) - start
    along = relative @ direction / length
    across = np.abs(relative[:, 0] * direction[1] - relative[:, 1] * direction[0]) / length
    return (across <= tol) & (along >= -tol) & (along <= length + tol)


# How far off the boundary a point a person typed or measured (a needle entry, the end of a
# load or clamped segment, a probe) may lie and still mean a boundary point: a micrometre, or
# a millionth of the tissue's size when that is larger. Coordinates written to three decimals
# (mm) lie within 0.71 um of the point meant; points on a slanted edge or a circular hole's
# wall typed to three to six decimals were 2.4e-7 to 1.5e-4 mm off it, and refused. A micrometre is
# also the finest accuracy the tool accepts (discretization.accuracy, the planner's tolerance)
# and a thousandth of a typical particle spacing: moving a point that far onto the boundary
# changes nothing the model resolves. Beyond a metre of tissue, 1e-6 of its size is the
# rounding of coordinates typed to seven significant digits.
INPUT_TOLERANCE_MM = 1e-3
INPUT_TOLERANCE_RELATIVE = 1e-6


class BoundingBox:
    """`size` and `tolerance` of a domain from its bounding box's `width` and `height` (mm)."""

    width: float
    height: float

    @property
    def size(self) -> tuple[float, float]:
        """The bounding box's sides (mm)."""
        return (self.width, self.height)

    @property
    def tolerance(self) -> float:
        """Distance below which a point counts as on the boundary (round-off of the input)."""
        return 1e-9 * max(self.width, self.height)

    @property
    def input_tolerance(self) -> float:
        """Distance within which a point a file gives is moved onto the boundary (snap_to_boundary)."""
        return max(INPUT_TOLERANCE_MM, INPUT_TOLERANCE_RELATIVE * max(self.width, self.height))


@dataclass(frozen=True)
class Rectangle(BoundingBox):
    """The slab [0, W] x [0, H]."""

    width: float
    height: float

    @classmethod
    def of_size(cls, size) -> Rectangle:
        return cls(float(size[0]), float(size[1]))

    def describe(self) -> str:
        return f"{self.width:g} x {self.height:g} mm tissue"

    # --- edges ----------------------------------------------------------------------------

    def edge(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """End points of a named edge."""
        w, h = self.width, self.height
        ends = {"left": ((0.0, 0.0), (0.0, h)), "right": ((w, 0.0), (w, h)),
                "bottom": ((0.0, 0.0), (w, 0.0)), "top": ((0.0, h), (w, h))}[name]
        return np.asarray(ends[0]), np.asarray(ends[1])

    @staticmethod
    def inward_normal(name: str) -> np.ndarray:
        return np.asarray({"left": (1.0, 0.0), "right": (-1.0, 0.0), "bottom": (0.0, 1.0),
                           "top": (0.0, -1.0)}[name])

    def edge_mask(self, points: np.ndarray, name: str, tol: float | None = None) -> np.ndarray:
        """Mask of points (n, 2) on the named edge's line."""
        tol = self.tolerance if tol is None else tol
        coordinate, value = {"left": (0, 0.0), "right": (0, self.width), "bottom": (1, 0.0),
                             "top": (1, self.height)}[name]
        return np.abs(np.asarray(points)[:, coordinate] - value) <= tol

    def edges_at(self, point, tol: float | None = None) -> list[str]:
        """Names of the edges a point lies on (two at a corner, none inside or outside)."""
        tol = self.tolerance if tol is None else tol
        x, y = float(point[0]), float(point[1])
        if not self.contains(np.array([x, y]), tol):
            return []
        hits = (("left", abs(x) <= tol), ("right", abs(x - self.width) <= tol),
                ("bottom", abs(y) <= tol), ("top", abs(y - self.height) <= tol))
        return [name for name, hit in hits if hit]

    def segment_edge(self, start, end, tol: float | None = None) -> str | None:
        """The edge that holds the whole non-empty segment start-end, or None."""
        if np.allclose(start, end, rtol=0.0, atol=0.0):
            return None
        common = set(self.edges_at(start, tol)) & set(self.edges_at(end, tol))
        return sorted(common)[0] if common else None

    # --- inside, outside ------------------------------------------------------------------

    def contains(self, points: np.ndarray, tol: float = 0.0) -> np.ndarray:
        """Mask (...,) of points inside the closed domain, grown by tol."""
        points = np.asarray(points)
        return ((points[..., 0] >= -tol) & (points[..., 0] <= self.width + tol)
                & (points[..., 1] >= -tol) & (points[..., 1] <= self.height + tol))

    def outside_distance(self, point) -> float:
        """Positive outside the domain, negative inside (the largest coordinate excess); its
        zero is the boundary, and it is continuous, so a root finder can locate crossings."""
        x, y = float(point[0]), float(point[1])
        return float(max(-x, x - self.width, -y, y - self.height))

    def clip(self, points: np.ndarray) -> np.ndarray:
        """The nearest domain point of each point (...,2)."""
        return np.clip(points, [0.0, 0.0], [self.width, self.height])

    # --- general shapes ask the same questions ------------------------------------------------

    origin = np.zeros(2)
    holes: tuple = ()
    convex = True

    def boundary_segments(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The four edges, counter-clockwise (tissue on the left)."""
        w, h = self.width, self.height
        corners = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
        return list(zip(corners, np.roll(corners, -1, axis=0)))

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Distance (...,) of points to the boundary."""
        points = np.asarray(points, dtype=float)
        x, y = points[..., 0], points[..., 1]
        inside = np.minimum.reduce([x, self.width - x, y, self.height - y])
        outside = np.hypot(np.maximum.reduce([-x, x - self.width, 0 * x]),
                           np.maximum.reduce([-y, y - self.height, 0 * y]))
        return np.where(inside >= 0, inside, outside)

    def blocked(self, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
        """Convex: no segment between tissue points leaves it."""
        return np.zeros(len(starts), dtype=bool)

    def circle_crossings(self, center, radius: float, start_angle: float, sense: float,
                         max_rotation: float = 2 * math.pi) -> list[tuple[float, str]]:
        """Every crossing of the circle with the boundary within max_rotation, in order."""
        ends = self.boundary_segments()
        return circle_crossings(self, np.array([a for a, _ in ends]), np.array([b for _, b in ends]),
                                np.asarray(center, float), radius, start_angle, sense, max_rotation)

    # --- circles --------------------------------------------------------------------------

    def first_exit_rotation(self, center: np.ndarray, radius: float, start_angle: float,
                            sense: float) -> float | None:
        """Smallest rotation > 0 at which the circle point center + R (cos phi, sin phi),
        phi = start_angle + sense * rotation, crosses the boundary outward; None if never."""
        candidates = []
        for axis, value in ((0, 0.0), (0, self.width), (1, 0.0), (1, self.height)):
            offset = (value - center[axis]) / radius
            if abs(offset) > 1.0:
                continue
            base = math.acos(offset) if axis == 0 else math.asin(offset)
            for phi in ((base, -base) if axis == 0 else (base, math.pi - base)):
                rotation = ((phi - start_angle) * sense) % (2 * math.pi)
                if rotation >= 1e-9:
                    candidates.append(rotation)
        for rotation in sorted(candidates):
            angle = start_angle + sense * (rotation + 1e-7)
            ahead = center + radius * np.array([math.cos(angle), math.sin(angle)])
            if not self.contains(ahead):
                return rotation
        return None


def circle_center_at_entry(domain: Rectangle, entry, radius: float, turn: str) -> tuple[np.ndarray, str]:
    """Centre of a needle of `radius` entering orthogonally at `entry` (tip tangent to the
    inward normal), on the side `turn` (cw/ccw) selects; and the entry edge's name.
    The caller has checked that `entry` lies inside exactly one edge, or on a smooth vertex
    (smooth_vertex), whose inward normal is the mean of its two edges'."""
    names = domain.edges_at(entry)
    edge = names[0]
    inward = sum(domain.inward_normal(name) for name in names)
    inward = inward / float(np.hypot(*inward))
    # centre to the right of the motion for a clockwise turn, to the left for ccw
    side = np.array([inward[1], -inward[0]]) if turn == "cw" else np.array([-inward[1], inward[0]])
    return np.asarray(entry, dtype=float) + radius * side, edge


# --- edges on a grid ---------------------------------------------------------------------------

PAIR_BLOCK = 1 << 16  # (query, edge) pairs per block of a geometry query: work arrays of ~0.5 MB
MAX_GRID_SIDE = 1024  # cells per side of an EdgeGrid
FEW_PAIRS = 1 << 14  # up to here a query tests all (query, edge) pairs (a grid would cost more),
FEW_EDGES = 16  # and with up to this many edges


def concatenated_ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The concatenated ranges starts[i] .. starts[i] + counts[i] - 1."""
    ends = np.cumsum(counts)
    return np.repeat(starts - (ends - counts), counts) + np.arange(ends[-1] if len(ends) else 0)


def _blocks(counts: np.ndarray) -> Iterator[slice]:
    """Consecutive slices of entries whose counts sum to about PAIR_BLOCK (at most that plus
    one entry's count), so that expanding a slice's entries stays within a bounded block."""
    if len(counts) == 0:
        return
    block = (np.cumsum(counts) - counts) // PAIR_BLOCK
    cuts = np.flatnonzero(np.diff(block)) + 1
    for first, last in zip(np.concatenate([[0], cuts]), np.concatenate([cuts, [len(counts)]])):
        yield slice(int(first), int(last))


@dataclass(frozen=True, eq=False)
class EdgeGrid:
    """Straight edges registered on a uniform grid of cells: every edge in each cell its
    bounding box covers, so that a query box meets only the edges of the cells it covers.

    A geometry query (inside, near the boundary, crossing a segment, cutting a cell) then
    costs the edges near each point, not (points x edges): a traced outline of a thousand
    vertices or a few circular holes (CIRCLE_SEGMENTS edges each) stay cheap. The exact test
    of each candidate pair is the same arithmetic as on all pairs, so the answers are."""

    origin: np.ndarray  # (2,) lower left corner of the grid
    cell: np.ndarray  # (2,) sides of a cell (mm)
    shape: tuple[int, int]  # cells along x and y
    first: np.ndarray  # (E, 2) cell (i, j) of each edge's lower left box corner
    indptr: np.ndarray  # (nx ny + 1,) registrations of cell j nx + i: indptr[c] .. indptr[c + 1] - 1
    edge: np.ndarray  # (registrations,) the edge registered
    column: np.ndarray  # (registrations,) the cell column i of the registration

    @classmethod
    def of(cls, starts: np.ndarray, ends: np.ndarray, bands: bool = False) -> EdgeGrid:
        """The grid over the edges' bounding box: square cells, about one per edge (at most
        MAX_GRID_SIDE per side); with `bands`, one column of about one row per edge (a ray
        along x then meets the edges of one thin band)."""
        low, high = np.minimum(starts, ends), np.maximum(starts, ends)  # (E, 2) edge boxes
        origin = low.min(axis=0)
        extent = high.max(axis=0) - origin
        if bands:
            shape = (1, int(np.clip(len(starts), 1, MAX_GRID_SIDE)))
        else:
            side = max(math.sqrt(float(extent[0] * extent[1]) / len(starts)), float(extent.max()) / MAX_GRID_SIDE)
            shape = tuple(int(n) for n in np.clip(np.ceil(extent / side), 1, MAX_GRID_SIDE)) if side > 0 else (1, 1)
        cell = np.where(extent > 0, extent / np.array(shape), 1.0)
        grid = cls(origin, cell, shape, np.zeros((0, 2), int), np.zeros(1, int), np.zeros(0, int), np.zeros(0, int))
        first, last = grid.cells_of(low), grid.cells_of(high)  # (E, 2)
        width = last[:, 0] - first[:, 0] + 1
        count = width * (last[:, 1] - first[:, 1] + 1)
        edge = np.repeat(np.arange(len(starts)), count)
        local = concatenated_ranges(np.zeros(len(starts), int), count)
        column = first[edge, 0] + local % width[edge]
        row = first[edge, 1] + local // width[edge]
        key = row * shape[0] + column
        order = np.argsort(key, kind="stable")
        indptr = np.concatenate([[0], np.cumsum(np.bincount(key, minlength=shape[0] * shape[1]))])
        return cls(origin, cell, shape, first, indptr, edge[order], column[order])

    def cells_of(self, points: np.ndarray) -> np.ndarray:
        """Cell (i, j) (n, 2) holding each point, clipped to the grid (monotone in x and y, so
        boxes that meet cover cells that meet)."""
        with np.errstate(invalid="ignore"):
            scaled = np.nan_to_num((np.asarray(points, dtype=float) - self.origin) / self.cell,
                                   nan=0.0, posinf=MAX_GRID_SIDE + 1.0, neginf=-1.0)
        index = np.floor(np.clip(scaled, -1.0, MAX_GRID_SIDE + 1.0)).astype(int)
        return np.clip(index, 0, np.array(self.shape) - 1)

    def pairs(self, low: np.ndarray, high: np.ndarray) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Blocks (query index, edge index) of the query boxes (n, 2 lower and upper corners)
        with every edge registered in a cell the box covers, each pair once (in the first
        cell of both: a superset of the edges whose boxes meet the query's); about
        PAIR_BLOCK pairs per block."""
        first, last = self.cells_of(low), self.cells_of(high)
        rows = last[:, 1] - first[:, 1] + 1
        nx = self.shape[0]
        for part in _blocks(rows):  # entries (query, row): the registrations of its cells in that row
            queries = np.arange(len(low))[part]
            query = np.repeat(queries, rows[part])
            row = concatenated_ranges(first[queries, 1], rows[part])
            begin = self.indptr[row * nx + first[query, 0]]
            count = self.indptr[row * nx + last[query, 0] + 1] - begin
            for block in _blocks(count):
                entry = np.repeat(np.arange(block.start, block.stop), count[block])
                registration = concatenated_ranges(begin[block], count[block])
                q, e = query[entry], self.edge[registration]
                once = ((self.column[registration] == np.maximum(first[q, 0], self.first[e, 0]))
                        & (row[entry] == np.maximum(first[q, 1], self.first[e, 1])))
                yield q[once], e[once]


# --- polygons ---------------------------------------------------------------------------------

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


def smooth_vertex(domain, point) -> bool:
    """Whether `point` is a boundary vertex where the boundary turns by at most CORNER_TURN
    (a traced contour's vertex, which the model treats as a point inside an edge)."""
    names = domain.edges_at(point)
    if len(names) != 2:
        return False
    (a0, a1), (b0, b1) = (domain.edge(name) for name in names)
    d, e = a1 - a0, b1 - b0
    return abs(math.atan2(float(_cross(d, e)), float(np.dot(d, e)))) <= CORNER_TURN


def boundary_edges(domain) -> tuple[np.ndarray, np.ndarray]:
    """Starts and ends (k, 2) of every directed boundary edge of a domain."""
    segments = domain.boundary_segments()
    return (np.array([start for start, _ in segments], dtype=float),
            np.array([end for _, end in segments], dtype=float))


def nearest_on_edges(starts: np.ndarray, ends: np.ndarray, point) -> tuple[int, float, np.ndarray, float]:
    """The point of the segments starts -> ends (k, 2) nearest `point` (2,): its segment,
    the fraction along it, the point, and how far it is (mm)."""
    x = np.asarray(point, dtype=float)
    e = ends - starts  # (k, 2)
    along = np.clip(np.sum((x - starts) * e, axis=1) / np.sum(e * e, axis=1), 0.0, 1.0)
    candidates = starts + along[:, None] * e
    distances = np.linalg.norm(candidates - x, axis=1)
    k = int(np.argmin(distances))
    return k, float(along[k]), candidates[k], float(distances[k])


def nearest_boundary_point(domain, point) -> tuple[np.ndarray, float]:
    """The boundary point nearest `point` (2,), and how far it is (mm)."""
    _, _, nearest, distance = nearest_on_edges(*boundary_edges(domain), point)
    return nearest, distance


def snap_to_boundary(domain, point) -> np.ndarray | None:
    """The boundary point that a typed or measured `point` (2,) means, or None when it lies
    more than domain.input_tolerance off the boundary. A boundary vertex within that tolerance
    is the point (a point typed next to a corner is the corner, refused as one wherever a
    corner is); else the point itself when it lies on the boundary to round-off
    (domain.tolerance: a file's exact points are kept to the bit); else the nearest boundary
    point."""
    x = np.asarray(point, dtype=float)
    starts, _ = boundary_edges(domain)
    gaps = np.linalg.norm(starts - x, axis=1)
    k = int(np.argmin(gaps))
    if gaps[k] <= domain.input_tolerance:
        return x.copy() if gaps[k] <= domain.tolerance else starts[k].copy()
    nearest, distance = nearest_boundary_point(domain, x)
    if distance <= domain.tolerance:
        return x.copy()
    return nearest if distance <= domain.input_tolerance else None


def signed_area(vertices: np.ndarray) -> float:
    """Shoelace area: positive for a counter-clockwise polygon."""
    x, y = vertices[:, 0], vertices[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def segments_cross(p: np.ndarray, q: np.ndarray, a: np.ndarray, b: np.ndarray, tol: float) -> np.ndarray:
    """Mask of segment pairs p-q and a-b (broadcasting (..., 2) arrays) that cross properly:
    each segment's ends lie strictly (beyond `tol` mm) on opposite sides of the other's line.
    Touching at an end, running along each other or meeting at a vertex is not a crossing."""
    d, e = q - p, b - a
    length_d = np.maximum(np.linalg.norm(d, axis=-1), 1e-300)
    length_e = np.maximum(np.linalg.norm(e, axis=-1), 1e-300)
    o1, o2 = _cross(d, a - p) / length_d, _cross(d, b - p) / length_d  # a, b seen from p-q
    o3, o4 = _cross(e, p - a) / length_e, _cross(e, q - a) / length_e  # p, q seen from a-b
    return (((o1 > tol) & (o2 < -tol)) | ((o1 < -tol) & (o2 > tol))) & \
        (((o3 > tol) & (o4 < -tol)) | ((o3 < -tol) & (o4 > tol)))


def segments_touch(p, q, a, b, tol: float) -> np.ndarray:
    """Mask of segment pairs that come within `tol` of each other (crossing, touching,
    overlapping)."""
    p, q, a, b = (np.asarray(v, dtype=float) for v in (p, q, a, b))
    close = np.minimum.reduce([_point_segment_distance(p, a, b), _point_segment_distance(q, a, b),
                               _point_segment_distance(a, p, q), _point_segment_distance(b, p, q)])
    return (close <= tol) | segments_cross(p, q, a, b, 0.0)


def _point_segment_distance(x: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    e = b - a
    t = np.clip(np.sum((x - a) * e, axis=-1) / np.maximum(np.sum(e * e, axis=-1), 1e-300), 0.0, 1.0)
    return np.linalg.norm(x - (a + t[..., None] * e), axis=-1)


def polygon_problem(vertices: np.ndarray, tol: float) -> str | None:
    """Why `vertices` (k, 2) is not a simple polygon (None when it is): fewer than three
    vertices, a repeated vertex, no area, or two edges that cross or touch."""
    k = len(vertices)
    if k < 3:
        return "at least three vertices"
    starts, ends = vertices, np.roll(vertices, -1, axis=0)
    if np.any(np.linalg.norm(ends - starts, axis=1) <= tol):
        return "a polygon without repeated consecutive vertices (an edge has zero length)"
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
    folded = (_point_segment_distance(other_i, starts[j], ends[j]) <= tol) | \
        (_point_segment_distance(other_j, starts[i], ends[i]) <= tol)
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


@dataclass(frozen=True, eq=False)
class PolygonDomain(BoundingBox):
    """A simple polygon (counter-clockwise) with polygonal holes, in mm.

    Boundary pieces are named `outline[i]` (the edge from vertex i to i + 1) and
    `holes[j][i]`; every directed boundary edge has the tissue on its left (holes are walked
    clockwise), so the inward normal is the edge direction turned left. Circles are held as
    their inscribed polygons (CIRCLE_SEGMENTS edges).
    """

    outline: np.ndarray  # (k, 2) counter-clockwise
    holes: tuple = ()  # (m, 2) arrays, counter-clockwise (as drawn)
    edge_names: tuple = ()  # names of the outline edges when they have some (a rectangle's)

    @classmethod
    def rectangle(cls, size, holes=()) -> PolygonDomain:
        """The slab [0, W] x [0, H] with holes; its edges keep their names."""
        w, h = float(size[0]), float(size[1])
        return cls(np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]]), tuple(holes),
                   ("bottom", "right", "top", "left"))

    def __post_init__(self):
        loops = [self.outline] + [hole[::-1] for hole in self.holes]  # tissue on the left
        names, starts, ends = [], [], []
        for j, loop in enumerate(loops):
            count = len(loop)
            for i in range(count):  # reversed hole: walked edge i is the hole's edge m - 2 - i
                if j == 0:
                    names.append(self.edge_names[i] if self.edge_names else f"outline[{i}]")
                else:
                    names.append(f"holes[{j - 1}][{(count - 2 - i) % count}]")
            starts.append(loop)
            ends.append(np.roll(loop, -1, axis=0))
        object.__setattr__(self, "segment_names", tuple(names))
        object.__setattr__(self, "segment_starts", np.concatenate(starts))
        object.__setattr__(self, "segment_ends", np.concatenate(ends))
        low, high = self.outline.min(axis=0), self.outline.max(axis=0)
        # a side of the bounding box that holds exactly one outline edge answers to its name
        # (the outline's right edge is `right`), as a rectangle's edges do
        aliases = {}
        if not self.edge_names:
            tol = 1e-9 * float(np.max(high - low))
            starts, ends = self.outline, np.roll(self.outline, -1, axis=0)
            for name, axis, value in (("left", 0, low[0]), ("right", 0, high[0]), ("bottom", 1, low[1]),
                                      ("top", 1, high[1])):
                on = np.flatnonzero((np.abs(starts[:, axis] - value) <= tol) & (np.abs(ends[:, axis] - value) <= tol))
                if len(on) == 1:
                    aliases[name] = int(on[0])
        object.__setattr__(self, "aliases", aliases)
        object.__setattr__(self, "origin", low)
        object.__setattr__(self, "width", float(high[0] - low[0]))
        object.__setattr__(self, "height", float(high[1] - low[1]))

    @property
    def convex(self) -> bool:
        """No holes and no reflex vertex: every segment between tissue points stays inside."""
        if self.holes:
            return False
        d = np.roll(self.outline, -1, axis=0) - self.outline
        return bool(np.all(_cross(d, np.roll(d, -1, axis=0)) >= -self.tolerance**2))

    def describe(self) -> str:
        holes = f" with {len(self.holes)} hole{'s' if len(self.holes) != 1 else ''}" if self.holes else ""
        return f"polygon tissue ({len(self.outline)} vertices{holes})"

    def boundary_segments(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Every directed boundary edge (tissue on its left)."""
        return list(zip(self.segment_starts, self.segment_ends))

    # --- edges ----------------------------------------------------------------------------

    def _index(self, name: str) -> int:
        if name in self.aliases:
            return self.aliases[name]
        try:
            return self.segment_names.index(name)
        except ValueError:
            raise KeyError(name) from None

    def edge(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        k = self._index(name)
        return self.segment_starts[k].copy(), self.segment_ends[k].copy()

    def inward_normal(self, name: str) -> np.ndarray:
        k = self._index(name)
        d = self.segment_ends[k] - self.segment_starts[k]
        return np.array([-d[1], d[0]]) / float(np.hypot(*d))

    def edge_mask(self, points: np.ndarray, name: str, tol: float | None = None) -> np.ndarray:
        tol = self.tolerance if tol is None else tol
        return on_segment(np.asarray(points, dtype=float), *self.edge(name), tol)

    def edges_at(self, point, tol: float | None = None) -> list[str]:
        """Names of the boundary edges holding the point (two at a vertex)."""
        tol = self.tolerance if tol is None else tol
        x = np.asarray(point, dtype=float)
        d = _point_segment_distance(x[None], self.segment_starts, self.segment_ends)
        return [self.segment_names[k] for k in np.flatnonzero(d <= tol)]

    def segment_edge(self, start, end, tol: float | None = None) -> str | None:
        """The boundary edge holding the whole non-empty segment start-end, or None."""
        if np.allclose(start, end, rtol=0.0, atol=0.0):
            return None
        common = set(self.edges_at(start, tol)) & set(self.edges_at(end, tol))
        return sorted(common)[0] if common else None

    # --- inside, outside ------------------------------------------------------------------

    @functools.cached_property
    def grid(self) -> EdgeGrid:
        """The boundary edges on a grid of square cells (built on first use): the geometry
        queries look only at the edges near each point."""
        return EdgeGrid.of(self.segment_starts, self.segment_ends)

    @functools.cached_property
    def bands(self) -> EdgeGrid:
        """The boundary edges on thin bands along x (built on first use): the inside test's
        ray meets the edges of one band."""
        return EdgeGrid.of(self.segment_starts, self.segment_ends, bands=True)

    def candidates(self, low: np.ndarray, high: np.ndarray,
                   bands: bool = False) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Blocks (query index, edge index) holding every pair of a query box (n, 2 lower and
        upper corners) and a boundary edge whose box meets it, each pair once: all pairs when
        there are few or the edges are (a small domain's queries need no grid), else the
        grid's (`bands`: the bands')."""
        count = len(self.segment_starts)
        if count > FEW_EDGES and len(low) * count > FEW_PAIRS:
            yield from (self.bands if bands else self.grid).pairs(low, high)
            return
        rows = max(PAIR_BLOCK // count, 1)
        for first in range(0, len(low), rows):  # (rows x edges) blocks
            n = min(rows, len(low) - first)
            yield np.repeat(np.arange(first, first + n), count), np.tile(np.arange(count), n)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Distance (...,) of points to the boundary."""
        points = np.asarray(points, dtype=float)
        flat = points.reshape(-1, 2)
        out = np.empty(len(flat))
        rows = max(PAIR_BLOCK // len(self.segment_starts), 1)
        for chunk in range(0, len(flat), rows):  # (rows x edges) work arrays
            part = flat[chunk:chunk + rows, None, :]
            out[chunk:chunk + rows] = _point_segment_distance(part, self.segment_starts[None],
                                                              self.segment_ends[None]).min(axis=1)
        return out.reshape(points.shape[:-1])

    def near_boundary(self, flat: np.ndarray, tol: float) -> np.ndarray:
        """Mask (n,) of points (n, 2) within tol of the boundary (distance(flat) <= tol, from
        the edges near each point only)."""
        near = np.zeros(len(flat), dtype=bool)
        pad = 2.0 * tol + self.tolerance  # the boxes of the edges within tol meet the point's
        for q, e in self.candidates(flat - pad, flat + pad):
            close = _point_segment_distance(flat[q], self.segment_starts[e], self.segment_ends[e]) <= tol
            near[q[close]] = True
        return near

    def _inside_strict(self, flat: np.ndarray) -> np.ndarray:
        """Even-odd crossing test of points (n, 2) over every boundary loop: the edges that
        straddle a point's y to the right of it (from the edges of the point's band)."""
        flat = np.asarray(flat, dtype=float).reshape(-1, 2)
        crossings = np.zeros(len(flat), dtype=np.int64)
        a, b = self.segment_starts, self.segment_ends
        pad = self.tolerance  # round-off of the crossing's x beyond the edge's box
        right = np.column_stack([np.full(len(flat), np.inf), flat[:, 1]])
        for q, e in self.candidates(flat - [pad, 0.0], right, bands=True):
            x, y = flat[q, 0], flat[q, 1]
            straddle = (a[e, 1] > y) != (b[e, 1] > y)
            with np.errstate(divide="ignore", invalid="ignore"):
                x_cross = a[e, 0] + (y - a[e, 1]) * (b[e, 0] - a[e, 0]) / (b[e, 1] - a[e, 1])
            crossed = q[straddle & (x < x_cross)]
            if len(crossed):  # a block holds a range of points: count over that range only
                first = int(crossed.min())
                count = np.bincount(crossed - first)
                crossings[first:first + len(count)] += count
        return (crossings % 2) == 1

    def contains(self, points: np.ndarray, tol: float = 0.0) -> np.ndarray:
        """Mask (...,) of points inside the closed domain, grown by tol (at least round-off)."""
        points = np.asarray(points, dtype=float)
        flat = points.reshape(-1, 2)
        result = self._inside_strict(flat) | self.near_boundary(flat, max(tol, self.tolerance))
        return result.reshape(points.shape[:-1])

    def outside_distance(self, point) -> float:
        """Signed distance to the boundary: positive outside, negative inside."""
        x = np.asarray(point, dtype=float).reshape(1, 2)
        d = float(self.distance(x)[0])
        return -d if self._inside_strict(x)[0] else d

    def clip(self, points: np.ndarray) -> np.ndarray:
        """The nearest domain point of each point (..., 2): itself inside, the nearest boundary
        point outside."""
        points = np.asarray(points, dtype=float)
        flat = points.reshape(-1, 2).copy()
        out = ~self.contains(flat)
        if np.any(out):
            x = flat[out][:, None, :]
            a, b = self.segment_starts[None], self.segment_ends[None]
            e = b - a
            t = np.clip(np.sum((x - a) * e, axis=-1) / np.sum(e * e, axis=-1), 0.0, 1.0)
            nearest = a + t[..., None] * e
            k = np.argmin(np.linalg.norm(x - nearest, axis=-1), axis=1)
            flat[out] = nearest[np.arange(len(k)), k]
        return flat.reshape(points.shape)

    # --- visibility -----------------------------------------------------------------------

    def blocked(self, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
        """Mask (n,) of the straight segments starts-ends (n, 2) that cross the boundary
        (leave the tissue through an edge): the visibility criterion of the shape functions."""
        starts, ends = np.asarray(starts, dtype=float), np.asarray(ends, dtype=float)
        hit = np.zeros(len(starts), dtype=bool)
        tol = 1e-7 * max(self.width, self.height)
        low, high = np.minimum(starts, ends), np.maximum(starts, ends)
        a, b = self.segment_starts, self.segment_ends
        edge_low, edge_high = np.minimum(a, b), np.maximum(a, b)
        for pair, edge in self.candidates(low - self.tolerance, high + self.tolerance):
            near = ((high[pair, 0] >= edge_low[edge, 0]) & (low[pair, 0] <= edge_high[edge, 0])
                    & (high[pair, 1] >= edge_low[edge, 1]) & (low[pair, 1] <= edge_high[edge, 1]))
            pair, edge = pair[near], edge[near]  # the segments' exact test only where the boxes meet
            crossed = segments_cross(starts[pair], ends[pair], a[edge], b[edge], tol)
            hit[pair[crossed]] = True
        # a segment between two boundary points crossing a gap touches the boundary only at
        # its ends: its middle lies outside
        rest = np.flatnonzero(~hit)
        if len(rest):
            middle = 0.5 * (starts[rest] + ends[rest])
            outside = rest[~self._inside_strict(middle)]  # the distance only for those (few)
            hit[outside] = ~self.near_boundary(0.5 * (starts[outside] + ends[outside]), tol)
        return hit

    # --- circles --------------------------------------------------------------------------

    def circle_crossings(self, center, radius: float, start_angle: float, sense: float,
                         max_rotation: float = 2 * math.pi) -> list[tuple[float, str]]:
        """Every crossing of the circle point center + R (cos phi, sin phi),
        phi = start_angle + sense * rotation, with the boundary for 0 < rotation <= max_rotation,
        in order: (rotation, 'entry' or 'exit')."""
        return circle_crossings(self, self.segment_starts, self.segment_ends, np.asarray(center, float),
                                radius, start_angle, sense, max_rotation)

    def first_exit_rotation(self, center: np.ndarray, radius: float, start_angle: float,
                            sense: float) -> float | None:
        for rotation, kind in self.circle_crossings(center, radius, start_angle, sense):
            if kind == "exit":
                return rotation
        return None


def circle_crossings(domain, starts: np.ndarray, ends: np.ndarray, center: np.ndarray, radius: float,
                     start_angle: float, sense: float, max_rotation: float) -> list[tuple[float, str]]:
    """Crossings of a circle with boundary edges (starts, ends (ns, 2)): the rotations where
    the circle meets an edge, kept where the point's inside/outside state changes."""
    d = ends - starts
    f = starts - center
    a = np.sum(d * d, axis=1)
    b = 2.0 * np.sum(f * d, axis=1)
    c = np.sum(f * f, axis=1) - radius**2
    disc = b * b - 4 * a * c
    ok = disc >= 0.0
    root = np.sqrt(np.where(ok, disc, 0.0))
    ts = np.concatenate([(-b - root) / (2 * a), (-b + root) / (2 * a)])
    valid = np.concatenate([ok, ok]) & (ts >= -1e-12) & (ts <= 1 + 1e-12)
    points = np.concatenate([starts, starts])[valid] + ts[valid, None] * np.concatenate([d, d])[valid]
    phi = np.arctan2(points[:, 1] - center[1], points[:, 0] - center[0])
    rotations = np.sort(np.mod((phi - start_angle) * sense, 2 * math.pi))
    rotations = rotations[(rotations >= 1e-9) & (rotations <= max_rotation + 1e-9)]
    if len(rotations):
        rotations = rotations[np.concatenate([[True], np.diff(rotations) > 1e-9])]
    result = []
    eps = 1e-7
    for rotation in rotations:
        before, after = (start_angle + sense * (rotation + s * eps) for s in (-1.0, 1.0))
        pts = center + radius * np.array([[math.cos(before), math.sin(before)],
                                          [math.cos(after), math.sin(after)]])
        inside = domain.contains(pts, tol=0.0) if not isinstance(domain, PolygonDomain) else \
            domain._inside_strict(pts)
        if inside[0] and not inside[1]:
            result.append((float(rotation), "exit"))
        elif inside[1] and not inside[0]:
            result.append((float(rotation), "entry"))
    return result
