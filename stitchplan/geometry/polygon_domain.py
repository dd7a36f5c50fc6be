"""PolygonDomain: a polygon tissue with holes; and a circle's crossings with a domain's boundary."""

from __future__ import annotations

import functools
import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from .bounding_box import BoundingBox
from .edge_grid import FEW_EDGES, FEW_PAIRS, PAIR_BLOCK, EdgeGrid
from .segments import cross_2d, on_segment, point_segment_distance, point_segment_foot, segments_cross


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
        names, starts, ends, following = [], [], [], []
        for j, loop in enumerate(loops):
            count, first = len(loop), len(names)
            for i in range(count):  # reversed hole: walked edge i is the hole's edge m - 2 - i
                if j == 0:
                    names.append(self.edge_names[i] if self.edge_names else f"outline[{i}]")
                else:
                    names.append(f"holes[{j - 1}][{(count - 2 - i) % count}]")
            starts.append(loop)
            ends.append(np.roll(loop, -1, axis=0))
            following.append(first + (np.arange(count) + 1) % count)
        object.__setattr__(self, "segment_names", tuple(names))
        object.__setattr__(self, "segment_starts", np.concatenate(starts))
        object.__setattr__(self, "segment_ends", np.concatenate(ends))
        object.__setattr__(self, "next_edge", np.concatenate(following))  # (edges,) the edge after each in its loop
        low, high = self.outline.min(axis=0), self.outline.max(axis=0)
        # a side of the bounding box that holds one straight piece of the outline (one edge, or
        # consecutive ones: a vertex on a straight side) answers to its name (the outline's right
        # edge is `right`), as a rectangle's edges do; side_pieces keeps what each side holds
        aliases, side_pieces = {}, {}
        if not self.edge_names:
            tol = 1e-9 * float(np.max(high - low))
            starts, ends = self.outline, np.roll(self.outline, -1, axis=0)
            for name, axis, value in (("left", 0, low[0]), ("right", 0, high[0]), ("bottom", 1, low[1]),
                                      ("top", 1, high[1])):
                on = np.flatnonzero((np.abs(starts[:, axis] - value) <= tol) & (np.abs(ends[:, axis] - value) <= tol))
                side_pieces[name] = _runs(on.tolist(), len(self.outline))
                if len(side_pieces[name]) == 1:
                    aliases[name] = side_pieces[name][0]
        object.__setattr__(self, "aliases", aliases)  # name -> the outline edges it names, in walking order
        object.__setattr__(self, "side_pieces", side_pieces)
        object.__setattr__(self, "origin", low)
        object.__setattr__(self, "width", float(high[0] - low[0]))
        object.__setattr__(self, "height", float(high[1] - low[1]))

    @property
    def convex(self) -> bool:
        """No holes and no reflex vertex: every segment between tissue points stays inside."""
        if self.holes:
            return False
        d = np.roll(self.outline, -1, axis=0) - self.outline
        return bool(np.all(cross_2d(d, np.roll(d, -1, axis=0)) >= -self.tolerance**2))

    def describe(self) -> str:
        holes = f" with {len(self.holes)} hole{'s' if len(self.holes) != 1 else ''}" if self.holes else ""
        return f"polygon tissue ({len(self.outline)} vertices{holes})"

    def boundary_segments(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Every directed boundary edge (tissue on its left)."""
        return list(zip(self.segment_starts, self.segment_ends))

    # --- edges ----------------------------------------------------------------------------

    def _indices(self, name: str) -> tuple[int, ...]:
        """The edges a name stands for: one, or a side's straight run of them (aliases)."""
        if name in self.aliases:
            return self.aliases[name]
        try:
            return (self.segment_names.index(name),)
        except ValueError:
            raise KeyError(name) from None

    def _index(self, name: str) -> int:
        return self._indices(name)[0]

    def edge(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """Ends of the named edge (of a side's straight run of edges: its first start, last end)."""
        run = self._indices(name)
        return self.segment_starts[run[0]].copy(), self.segment_ends[run[-1]].copy()

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
        d = point_segment_distance(x[None], self.segment_starts, self.segment_ends)
        return [self.segment_names[k] for k in np.flatnonzero(d <= tol)]

    def segment_edge(self, start, end, tol: float | None = None) -> str | None:
        """The boundary edge holding the whole non-empty segment start-end (for a segment along
        consecutive edges on one straight line, straight_run's, the one at `start`), or None."""
        if np.allclose(start, end, rtol=0.0, atol=0.0):
            return None
        common = set(self.edges_at(start, tol)) & set(self.edges_at(end, tol))
        if common:
            return sorted(common)[0]
        at_end = set(self._edges_holding(end, tol))
        for k in self._edges_holding(start, tol):
            if at_end & set(self.straight_run(k, tol)):
                return self.segment_names[k]
        return None

    def straight_run(self, k: int, tol: float | None = None) -> list[int]:
        """Edge k and the consecutive edges before and after it in its loop that lie on its
        line to round-off (tol: the domain's; a vertex on a straight side turns by none, while
        a traced contour's turn, which an entry takes as no corner, bends a load's line), in
        walking order."""
        tol = self.tolerance if tol is None else tol
        a, b = self.segment_starts[k], self.segment_ends[k]
        direction = (b - a) / float(np.hypot(*(b - a)))

        def on_line(j: int) -> bool:
            ends = np.stack([self.segment_starts[j], self.segment_ends[j]]) - a  # (2, 2)
            return bool(np.all(np.abs(cross_2d(ends, direction)) <= tol))

        before = {int(j): i for i, j in enumerate(self.next_edge)}  # the edge before each
        run = [k]
        while (j := int(self.next_edge[run[-1]])) != k and on_line(j):
            run.append(j)
        while (j := before[run[0]]) not in run and on_line(j):
            run.insert(0, j)
        return run

    def nearest_boundary_point(self, point) -> tuple[np.ndarray, bool]:
        """The boundary point nearest `point`, and whether its edge is the outline's (not a hole's)."""
        x = np.asarray(point, dtype=float)
        nearest = point_segment_foot(x[None], self.segment_starts, self.segment_ends)  # (edges, 2)
        k = int(np.argmin(np.linalg.norm(nearest - x, axis=1)))
        return nearest[k], k < len(self.outline)

    def _edges_holding(self, point, tol: float | None = None) -> list[int]:
        tol = self.tolerance if tol is None else tol
        x = np.asarray(point, dtype=float)
        return np.flatnonzero(point_segment_distance(x[None], self.segment_starts, self.segment_ends) <= tol).tolist()

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
            out[chunk:chunk + rows] = point_segment_distance(part, self.segment_starts[None],
                                                             self.segment_ends[None]).min(axis=1)
        return out.reshape(points.shape[:-1])

    def near_boundary(self, flat: np.ndarray, tol: float) -> np.ndarray:
        """Mask (n,) of points (n, 2) within tol of the boundary (distance(flat) <= tol, from
        the edges near each point only)."""
        near = np.zeros(len(flat), dtype=bool)
        pad = 2.0 * tol + self.tolerance  # the boxes of the edges within tol meet the point's
        for q, e in self.candidates(flat - pad, flat + pad):
            close = point_segment_distance(flat[q], self.segment_starts[e], self.segment_ends[e]) <= tol
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
            nearest = point_segment_foot(x, self.segment_starts[None], self.segment_ends[None])  # (n, edges, 2)
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


def _runs(indices: list[int], count: int) -> list[tuple[int, ...]]:
    """The sorted edge `indices` of a loop of `count` edges as runs of consecutive ones (the
    loop's last edge followed by its first), each in walking order."""
    chosen = set(indices)
    firsts = [i for i in indices if (i - 1) % count not in chosen]
    runs = []
    for first in firsts:
        run = [first]
        while (following := (run[-1] + 1) % count) in chosen and following != first:
            run.append(following)
        runs.append(tuple(run))
    return runs


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
