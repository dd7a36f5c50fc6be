"""Particles and quadrature of a tissue that is not a plain rectangle: a polygon outline,
holes, material regions.

The graded lattice of `particles` is kept (its lines pass through every polygon vertex, so
edges along the lattice directions never cut a background cell); particles outside the
shape are dropped and particles are added along every boundary edge at the local spacing,
so free and clamped edges carry particles. Background cells cut by the boundary or by a
region's edge are split in four, recursively (CUT_LEVELS times); the cells no edge cuts
are integrated whole (inside) or dropped (outside), the finest cut cells keep only their
Gauss points inside the tissue. The quadrature thus follows the boundary and the material
interfaces to 1/2^CUT_LEVELS of a cell, and exactly where they run along lattice lines.
"""

from __future__ import annotations

import numpy as np

from ..config import Discretization, Tissue
from ..config.blocks import default_spacing_of
from ..geometry import CIRCLE_SEGMENTS, PolygonDomain
from .particles import GradedParticles, RefinementZone, end_spacing, leaf_quadrature

CUT_LEVELS = 3  # halvings of a cut background cell
MERGE = 0.35  # a boundary particle replaces lattice particles closer than this x local spacing


def shape_breaks(tissue: Tissue) -> tuple[list[float], list[float]]:
    """Grid-line coordinates through the polygon vertices (outline, polygon holes, regions,
    and where holes cut into the outline); circles are left out (their many vertices would
    crowd the lattice)."""
    loops = []
    domain = tissue.domain
    if isinstance(domain, PolygonDomain) and not domain.edge_names:  # not a rectangle's
        outline = domain.outline
        for hole in tissue.holes:  # a circle cut into the outline: its vertices and ends on the chords
            if hole.circle is not None:
                r = np.hypot(*(outline - hole.circle.center).T)
                outline = outline[(r < hole.circle.radius * np.cos(np.pi / CIRCLE_SEGMENTS) - domain.tolerance)
                                  | (r > hole.circle.radius + domain.tolerance)]
        loops.append(outline)
    loops += [np.asarray(hole.polygon, dtype=float) for hole in tissue.holes if hole.polygon is not None]
    loops += [np.asarray(region.polygon, dtype=float) for region in tissue.regions]
    if not loops:
        return [], []
    points = np.concatenate(loops)
    return list(points[:, 0]), list(points[:, 1])


REENTRANT = 0.2  # rad beyond a straight angle: a corner the solution is singular at


def corner_zones(tissue: Tissue, discretization: Discretization) -> tuple[RefinementZone, ...]:
    """Refinement zones at the re-entrant corners of the tissue (interior angle above
    pi + REENTRANT: a notch's or a hole's corners), graded like the load-segment ends
    (particles.end_spacing: the solution is singular there, r^(~1/2) at a slit's tip);
    none with discretization.segment_end_levels 0."""
    domain = tissue.domain
    if discretization.segment_end_levels == 0 or not isinstance(domain, PolygonDomain):
        return ()
    fine = end_spacing(discretization.spacing, default_spacing_of(tissue.bounding_size, None),
                       discretization.segment_end_levels)
    zones = []
    for loop in [domain.outline] + [hole[::-1] for hole in domain.holes]:  # tissue on the left
        before = loop - np.roll(loop, 1, axis=0)
        after = np.roll(loop, -1, axis=0) - loop
        turn = np.arctan2(before[:, 0] * after[:, 1] - before[:, 1] * after[:, 0],
                          np.sum(before * after, axis=1))  # > 0 left turn (convex corner)
        for vertex in loop[turn < -REENTRANT]:
            zones.append(RefinementZone(np.asarray(vertex, dtype=float), 0.0, fine))
    return tuple(zones)


def cutting_edges(tissue: Tissue) -> tuple[np.ndarray, np.ndarray]:
    """Start and end points (n, 2) of every edge that cuts background cells: the boundary
    and the regions' edges."""
    domain = tissue.domain
    starts = [np.array([a for a, _ in domain.boundary_segments()])]
    ends = [np.array([b for _, b in domain.boundary_segments()])]
    for region in tissue.regions:
        vertices = np.asarray(region.polygon, dtype=float)
        starts.append(vertices)
        ends.append(np.roll(vertices, -1, axis=0))
    return np.concatenate(starts), np.concatenate(ends)


def cells_cut(cells: np.ndarray, starts: np.ndarray, ends: np.ndarray, chunk: int = 4000) -> np.ndarray:
    """Mask (nc,) of cells (x0, y0, width, height) whose open interior some edge passes
    through (Liang-Barsky clipping of every edge against every cell, shrunk by round-off)."""
    cut = np.zeros(len(cells), dtype=bool)
    if len(starts) == 0:
        return cut
    delta = ends - starts  # (ns, 2)
    for first in range(0, len(cells), chunk):
        c = cells[first:first + chunk, None, :]
        shrink = 1e-9 * np.maximum(c[..., 2], c[..., 3])
        low_x, high_x = c[..., 0] + shrink, c[..., 0] + c[..., 2] - shrink
        low_y, high_y = c[..., 1] + shrink, c[..., 1] + c[..., 3] - shrink
        t0 = np.zeros((len(c), len(starts)))
        t1 = np.ones_like(t0)
        reject = np.zeros_like(t0, dtype=bool)
        for p, q in ((-delta[:, 0], starts[:, 0] - low_x), (delta[:, 0], high_x - starts[:, 0]),
                     (-delta[:, 1], starts[:, 1] - low_y), (delta[:, 1], high_y - starts[:, 1])):
            p = np.broadcast_to(p, t0.shape)
            parallel = p == 0.0
            reject |= parallel & (q < 0.0)
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.where(parallel, 0.0, q / np.where(parallel, 1.0, p))
            t0 = np.where(~parallel & (p < 0.0), np.maximum(t0, t), t0)
            t1 = np.where(~parallel & (p > 0.0), np.minimum(t1, t), t1)
        cut[first:first + chunk] = np.any(~reject & (t0 < t1), axis=1)
    return cut


