"""Particles of the tissue model: a uniform grid whose lines pass through every load
segment's ends, or particles graded toward refinement zones (the needle, segment ends) on
a 2:1-balanced quadtree, with the background cells their quadrature lives on."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ..config import Discretization, Tissue
from ..config.blocks import default_spacing_of
from ..geometry.boundary import smooth_vertex
from ..geometry.segments import point_segment_distance
from .quadrature import cell_quadrature

log = logging.getLogger(__name__)


def grid_lines(length: float, spacing: float, breaks=()) -> np.ndarray:
    """Grid lines on [0, length], about `spacing` apart, with a line at every break point
    (the ends of load segments): each piece between breaks is divided evenly. Without breaks
    it is the uniform grid that ends exactly on both edges."""
    cells = max(int(round(length / spacing)), 1)
    knots = _merged_knots(np.unique(np.clip(np.asarray([0.0, length, *breaks], dtype=float), 0.0, length)),
                          length, MIN_BREAK_GAP * spacing)
    if len(knots) == 2:
        return np.linspace(0.0, length, cells + 1)
    pieces = [np.linspace(a, b, max(int(round(cells * (b - a) / length)), 1) + 1)[:-1]
              for a, b in zip(knots[:-1], knots[1:])]
    return np.append(np.concatenate(pieces), length)


# breaks closer than this x the spacing are one line: two segment ends a hair apart in x (the
# ends of a load on a slightly slanted edge of a traced outline: 0.0009 mm) made a sliver of
# lattice cells between them, every level of refinement stacking particles 1e-4 mm apart,
# and the stiffness of a load step that failed at 16 uN
MIN_BREAK_GAP = 0.125


def _merged_knots(knots: np.ndarray, length: float, gap: float) -> np.ndarray:
    """The sorted `knots` (0 and `length` among them) without those within `gap` of the one
    kept before them; an edge (0, `length`) is kept over a break beside it."""
    kept = [0.0]
    for knot in knots[1:]:
        if knot - kept[-1] > gap:
            kept.append(float(knot))
        elif knot == length and len(kept) > 1:
            kept[-1] = length
    if kept[-1] != length:  # a length within `gap` of 0: one cell
        kept.append(length)
    return np.asarray(kept)


def segment_breaks(segments) -> tuple[list[float], list[float]]:
    """x and y coordinates of the end points of boundary segments: the grid lines that put a
    particle on each segment end."""
    ends = np.asarray([point for segment in segments for point in segment], dtype=float).reshape(-1, 2)
    return list(ends[:, 0]), list(ends[:, 1])


def grid_particles(size: tuple[float, float], spacing: float,
                   breaks: tuple = ((), ())) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Particles on a tensor grid covering [0, W] x [0, H], and their tributary areas.

    The lines are ~`spacing` apart, adjusted so the grid ends exactly on the edges and has a
    line through every break (x breaks, y breaks; see grid_lines).
    Returns particles (NP, 2), volumes (NP,), dx, dy (the largest line intervals).
    """
    x, y = grid_lines(size[0], spacing, breaks[0]), grid_lines(size[1], spacing, breaks[1])
    particles = np.stack(np.meshgrid(x, y, indexing="ij"), axis=-1).reshape(-1, 2)
    wx, wy = _tributary(x), _tributary(y)
    volumes = np.outer(wx, wy).ravel()
    return particles, volumes, float(np.diff(x).max()), float(np.diff(y).max())


def _tributary(lines: np.ndarray) -> np.ndarray:
    """Half of each adjacent interval, per line."""
    half = 0.5 * np.diff(lines)
    return np.concatenate([half, [0.0]]) + np.concatenate([[0.0], half])


@dataclass(frozen=True)
class GradedParticles:
    """Particles at the corners of the leaf cells of a balanced quadtree over the slab."""

    particles: np.ndarray  # (NP, 2)
    volumes: np.ndarray  # (NP,) tributary areas: a quarter of each adjacent leaf cell
    local_spacing: np.ndarray  # (NP,) largest side of the leaf cells meeting at the particle
    cells: np.ndarray  # (nc, 4) leaf cells: x0, y0, width, height (mm)
    fine_spacing: float  # leaf side near the needle (mm)
    coarse_spacing: float  # leaf side far from it (mm)


