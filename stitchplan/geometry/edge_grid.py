"""EdgeGrid: straight edges binned on a grid of cells, and the (query, edge) pairs of a query in bounded blocks."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

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