def _split(cells: np.ndarray) -> np.ndarray:
    """Each cell in four."""
    half = cells[:, 2:] / 2.0
    offsets = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], dtype=float)
    origins = cells[:, None, :2] + offsets[None] * half[:, None, :]
    return np.concatenate([origins, np.broadcast_to(half[:, None, :], origins.shape)], axis=2).reshape(-1, 4)


def shaped_quadrature(tissue: Tissue, cells: np.ndarray, order: int, subdivisions: int = 1,
                      levels: int = CUT_LEVELS) -> tuple[np.ndarray, np.ndarray]:
    """Gauss points (n, 2) and areas (n,) over the tissue: whole cells inside, cut cells
    split `levels` times, the last cut pieces masked point by point (see the module)."""
    domain = tissue.domain
    starts, ends = cutting_edges(tissue)
    current = _split_n(cells, subdivisions)
    points, weights = [], []
    for level in range(levels + 1):
        cut = cells_cut(current, starts, ends)
        whole = current[~cut]
        centres = whole[:, :2] + 0.5 * whole[:, 2:]
        inside = domain.contains(centres) if not isinstance(domain, PolygonDomain) else domain._inside_strict(centres)
        p, w = leaf_quadrature(whole[inside], order)
        points.append(p)
        weights.append(w)
        if level == levels:
            p, w = leaf_quadrature(current[cut], order)
            keep = domain._inside_strict(p) if isinstance(domain, PolygonDomain) else domain.contains(p)
            points.append(p[keep])
            weights.append(w[keep])
        else:
            current = _split(current[cut])
    return np.concatenate(points), np.concatenate(weights)


def _split_n(cells: np.ndarray, n: int) -> np.ndarray:
    """Each cell in n x n equal cells."""
    if n == 1:
        return cells
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    offsets = np.stack([i.ravel(), j.ravel()], axis=1) / n  # (n^2, 2)
    origins = cells[:, None, :2] + offsets[None] * cells[:, None, 2:]
    sides = np.broadcast_to(cells[:, None, 2:] / n, origins.shape)
    return np.concatenate([origins, sides], axis=2).reshape(-1, 4)


def fit_particles(tissue: Tissue, graded: GradedParticles) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lattice's particles inside the shape plus particles along every boundary edge at
    the local spacing (every vertex one of them); lattice particles closer than MERGE x the
    local spacing to an added one are dropped. Returns particles, volumes, local spacing."""
    domain = tissue.domain
    if not isinstance(domain, PolygonDomain):  # a rectangle with regions: the lattice fits
        return graded.particles, graded.volumes, graded.local_spacing
    from scipy.spatial import cKDTree  # here: a rectangle's commands need not import scipy.spatial

    tol = 1e-7 * max(domain.size)
    keep = domain.contains(graded.particles, tol)
    particles, volumes, local = graded.particles[keep], graded.volumes[keep], graded.local_spacing[keep]
    tree = cKDTree(graded.particles)
    added = []
    for start, end in domain.boundary_segments():
        # points one local spacing apart along the edge: where the count of spacings
        # int ds / h(s) (h of the nearest lattice particle, sampled finely) passes an integer
        length = float(np.linalg.norm(end - start))
        finest = float(graded.local_spacing.min())
        t = np.linspace(0.0, 1.0, max(int(np.ceil(8 * length / finest)), 2) + 1)
        _, near = tree.query(start + t[:, None] * (end - start))
        density = 1.0 / graded.local_spacing[near]
        count = np.concatenate([[0.0], np.cumsum(0.5 * (density[1:] + density[:-1]) * np.diff(t) * length)])
        total = max(int(round(count[-1])), 1)
        # the end is the next edge's start
        t_points = np.interp(np.arange(total) * count[-1] / total, count, t)
        added.append(start + t_points[:, None] * (end - start))
    added = np.concatenate(added)
    _, near = tree.query(added)
    added_local = graded.local_spacing[near]
    # an added particle onto an existing one (a lattice line along the edge): keep the old one
    own = cKDTree(particles)
    distance, _ = own.query(added)
    new = distance > MERGE * added_local
    added, added_local = added[new], added_local[new]
    if len(added):
        # lattice particles just inside the boundary next to an added one would nearly coincide
        distance, index = cKDTree(added).query(particles)
        on_boundary = domain.distance(particles) <= tol
        crowded = (distance < MERGE * added_local[index]) & ~on_boundary
        particles, volumes, local = particles[~crowded], volumes[~crowded], local[~crowded]
    particles = np.concatenate([particles, added])
    volumes = np.concatenate([volumes, 0.5 * added_local**2])  # half a cell: the other half is outside
    local = np.concatenate([local, added_local])
    return particles, volumes, local


def region_index(tissue: Tissue, points: np.ndarray) -> np.ndarray:
    """Index of the region holding each point (n,): the first that holds it, -1 for the
    tissue's own material."""
    index = np.full(len(points), -1)
    for k in range(len(tissue.regions) - 1, -1, -1):  # the first region wins: assign it last
        vertices = np.asarray(tissue.regions[k].polygon, dtype=float)
        region = PolygonDomain(vertices if _ccw(vertices) else vertices[::-1].copy())
        index[region._inside_strict(points)] = k
    return index


def _ccw(vertices: np.ndarray) -> bool:
    x, y = vertices[:, 0], vertices[:, 1]
    return float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)) > 0
