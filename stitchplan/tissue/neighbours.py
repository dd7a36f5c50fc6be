"""Fixed-radius neighbour search on square cells (a cell list), in numpy.

The RK shape functions at a point need the particles whose kernel support reaches it. With
the particles binned in square cells of side `size`, every particle within `size` of a point
in the max norm lies in the point's cell or one of its eight neighbours. Each cell that has a
particle in its 3 x 3 block keeps that block's particles as one list, in ascending index, so a
point's candidates are one slice: the pairs come out ordered by point, then particle, without
a sort. Only those cells are kept (as sorted keys), so the memory follows the particles (at
most nine entries each), not the tissue's extent.

This replaces scipy.spatial's KD-trees: importing scipy.spatial costs every command about
0.1 s of start-up (benchmarks/model_build_speed.py, start-up table), and the searches here are
max-norm balls of one radius, which cells answer with a few array operations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..geometry.edge_grid import concatenated_ranges

_CELL_LIMIT = 2**30  # cell coordinates are clipped here: a point far outside finds no cell
FEW_POINTS = 4  # up to here `within` takes the points one by one
_BLOCK = np.array([(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1)])  # a cell's 3 x 3 block, (9, 2)


def _key(cx, cy):
    """One integer per cell (arrays or ints), distinct for coordinates within +-_CELL_LIMIT
    and below 2^62 there (no int64 overflow)."""
    return (cx + _CELL_LIMIT) * (2 * _CELL_LIMIT + 1) + (cy + _CELL_LIMIT)


def _keys(cells: np.ndarray) -> np.ndarray:
    """The int64 keys of cells (..., 2) -> (...)."""
    return _key(cells[..., 0], cells[..., 1])


@dataclass(frozen=True, eq=False)
class CellGrid:
    """Some of the particles (`members`) binned in square cells of side `size` (mm): the
    particles in the 3 x 3 block around cell keys[c] are blocks[starts[c]:starts[c + 1]], in
    ascending index."""

    x: np.ndarray  # every particle's coordinates, (NP,) each: the filter gathers 1D arrays
    y: np.ndarray
    origin: np.ndarray  # (2,)
    size: float
    keys: np.ndarray  # the cells with a member in their block, ascending, (C,)
    starts: np.ndarray  # (C + 1,)
    blocks: np.ndarray  # particle indices, (starts[-1],)
    block_x: np.ndarray  # their coordinates, aligned with `blocks`: a point's filter reads slices
    block_y: np.ndarray

    @classmethod
    def of(cls, particles: np.ndarray, size: float, members: np.ndarray | None = None) -> CellGrid:
        members = np.arange(len(particles)) if members is None else np.asarray(members, dtype=np.int64)
        chosen = particles[members]
        origin = chosen.min(axis=0) if len(chosen) else np.zeros(2)
        cells = np.floor((chosen - origin) / size).astype(np.int64)
        # every member is in the blocks of the 9 cells around its own: (cell, particle) pairs
        # sorted by cell, then particle, through one int64 key
        around = _keys(cells[:, None, :] + _BLOCK).ravel()  # (n x 9,)
        keys, cell = np.unique(around, return_inverse=True)
        count = max(len(particles), 1)
        pairs = np.sort(cell.ravel() * count + np.repeat(members, len(_BLOCK)))
        starts = np.searchsorted(pairs // count, np.arange(len(keys) + 1))
        blocks = pairs % count
        return cls(np.ascontiguousarray(particles[:, 0]), np.ascontiguousarray(particles[:, 1]), origin,
                   float(size), keys, starts, blocks, particles[blocks, 0], particles[blocks, 1])

    def within(self, points: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
        """(point, particle) index pairs with |X - X_I|_inf <= reach (reach <= size), ordered
        by point, then particle; a point with a coordinate that is not finite has none."""
        if len(points) <= FEW_POINTS:
            return self._within_each(points, reach)
        index = np.flatnonzero(np.isfinite(points).all(axis=1))
        if not len(self.keys) or not len(index):
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        cells = np.floor(np.clip((points[index] - self.origin) / self.size, -_CELL_LIMIT, _CELL_LIMIT))
        keys = _keys(cells.astype(np.int64))
        slot = np.minimum(np.searchsorted(self.keys, keys), len(self.keys) - 1)
        hit = self.keys[slot] == keys
        index, slot = index[hit], slot[hit]
        counts = self.starts[slot + 1] - self.starts[slot]
        rows = np.repeat(index, counts)
        cols = self.blocks[concatenated_ranges(self.starts[slot], counts)]
        near = ((np.abs(points[:, 0][rows] - self.x[cols]) <= reach)
                & (np.abs(points[:, 1][rows] - self.y[cols]) <= reach))
        return rows[near], cols[near]

    def _within_each(self, points: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
        """`within` point by point: for the one or two points of tip tracking and needle
        points, fewer array operations than the batched search."""
        rows, cols = [], []
        for row, (start, end, x, y) in enumerate(self._block_of(points)):
            near = np.flatnonzero((np.abs(self.block_x[start:end] - x) <= reach)
                                  & (np.abs(self.block_y[start:end] - y) <= reach))
            rows.append(np.full(len(near), row, dtype=np.int64))
            cols.append(self.blocks[start + near])
        if not rows:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        return np.concatenate(rows), np.concatenate(cols)

    def block(self, x: float, y: float) -> tuple[int, int]:
        """The range of `blocks` of the cell holding (x, y) (empty where none): every member
        within `size` of the point in the max norm lies in it."""
        ox, oy = self.origin.tolist()
        if not (math.isfinite(x) and math.isfinite(y)):
            return 0, 0
        cx = min(max(math.floor((x - ox) / self.size), -_CELL_LIMIT), _CELL_LIMIT)
        cy = min(max(math.floor((y - oy) / self.size), -_CELL_LIMIT), _CELL_LIMIT)
        key = _key(cx, cy)
        slot = int(self.keys.searchsorted(key))
        if slot < len(self.keys) and self.keys[slot] == key:
            return int(self.starts[slot]), int(self.starts[slot + 1])
        return 0, 0

    def _block_of(self, points: np.ndarray) -> list[tuple[int, int, float, float]]:
        """Per point, the range of `blocks` of its cell (empty where no cell) and its coordinates."""
        return [(*self.block(x, y), x, y) for x, y in points.tolist()]

    def nearest(self, points: np.ndarray) -> np.ndarray:
        """The index of each point's nearest particle among the members (Euclidean; on a tie
        the lowest index), (n,)."""
        points = np.atleast_2d(points)
        found = np.full(len(points), -1, dtype=np.int64)
        for row, (start, end, x, y) in enumerate(self._block_of(points)):
            if end > start:
                distance = (self.block_x[start:end] - x) ** 2 + (self.block_y[start:end] - y) ** 2
                best = int(np.argmin(distance))  # the first of equals: the lowest index
                # a particle outside the block is more than `size` away
                if distance[best] < self.size**2:
                    found[row] = self.blocks[start + best]
        unsure = np.flatnonzero(found < 0)
        members = np.unique(self.blocks) if len(unsure) else None
        for point in unsure:  # none surely nearest within the block: every member
            distance = (self.x[members] - points[point, 0]) ** 2 + (self.y[members] - points[point, 1]) ** 2
            found[point] = members[np.argmin(distance)]
        return found