@dataclass(frozen=True)
class RefinementZone:
    """Leaf cells of side ~`spacing` within `radius` of `center` (a disk; radius 0: a point),
    or with an `end` within `radius` of the segment from `center` to `end` (a material
    interface)."""

    center: np.ndarray  # (2,)
    radius: float
    spacing: float
    end: np.ndarray | None = None  # (2,)

    def distance(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Distance (mm, negative inside) of the points (x, y) (broadcast together) from the zone."""
        dx, dy = x - self.center[0], y - self.center[1]
        if self.end is not None:
            (ax, ay) = self.end - self.center
            t = np.clip((dx * ax + dy * ay) / (ax * ax + ay * ay), 0.0, 1.0)
            dx, dy = dx - t * ax, dy - t * ay
        return np.hypot(dx, dy) - self.radius

    def shifted(self, offset: np.ndarray) -> RefinementZone:
        """The zone moved by `offset` (2,)."""
        end = None if self.end is None else self.end + offset
        return RefinementZone(self.center + offset, self.radius, self.spacing, end)


def graded_particles(size: tuple[float, float], spacing: float, fine_spacing: float,
                     center: np.ndarray, radius: float, growth: float = 0.5,
                     points: tuple[RefinementZone, ...] = (), breaks: tuple = ((), ())) -> GradedParticles:
    """A particle set graded toward a disk (the needle's zone): leaf cells of side
    ~`fine_spacing` within `radius` of `center`, the side allowed to grow by `growth` mm per
    mm of distance beyond it, up to ~`spacing` (coarse side = fine x 2^L, L the nearest
    integer); neighbouring leaves differ by at most one level (2:1 balance), so the local
    spacing, and with it the kernel support, varies smoothly. `points` adds further zones
    (the ends of load segments) graded the same way, `breaks` grid lines of the coarse
    lattice (see grid_lines).

    Particles sit at the leaf corners (hanging corners included, as meshfree allows), with
    volume a quarter of each adjacent leaf, so the volumes sum to the slab's area.
    """
    zones = (RefinementZone(np.asarray(center, dtype=float), float(radius), fine_spacing), *points)
    levels = max(int(round(np.log2(spacing / fine_spacing))), 0)
    return graded_lattice(size, fine_spacing * 2**levels, zones, growth, breaks)


MAX_LATTICE_CELLS = 4_000_000  # finest-lattice cells of graded_lattice (a few hundred MB of work arrays)


def graded_lattice(size: tuple[float, float], base: float, zones: tuple[RefinementZone, ...],
                   growth: float = 0.5, breaks: tuple = ((), ())) -> GradedParticles:
    """The quadtree behind graded_particles: coarse lattice lines ~`base` apart through the
    breaks (grid_lines), each coarse cell split into 2^l x 2^l leaves where a zone asks for
    it (leaf side <= zone spacing + growth x distance to the zone), 2:1 balanced."""
    width, height = size
    levels = max([_zone_level(base, zone) for zone in zones] + [0])
    coarse_x, coarse_y = grid_lines(width, base, breaks[0]), grid_lines(height, base, breaks[1])
    nx0, ny0 = len(coarse_x) - 1, len(coarse_y) - 1
    levels = _capped_levels(levels, base, nx0 * ny0)
    n = 2**levels  # finest lattice: nx0 n x ny0 n cells
    (xs, step_x), (ys, step_y) = _subdivided(coarse_x, n), _subdivided(coarse_y, n)  # (fx + 1,), (fy + 1,)
    xc, yc = _middles(xs, step_x), _middles(ys, step_y)
    # side of the coarse cell holding each finest cell, (fx, fy)
    side0 = (max(width / nx0, height / ny0) if step_x and step_y else
             np.maximum(np.repeat(np.diff(coarse_x), n)[:, None], np.repeat(np.diff(coarse_y), n)[None, :]))
    required = _required_levels(zones, base, levels, growth, xc, yc, side0)
    corner, side = _leaf_cells(_balanced_leaf_levels(required, levels), levels)
    particles, volumes, local, cells = _corner_particles(corner, side, xs, step_x, ys, step_y)
    fine = max(step_x or float(np.diff(xs).max()), step_y or float(np.diff(ys).max()))
    coarse = fine * n if step_x and step_y else max(float(np.diff(coarse_x).max()),
                                                    float(np.diff(coarse_y).max()))
    return GradedParticles(particles, volumes, local, cells, fine, coarse)


def _zone_level(base: float, zone: RefinementZone) -> int:
    """The halvings of `base` that bring it to about the zone's spacing (none below zero)."""
    return max(int(round(np.log2(base / zone.spacing))), 0)


def _capped_levels(levels: int, base: float, coarse_cells: int) -> int:
    """`levels`, or fewer where the finest lattice would pass MAX_LATTICE_CELLS cells: it is
    held as dense arrays (memory), so the zones get coarser leaves instead."""
    cap = max(int(np.floor(0.5 * np.log2(MAX_LATTICE_CELLS / coarse_cells))), 0)
    if levels > cap:
        log.info("graded particles: %d refinement levels capped at %d (at most %d lattice cells); "
                 "the finest spacing is %.3g mm instead of %.3g mm", levels, cap, MAX_LATTICE_CELLS,
                 base / 2**cap, base / 2**levels)
        return cap
    return levels


def _required_levels(zones: tuple[RefinementZone, ...], base: float, levels: int, growth: float,
                     xc: np.ndarray, yc: np.ndarray, side0: float | np.ndarray) -> np.ndarray:
    """The level each finest cell's leaf must reach for the zones, (fx, fy): the halvings of its
    coarse cell's side `side0` down to the zones' target side there (zone spacing + growth x
    distance to the zone), from the finest cells' centres xc (fx,) and yc (fy,)."""
    # the coarse cells exceed `base` a little where grid_lines rounds them to fit the edges or
    # the breaks, so a zone's cells may ask for one level more than its own (4x the particles
    # there): each zone's levels are capped at its own, zones of one level taken together
    def own_level(zone: RefinementZone) -> int:
        return min(_zone_level(base, zone), levels)

    required = np.zeros((len(xc), len(yc)), dtype=int)
    for cap in sorted({own_level(zone) for zone in zones}):
        group = [zone for zone in zones if own_level(zone) == cap]
        target = np.full((len(xc), len(yc)), np.inf)
        for zone in group:
            distance = zone.distance(xc[:, None], yc[None, :])
            target = np.minimum(target, zone.spacing * (1.0 + 1e-9) + growth * np.maximum(distance, 0.0))
        with np.errstate(divide="ignore"):  # no zone: target inf, no refinement
            required = np.maximum(required, np.clip(np.ceil(np.log2(side0 / target)), 0, cap).astype(int))
    return required


def _leaf_levels(required: np.ndarray, levels: int) -> np.ndarray:
    """Level of the leaf holding each finest cell: the smallest l whose level-l ancestor
    needs no split (no finest cell inside asks for more than l)."""
    fx, fy = required.shape
    leaf = np.full_like(required, levels)
    block = required
    for level in range(levels - 1, -1, -1):
        b = 2 ** (levels - level)
        # the level-l blocks' maxima from the level-(l + 1) ones, written through a view of
        # the leaves: neither is taken over the whole finest lattice again at each level
        block = block.reshape(fx // b, 2, fy // b, 2).max(axis=(1, 3))
        np.copyto(leaf.reshape(fx // b, b, fy // b, b), level, where=(block <= level)[:, None, :, None])
    return leaf


def _balanced_leaf_levels(required: np.ndarray, levels: int) -> np.ndarray:
    """_leaf_levels after 2:1 balance: a leaf's neighbours are at most one level coarser."""
    leaf = _leaf_levels(required, levels)
    while True:
        balanced = np.maximum(required, _neighbourhood_max(leaf) - 1)
        if np.array_equal(balanced, required):
            return leaf
        required = balanced
        leaf = _leaf_levels(required, levels)


def _leaf_cells(leaf: np.ndarray, levels: int) -> tuple[np.ndarray, np.ndarray]:
    """The leaf cells of the finest cells' leaf levels (fx, fy): lower-left corners on the
    finest lattice (nc, 2) and sides in finest cells (nc,), by level."""
    corners, sides = [], []
    for level in range(levels + 1):
        b = 2 ** (levels - level)
        i, j = np.nonzero(leaf[::b, ::b] == level)  # a leaf's first cell lies on every b-th line
        corners.append(np.stack([i * b, j * b], axis=1))
        sides.append(np.full(len(i), b))
    return np.concatenate(corners), np.concatenate(sides)


def _corner_particles(corner: np.ndarray, side: np.ndarray, xs: np.ndarray, step_x: float | None,
                      ys: np.ndarray, step_y: float | None):
    """Particles at the leaf cells' corners (NP, 2), once each, with volumes (NP,) a quarter
    of each adjacent leaf, local spacings (NP,) the largest side of those leaves, and the
    leaves (nc, 4: x0, y0, width, height) on the finest lattice lines xs, ys."""
    offsets = np.array([[0, 0], [1, 0], [0, 1], [1, 1]])
    lattice = corner[:, None, :] + offsets[None] * side[:, None, None]  # (nc, 4, 2)
    lines_y = len(ys)  # fy + 1
    keys = lattice[..., 0] * lines_y + lattice[..., 1]
    unique, inverse = np.unique(keys.ravel(), return_inverse=True)
    particles = np.stack([xs[unique // lines_y], ys[unique % lines_y]], axis=1)
    cell_w, x0 = _extent(xs, step_x, corner[:, 0], side)
    cell_h, y0 = _extent(ys, step_y, corner[:, 1], side)
    volumes = np.zeros(len(unique))
    np.add.at(volumes, inverse, np.repeat(cell_w * cell_h / 4.0, 4))
    local = np.zeros(len(unique))
    np.maximum.at(local, inverse, np.repeat(np.maximum(cell_w, cell_h), 4))
    return particles, volumes, local, np.column_stack([x0, y0, cell_w, cell_h])


def _neighbourhood_max(levels: np.ndarray) -> np.ndarray:
    """The largest value in each cell's 3 x 3 neighbourhood (edges repeated outward)."""
    padded = np.pad(levels, 1, mode="edge")
    rows, cols = levels.shape
    across = np.maximum(np.maximum(padded[:, :cols], padded[:, 1:cols + 1]), padded[:, 2:])  # by rows, then columns
    return np.maximum(np.maximum(across[:rows], across[1:rows + 1]), across[2:])


def _subdivided(lines: np.ndarray, n: int) -> tuple[np.ndarray, float | None]:
    """Every interval of `lines` split into n equal parts, and the common step when the result
    is uniform (then computed as i / N x length, the same numbers as the uniform lattice)."""
    if len(lines) > 2 and not np.allclose(np.diff(lines), lines[1] - lines[0], rtol=1e-12, atol=0.0):
        parts = [a + (b - a) * np.arange(n) / n for a, b in zip(lines[:-1], lines[1:])]
        return np.append(np.concatenate(parts), lines[-1]), None
    cells = n * (len(lines) - 1)
    return np.arange(cells + 1) / cells * lines[-1], lines[-1] / cells


def _middles(lines: np.ndarray, step: float | None) -> np.ndarray:
    return 0.5 * (lines[:-1] + lines[1:]) if step is None else (np.arange(len(lines) - 1) + 0.5) * step


def _extent(lines: np.ndarray, step: float | None, first: np.ndarray, count: np.ndarray):
    """Width and start of the cells spanning `count` lattice intervals from line `first`."""
    if step is None:
        return lines[first + count] - lines[first], lines[first]
    return count * step, first * step


END_GROWTH = 0.5  # mm of leaf side per mm of distance from a graded segment end


def end_spacing(spacing: float, reference: float, reference_levels: int = 3) -> float:
    """Leaf side at the end of a load segment for a coarse `spacing`.

    The solution is singular at a segment end (the traction or the displacement jumps along
    the edge), so uniform refinement converges only like h^(~1) there and pollutes the whole
    field. Here the end's leaf side falls like spacing^2 (the grading that restores the
    smooth-solution rate for an r^(1/2) singularity with a linear basis):
    spacing / 2^reference_levels at the `reference` spacing (the scene's default,
    min(W, H)/20), one level more per halving of the spacing and one less per doubling
    (discretization.segment_end_levels; benchmarks/deform_segments.py).
    """
    levels = max(reference_levels + int(round(np.log2(reference / spacing))), 0)
    return spacing / 2**levels


def clamp_ends(tissue: Tissue) -> list[np.ndarray]:
    """The ends of the clamped stretches of the boundary: the clamped pieces' end points that
    lie on no other clamped piece (a clamp of several pieces along a traced contour ends
    twice, not at every vertex between its pieces)."""
    pieces = tissue.clamped_pieces()
    if not pieces:
        return []
    starts, ends = (np.array([piece[k] for piece in pieces], dtype=float) for k in (0, 1))
    points = np.vstack([starts, ends])  # (2 p, 2)
    owner = np.tile(np.arange(len(pieces)), 2)
    free = np.empty(len(points), dtype=bool)
    for first in range(0, len(points), 256):  # (256, p) distances at a time: a traced clamp may have thousands
        rows = slice(first, first + 256)
        distance = point_segment_distance(points[rows, None, :], starts[None], ends[None])
        distance[np.arange(len(distance)), owner[rows]] = np.inf
        free[rows] = (distance > tissue.domain.tolerance).all(axis=1)
    return list(points[free])


def end_zones(tissue: Tissue, segments, discretization: Discretization) -> tuple[RefinementZone, ...]:
    """Refinement zones (points) at the load-segment ends and the clamped stretches' ends
    (clamp_ends) that lie inside an edge or at a vertex where the boundary hardly turns (a
    traced contour's: geometry.boundary.smooth_vertex; corners are left as they are); none
    with discretization.segment_end_levels 0. A clamp ending inside an edge (u = 0 beside a
    free edge) is as singular as a displacement segment's end: ungraded, a slab held along part
    of its bottom edge was 2.2 % off scikit-fem at the default spacing and 2.9 % at half of it."""
    if discretization.segment_end_levels == 0:
        return ()
    domain = tissue.domain
    fine = end_spacing(discretization.spacing, default_spacing_of(tissue.bounding_size, None),
                       discretization.segment_end_levels)
    zones = []
    for point in (*(point for segment in segments for point in segment), *clamp_ends(tissue)):
        if len(domain.edges_at(point)) == 1 or smooth_vertex(domain, point):
            zones.append(RefinementZone(np.asarray(point, dtype=float), 0.0, fine))
    return tuple(zones)


def leaf_quadrature(cells: np.ndarray, order: int, subdivisions: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Gauss rule of `order` points per direction on each of subdivisions^2 sub-cells of every
    leaf cell (nc, 4: x0, y0, width, height). Returns points (n, 2), weights (n,) (mm^2)."""
    unit_points, unit_weights = cell_quadrature((1.0, 1.0), (subdivisions, subdivisions), order)
    origin, extent = cells[:, None, :2], cells[:, None, 2:]  # (nc, 1, 2)
    points = origin + unit_points[None] * extent  # (nc, g, 2)
    weights = unit_weights[None] * (cells[:, 2] * cells[:, 3])[:, None]
    return points.reshape(-1, 2), weights.ravel()
