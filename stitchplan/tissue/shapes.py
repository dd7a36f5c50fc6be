"""Particles and quadrature of a tissue that is not a plain rectangle: a polygon outline,
holes, material regions.

The graded lattice of `particles` is kept, with lines through the polygon vertices that need
them (the coordinates of edges along x and y, so such edges never cut a background cell,
and the corners: shape_breaks); particles outside the shape are dropped and particles are
added along the boundary at the local spacing, every corner one of them, so free and
clamped edges carry particles (fit_particles), but not between the lattice's own particles
on an edge along a lattice line. A traced contour's vertices that turn little, a circular
hole's (but where tissue beyond it is thin: circle_vertices), and lines closer than a
fraction of the spacing, are left out: the model's size follows the spacing, not the vertex
count. Background cells cut by the boundary or by a region's edge
are split in four, recursively (CUT_LEVELS times); the cells no edge cuts are integrated
whole (inside) or dropped (outside), the finest cut cells keep only their Gauss points
inside the tissue. The quadrature thus follows the boundary and the material interfaces to
1/2^CUT_LEVELS of a cell, and exactly where they run along lattice lines.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from ..config import Discretization, Tissue
from ..config.blocks import default_spacing_of
from ..geometry.edge_grid import EdgeGrid, concatenated_ranges
from ..geometry.polygon_domain import PolygonDomain
from ..geometry.polygons import CIRCLE_SEGMENTS, CORNER_TURN, turns
from .particles import GradedParticles, RefinementZone, end_spacing, leaf_quadrature
from .shape_functions import RoundHole
from .thin_features import wall_thickness

CUT_LEVELS = 3  # halvings of a cut background cell
MERGE = 0.35  # a boundary particle replaces lattice particles closer than this x local spacing
THIN = 0.25  # x the spacing: a lattice line closer than this to a kept one is left out
ALONG = 0.75  # x the local spacing: no particle added this close to a lattice particle on its edge
NEAREST_ALONG = 4  # lattice particles on the boundary looked at around each added one


def shape_breaks(tissue: Tissue, spacing: float | None = None) -> tuple[list[float], list[float]]:
    """Grid-line coordinates through the polygon vertices that need one (outline, polygon
    holes and regions, and where holes cut into the outline): the x of every edge along y and the
    y of every edge along x (so those never cut a background cell), and both coordinates of
    every corner (a turn above CORNER_TURN) between two such long edges, where long is at
    least THIN x `spacing` (default: the tissue's default spacing, min(W, H)/20). Lines closer
    than that to a kept one or to the bounding box are left out, the edges' kept before the
    corners'; so are circles' vertices and a traced contour's that turn less: the lattice
    follows the spacing, not the vertex count (a jagged contour's steps and wiggles, shorter
    than the spacing resolves, add no lines)."""
    loops = []
    domain = tissue.domain
    if isinstance(domain, PolygonDomain) and not domain.edge_names:  # not a rectangle's
        outline = domain.outline
        keep = np.ones(len(outline), dtype=bool)
        for hole in tissue.holes:  # a circle cut into the outline: its vertices and ends on the chords
            if hole.circle is not None:
                r = np.hypot(*(outline - hole.circle.center).T)
                keep &= ((r < hole.circle.radius * np.cos(np.pi / CIRCLE_SEGMENTS) - domain.tolerance)
                         | (r > hole.circle.radius + domain.tolerance))
        loops.append((outline, keep))
    loops += [(np.asarray(hole.polygon, dtype=float), None) for hole in tissue.holes if hole.polygon is not None]
    loops += [(region.vertices(), None) for region in tissue.regions if region.polygon is not None]
    if not loops:
        return [], []
    tol = domain.tolerance
    gap = THIN * (default_spacing_of(tissue.bounding_size, None) if spacing is None else spacing)
    edges, corners = [], []  # (n, 2) vertices whose x / y the lattice follows: edges first
    for loop, keep in loops:
        keep = np.ones(len(loop), dtype=bool) if keep is None else keep
        after = np.roll(loop, -1, axis=0)
        length = np.linalg.norm(after - loop, axis=1)  # (k,) of the edge from each vertex
        long = keep & np.roll(keep, -1) & (length >= gap)
        along = (np.abs(after - loop) <= tol) & long[:, None]  # (k, 2): a long edge along y / x
        edges.append(np.where(along, loop, np.nan))  # x of edges along y, y of those along x
        edges.append(np.where(along, after, np.nan))
        corner = keep & (np.abs(turns(loop)) > CORNER_TURN) & long & np.roll(long, 1)
        corners.append(np.where(corner[:, None], loop, np.nan))
    edges, corners = np.concatenate(edges), np.concatenate(corners)
    low, high = domain.origin, domain.origin + np.asarray(domain.size)
    return tuple(_thinned([low[axis], high[axis]], [edges[:, axis], corners[:, axis]], gap)
                 for axis in (0, 1))


def _thinned(sides: list[float], groups: list[np.ndarray], gap: float) -> list[float]:
    """The coordinates of `groups` (NaN: none) that lie at least `gap` from the bounding box's
    `sides` and from every one kept before them: group by group, each greedily from the
    smallest (a coordinate already kept is that line again)."""
    kept = np.unique(np.asarray(sides, dtype=float))
    for group in groups:
        candidates = np.setdiff1d(group[~np.isnan(group)], kept)  # sorted, without repeats
        index = np.searchsorted(kept, candidates)
        distance = np.minimum(np.abs(candidates - kept[np.maximum(index - 1, 0)]),
                              np.abs(kept[np.minimum(index, len(kept) - 1)] - candidates))
        free = candidates[distance >= gap]
        chosen, i = [], 0
        while i < len(free):  # one step per line kept: at most (extent / gap) steps
            chosen.append(free[i])
            i = int(np.searchsorted(free, free[i] + gap))
        kept = np.union1d(kept, chosen)
    return [float(x) for x in kept if x not in sides]


REENTRANT = 0.2  # rad beyond a straight angle: a corner the solution is singular at


def corner_zones(tissue: Tissue, discretization: Discretization) -> tuple[RefinementZone, ...]:
    """Refinement zones at the re-entrant corners of the tissue (interior angle above
    pi + REENTRANT: a notch's or a hole's corners), graded like the load-segment ends
    (particles.end_spacing: the solution is singular there, r^(~1/2) at a slit's tip);
    none with discretization.segment_end_levels 0. A corner of an edge shorter than THIN x
    the spacing (a jagged traced contour's step, a feature the spacing does not resolve)
    is left as it is, unless the short edge lies between long ones and its two corners
    together turn re-entrant by more than REENTRANT (a jagged step's turns cancel): the tip
    of a slit thinner than that (an incision), singular as one corner, graded at the short
    edge's middle."""
    domain = tissue.domain
    if discretization.segment_end_levels == 0 or not isinstance(domain, PolygonDomain):
        return ()
    fine = end_spacing(discretization.spacing, default_spacing_of(tissue.bounding_size, None),
                       discretization.segment_end_levels)
    zones = []
    for loop in [domain.outline] + [hole[::-1] for hole in domain.holes]:  # tissue on the left
        after = np.roll(loop, -1, axis=0)
        long = np.linalg.norm(after - loop, axis=1) >= THIN * discretization.spacing
        turn = turns(loop)  # > 0: a left turn (convex)
        corner = (turn < -REENTRANT) & long & np.roll(long, 1)
        for vertex in loop[corner]:
            zones.append(RefinementZone(np.asarray(vertex, dtype=float), 0.0, fine))
        # a slit's tip: without it a 0.1 mm slit's walls were 6.4 % off at 1 mm spacing (1.2 %)
        tip = ~long & np.roll(long, 1) & np.roll(long, -1) & (turn + np.roll(turn, -1) < -REENTRANT)
        for a, b in zip(loop[tip], after[tip]):
            zones.append(RefinementZone(0.5 * (np.asarray(a, dtype=float) + b), 0.0, fine))
    return tuple(zones)


# refinement levels toward a round hole at most
HOLE_LEVELS = 5
# a pinhole, its inradius more than 2^PINHOLE_LEVELS below the default spacing, is left at the
# spacing whatever the hole_resolution, its wall's stress peak too small for any output to see (a
# 1 um hole on a plate at 1 mm: graded, 1197 particles against 861, 2.6x the time, the probes
# moved by 0.04 % of the largest displacement); a larger hole needing more levels gets HOLE_LEVELS
PINHOLE_LEVELS = 4


def hole_zones(tissue: Tissue, discretization: Discretization) -> tuple[RefinementZone, ...]:
    """Refinement zones at the round holes (geometry.polygons.is_round) whose wall the default
    spacing does not resolve: the stress round a hole peaks at its wall and falls off over
    about its inradius, which a spacing near that length smooths over (a 1 mm hole in a plate
    was 1.55 % off scikit-fem at its wall at the default spacing; benchmarks/small_holes.py).
    The leaf side at the wall is at most inradius / discretization.hole_resolution at the
    default spacing (min(W, H)/20) and the same number of levels below any other, so that
    `--spacing` refines it with the rest; the zone is a capsule along the hole's longest axis,
    its inradius wide, which holds the hole (a circle's: a disk); at most HOLE_LEVELS levels,
    and in a needle scene no finer than the needle's spacing. None with hole_resolution 0, nor
    for a pinhole (PINHOLE_LEVELS)."""
    domain = tissue.domain
    if discretization.hole_resolution == 0 or not isinstance(domain, PolygonDomain):
        return ()
    reference = default_spacing_of(tissue.bounding_size, None)
    zones = []
    for hole in domain.holes:
        round_hole = RoundHole.of(hole)
        if round_hole is None:  # a hole with corners is graded at them (corner_zones)
            continue
        loop, center, radius, inradius = round_hole.loop, round_hole.center, round_hole.radius, round_hole.inradius
        # 1 % slack: a circle's polygon is resolved where the circle would be
        if np.log2(reference / inradius) - 0.01 > PINHOLE_LEVELS:  # by size: a finer resolution asked grades no less
            continue
        levels = min(int(np.ceil(np.log2(reference * discretization.hole_resolution / inradius) - 0.01)), HOLE_LEVELS)
        if levels <= 0:
            continue
        fine = discretization.spacing / 2**levels
        if discretization.needle_spacing is not None:
            # a needle scene's particles no finer than at the needle: its coupling is set for that
            # spacing, and a patch of much finer ones by the track moved the exit by 1-2 %
            fine = max(fine, discretization.needle_spacing)
            if fine >= discretization.spacing:
                continue
        farthest = loop[np.argmax(np.linalg.norm(loop - center, axis=1))]
        reach = (radius - inradius) / radius * (farthest - center)  # centre to the capsule's end
        if radius - inradius <= 1e-3 * radius:  # a circle's polygon: a disk
            zones.append(RefinementZone(center, radius, fine))
        else:
            zones.append(RefinementZone(center - reach, inradius, fine, center + reach))
    return tuple(zones)


def shape_zones(tissue: Tissue, discretization: Discretization) -> tuple[RefinementZone, ...]:
    """Every refinement zone a shaped tissue's own geometry asks for: re-entrant corners and
    slits' tips (corner_zones), material interfaces (interface_zones), unresolved round holes
    (hole_zones)."""
    return (*corner_zones(tissue, discretization), *interface_zones(tissue, discretization),
            *hole_zones(tissue, discretization))


# pieces of a region edge at most: where the edge leaves the tissue, its zone ends within
# 1/INTERFACE_PIECES of the edge's length from there
INTERFACE_PIECES = 4096


def interface_zones(tissue: Tissue, discretization: Discretization) -> tuple[RefinementZone, ...]:
    """Refinement zones along the material interfaces: the pieces of the regions' edges with
    tissue of different materials on their two sides (not where an edge runs along the
    boundary, lies outside the tissue or inside a region listed before it), graded like the
    load-segment ends (particles.end_spacing from discretization.interface_levels). The
    displacement has a kink there that the smooth RK functions spread over their support, an
    error of order h in a band along the interface that pollutes the whole field; graded, the
    band narrows like the end spacing, h^2 (benchmarks/layer_contrast.py). None with
    interface_levels 0."""
    if discretization.interface_levels == 0 or not tissue.regions:
        return ()
    fine = end_spacing(discretization.spacing, default_spacing_of(tissue.bounding_size, None),
                       discretization.interface_levels)
    materials = [tissue.material, *(region.material for region in tissue.regions)]
    domain = tissue.domain
    starts = np.concatenate([region.vertices() for region in tissue.regions])
    ends = np.concatenate([np.roll(region.vertices(), -1, axis=0) for region in tissue.regions])
    # each edge tested in pieces of half the fine spacing (at most INTERFACE_PIECES); a run of
    # kept pieces is one zone
    pieces = np.clip(np.ceil(np.hypot(*(ends - starts).T) / (0.5 * fine)), 1, INTERFACE_PIECES).astype(int)
    edge = np.repeat(np.arange(len(starts)), pieces)
    t = (concatenated_ranges(np.zeros(len(pieces), dtype=int), pieces) + 0.5) / pieces[edge]
    middles = starts[edge] + t[:, None] * (ends - starts)[edge]
    along = (ends - starts)[edge]
    normal = np.column_stack([-along[:, 1], along[:, 0]]) / np.hypot(*along.T)[:, None] * 10.0 * domain.tolerance
    sides = np.concatenate([middles + normal, middles - normal])
    inside = domain.contains(sides).reshape(2, -1).all(axis=0)
    which = (region_index(tissue, sides) + 1).reshape(2, -1)
    material_id = np.array([materials.index(material) for material in materials])  # equal materials: one id
    kept = inside & (material_id[which[0]] != material_id[which[1]])
    zones = []
    first_piece = np.concatenate([[0], np.cumsum(pieces)])
    for k, (a, b) in enumerate(zip(starts, ends)):
        flags = kept[first_piece[k]:first_piece[k + 1]].astype(int)
        jumps = np.diff(np.concatenate([[0], flags, [0]]))  # runs of kept pieces: [first, last)
        for first, last in zip(np.flatnonzero(jumps == 1), np.flatnonzero(jumps == -1)):
            zones.append(RefinementZone(a + first / pieces[k] * (b - a), 0.0, fine, a + last / pieces[k] * (b - a)))
    return tuple(zones)


def cutting_edges(tissue: Tissue) -> tuple[np.ndarray, np.ndarray]:
    """Start and end points (n, 2) of every edge that cuts background cells: the boundary
    and the regions' edges."""
    domain = tissue.domain
    starts = [np.array([a for a, _ in domain.boundary_segments()])]
    ends = [np.array([b for _, b in domain.boundary_segments()])]
    for region in tissue.regions:
        vertices = region.vertices()
        starts.append(vertices)
        ends.append(np.roll(vertices, -1, axis=0))
    return np.concatenate(starts), np.concatenate(ends)


def cells_cut(cells: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """Mask (nc,) of cells (x0, y0, width, height) whose open interior some edge passes
    through (Liang-Barsky clipping, against the cell shrunk by round-off, of the edges whose
    boxes meet the cell: geometry.edge_grid.EdgeGrid)."""
    cut = np.zeros(len(cells), dtype=bool)
    if len(starts) == 0 or len(cells) == 0:
        return cut
    delta = ends - starts  # (ns, 2)
    pad = 1e-9 * float(np.max(np.abs(cells[:, 2:])))
    for cell, edge in EdgeGrid.of(starts, ends).pairs(cells[:, :2] - pad, cells[:, :2] + cells[:, 2:] + pad):
        c, start, d = cells[cell], starts[edge], delta[edge]  # one row per (cell, edge) pair
        shrink = 1e-9 * np.maximum(c[:, 2], c[:, 3])
        low_x, high_x = c[:, 0] + shrink, c[:, 0] + c[:, 2] - shrink
        low_y, high_y = c[:, 1] + shrink, c[:, 1] + c[:, 3] - shrink
        t0 = np.zeros(len(c))
        t1 = np.ones_like(t0)
        reject = np.zeros_like(t0, dtype=bool)
        for p, q in ((-d[:, 0], start[:, 0] - low_x), (d[:, 0], high_x - start[:, 0]),
                     (-d[:, 1], start[:, 1] - low_y), (d[:, 1], high_y - start[:, 1])):
            parallel = p == 0.0
            reject |= parallel & (q < 0.0)
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.where(parallel, 0.0, q / np.where(parallel, 1.0, p))
            t0 = np.where(~parallel & (p < 0.0), np.maximum(t0, t), t0)
            t1 = np.where(~parallel & (p > 0.0), np.minimum(t1, t), t1)
        cut[cell[~reject & (t0 < t1)]] = True
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


def fit_particles(tissue: Tissue, graded: GradedParticles,
                  spacing_at: Callable[[np.ndarray], np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lattice's particles inside a polygon tissue plus particles along the boundary at
    the local spacing (boundary_points: every corner one of them); lattice particles closer
    than MERGE x the local spacing to an added one are dropped. `spacing_at`: the lattice's
    lattice_spacing. Returns particles, volumes, local spacing."""
    from scipy.spatial import cKDTree  # here: a rectangle's commands need not import scipy.spatial

    domain = tissue.domain
    tol = 1e-7 * max(domain.size)
    keep = domain.contains(graded.particles, tol)
    particles, volumes, local = graded.particles[keep], graded.volumes[keep], graded.local_spacing[keep]
    kept = kept_vertices(tissue, spacing_at(domain.segment_starts))
    added = boundary_points(domain, kept, spacing_at, float(graded.local_spacing.min()))
    added_local = spacing_at(added)
    # an added particle onto a lattice particle on the boundary (a lattice line along the edge):
    # keep the lattice's; one just inside gives way to the added one below, so that the boundary
    # (a clamp, a displacement segment) is held at every local spacing along it
    on_boundary = domain.near_boundary(particles, tol)
    if on_boundary.any():
        distance, _ = cKDTree(particles[on_boundary]).query(added)
    else:
        distance = np.full(len(added), np.inf)
    new = distance > MERGE * added_local
    # nor between the lattice's particles on an edge along a lattice line, which already
    # stand there one local spacing apart: added ones would halve that spacing along the edge,
    # a dilation of 4 there, whose alternating mode the stiffness barely resists
    # (hole_near_stitch's top edge at 0.75 mm: K0's condition number ~3e13); a kept vertex
    # stays whatever its distance
    new &= ~_between_lattice_particles(domain, particles[on_boundary], added, added_local, kept, tol)
    added, added_local = added[new], added_local[new]
    if len(added):
        # lattice particles just inside the boundary next to an added one would nearly coincide
        distance, index = cKDTree(added).query(particles)
        crowded = (distance < MERGE * added_local[index]) & ~on_boundary
        particles, volumes, local = particles[~crowded], volumes[~crowded], local[~crowded]
    particles = np.concatenate([particles, added])
    volumes = np.concatenate([volumes, 0.5 * added_local**2])  # half a cell: the other half is outside
    local = np.concatenate([local, added_local])
    return particles, volumes, local


def _between_lattice_particles(domain: PolygonDomain, on_boundary: np.ndarray, added: np.ndarray,
                               added_local: np.ndarray, kept: np.ndarray, tol: float) -> np.ndarray:
    """Mask (n,) of the `added` boundary points within ALONG x their local spacing of a
    lattice particle on the boundary (`on_boundary`, (m, 2)) on the same edge (the midpoint
    between the two on the boundary: not one across a thin strip of tissue), kept vertices
    (mask over domain.segment_starts) excepted."""
    from scipy.spatial import cKDTree

    crowded = np.zeros(len(added), dtype=bool)
    if len(on_boundary) == 0 or len(added) == 0:
        return crowded
    nearest = min(NEAREST_ALONG, len(on_boundary))
    distance, index = cKDTree(on_boundary).query(added, nearest)  # (n, k): a few candidates each
    distance, index = distance.reshape(len(added), nearest), index.reshape(len(added), nearest)
    for k in range(nearest):  # a few columns
        close = np.flatnonzero(distance[:, k] <= ALONG * added_local)
        middle = 0.5 * (added[close] + on_boundary[index[close, k]])
        crowded[close[domain.near_boundary(middle, tol)]] = True
    if np.any(kept):
        crowded &= cKDTree(domain.segment_starts[kept]).query(added)[0] > tol
    return crowded


def lattice_spacing(graded: GradedParticles):
    """The local spacing of the lattice at points (n, 2): that of the nearest lattice particle."""
    from scipy.spatial import cKDTree

    tree = cKDTree(graded.particles)
    return lambda points: graded.local_spacing[tree.query(np.asarray(points, dtype=float).reshape(-1, 2))[1]]


def kept_vertices(tissue: Tissue, spacing_at: np.ndarray | None = None) -> np.ndarray:
    """Mask over the boundary edges' start vertices (domain.segment_starts) that carry a
    boundary particle: the corners (a turn above geometry.polygons.CORNER_TURN) but those closer than
    MERGE x the local spacing there (`spacing_at`, (E,)) to the corner before them, the ends
    of clamped pieces, and with `spacing_at` the vertices circle_vertices picks round each
    circular hole (not all CIRCLE_SEGMENTS of them). A traced contour's vertices that turn
    less, and the crowded corners of a jagged one, are passed by at the local spacing."""
    domain = tissue.domain
    vertices = domain.segment_starts
    loops = [domain.outline] + [hole[::-1] for hole in domain.holes]  # as segment_starts
    loop = np.repeat(np.arange(len(loops)), [len(vertices_of) for vertices_of in loops])
    corner = np.flatnonzero(np.abs(np.concatenate([turns(vertices_of) for vertices_of in loops])) > CORNER_TURN)
    kept = np.zeros(len(vertices), dtype=bool)
    kept[corner] = True
    if spacing_at is not None and len(corner):
        # the corner before each one in its loop (the loop's last before its first)
        last_of_loop = np.full(len(loops), -1)
        np.maximum.at(last_of_loop, loop[corner], np.arange(len(corner)))
        before = np.roll(np.arange(len(corner)), 1)
        starts_loop = np.concatenate([[True], loop[corner][1:] != loop[corner][:-1]])
        before[starts_loop] = last_of_loop[loop[corner][starts_loop]]
        gap = np.linalg.norm(vertices[corner] - vertices[corner[before]], axis=1)
        kept[corner[(gap > 0.0) & (gap < MERGE * spacing_at[corner])]] = False
    for start, end in tissue.clamped_pieces():  # a clamped piece holds the particles at its ends
        kept |= (np.linalg.norm(vertices - start, axis=1) <= domain.tolerance) | \
            (np.linalg.norm(vertices - end, axis=1) <= domain.tolerance)
    if spacing_at is not None:  # a circle's vertex next to a corner (where it crosses the outline) yields
        circle = np.flatnonzero(circle_vertices(tissue, spacing_at) & ~kept)
        if np.any(kept) and len(circle):
            from scipy.spatial import cKDTree

            distance, _ = cKDTree(vertices[kept]).query(vertices[circle])
            circle = circle[distance >= MERGE * spacing_at[circle]]
        kept[circle] = True
    return kept


BESIDE_THIN = 2.0  # x the local spacing: a circle's wall with less tissue beyond it than this ...
DENSE = 1.0 / 2**CUT_LEVELS  # x the local spacing: ... keeps its vertices this far apart (the finest cut cell)


def circle_vertices(tissue: Tissue, spacing_at: np.ndarray) -> np.ndarray:
    """Mask over domain.segment_starts of the circular holes' vertices that carry a particle:
    those with less than BESIDE_THIN x the local spacing h (`spacing_at`, (E,)) of tissue
    beyond them (along the wall's normal, to the next boundary), every k-th of them so that
    they stand at least DENSE x h apart (one vertex of a circle far below h); none elsewhere,
    where the wall is followed one local spacing apart as any edge (boundary_points).

    The visibility criterion (shape_functions.Visibility) weighs the pairs through a round
    hole by the way round it, and blocks those through a hole cut into the outline, part of
    the outline: a point near such a wall sees, of the wall's particles, those at the ends of
    the edge it is next to and few more.
    Where the tissue beyond the wall is thick, particles there cover the point; in a strip
    under a spacing or two thick (a hole near the outline or near another, a hole cut into
    the outline at a shallow angle) the other side's particles may be all it sees, on one
    line: with particles one spacing apart round it, a 6 mm hole 0.9 to 1.35 mm below the
    edge of a block gave a singular moment matrix at 1.5 mm; with these, no strip over a
    hole of 3 to 12 mm did from 0.45 x the spacing on (tissue.thin_features refuses less
    than 0.5). Elsewhere the 96 vertices only crowd the wall (a 4 mm hole's 0.13 mm apart at
    5 mm), and a hole far below the spacing with them: a 1 um hole moved a probe 60 mm away
    by 1.25 %, one of 0.1 um stopped Newton; now one particle, < 0.01 %
    (tests/test_thin_features.py)."""
    domain = tissue.domain
    vertices = domain.segment_starts
    kept = np.zeros(len(vertices), dtype=bool)
    for hole in tissue.holes:
        if hole.circle is None:
            continue
        center, radius = np.asarray(hole.circle.center, dtype=float), float(hole.circle.radius)
        offset = vertices - center
        on = np.flatnonzero(np.abs(np.hypot(*offset.T) - radius) <= domain.tolerance)  # inside or cut into the outline
        if len(on) == 0:
            continue
        beside_thin = on[wall_thickness(tissue, on, BESIDE_THIN * spacing_at[on]) < BESIDE_THIN * spacing_at[on]]
        if len(beside_thin) == 0:
            continue
        arc = 2.0 * np.pi * radius / CIRCLE_SEGMENTS
        every = int(min(np.ceil(DENSE * float(spacing_at[beside_thin].min()) / arc), CIRCLE_SEGMENTS))
        index = np.rint(np.arctan2(offset[beside_thin, 1], offset[beside_thin, 0]) * CIRCLE_SEGMENTS
                        / (2.0 * np.pi)).astype(int) % CIRCLE_SEGMENTS
        kept[beside_thin[index % every == 0]] = True
    return kept


def boundary_points(domain: PolygonDomain, kept: np.ndarray, spacing_at, finest: float) -> np.ndarray:
    """Points (n, 2) along every boundary loop one local spacing apart, a kept vertex (mask
    over domain.segment_starts) one of them: each loop is walked in runs from one kept vertex
    to the next (a loop with none from its first vertex), and a run's points lie where the
    count of spacings int ds / h(s) (h = `spacing_at`, the lattice's lattice_spacing,
    sampled 8 times per `finest` spacing) passes a multiple of its total / round(total). A run
    of one edge gives the same numbers as that edge taken alone."""
    starts, ends = domain.segment_starts, domain.segment_ends
    sizes = np.array([len(domain.outline)] + [len(hole) for hole in domain.holes])
    loop = np.repeat(np.arange(len(sizes)), sizes)  # (E,)
    position = np.arange(len(starts)) - (np.cumsum(sizes) - sizes)[loop]
    kept = kept | (position == 0) & (np.bincount(loop, weights=kept, minlength=len(sizes)) == 0)[loop]
    first_kept = np.full(len(sizes), len(starts))
    np.minimum.at(first_kept, loop[kept], position[kept])
    order = np.lexsort(((position - first_kept[loop]) % sizes[loop], loop))  # each loop from its first kept vertex
    a, b, kept = starts[order], ends[order], kept[order]
    edge_length = np.linalg.norm(b - a, axis=1)
    first = np.flatnonzero(kept)  # (R,) first edge of each run
    single = np.diff(np.append(first, len(a))) == 1
    length = np.add.reduceat(edge_length, first)
    # samples t in [0, 1] along each run, as np.linspace(0, 1, intervals + 1)
    intervals = np.maximum(np.ceil(8 * length / finest).astype(int), 2)
    run = np.repeat(np.arange(len(first)), intervals + 1)
    step = concatenated_ranges(np.zeros(len(first), dtype=int), intervals + 1)
    t = step * (1.0 / intervals)[run]
    t[step == intervals[run]] = 1.0
    density = 1.0 / spacing_at(_along_runs(a, b, edge_length, first, single, length, run, t))
    within = run[1:] == run[:-1]  # consecutive samples of one run
    increment = (0.5 * (density[1:] + density[:-1]) * np.diff(t) * length[run[1:]])[within]
    count = np.zeros(len(t))
    count[step > 0] = _cumsum_by_run(increment, intervals)  # int ds / h from each run's start
    total_count = count[step == intervals[run]]
    total = np.maximum(np.rint(total_count).astype(int), 1)  # the run's end is the next run's start
    point_run = np.repeat(np.arange(len(first)), total)
    target = concatenated_ranges(np.zeros(len(first), dtype=int), total) * total_count[point_run] / total[point_run]
    t_points = _interp_by_run(target, point_run, count, t, run)
    return _along_runs(a, b, edge_length, first, single, length, point_run, t_points)


def _along_runs(a, b, edge_length, first, single, length, run, t) -> np.ndarray:
    """Points (n, 2) at the fractions t (n,) of the arc length of runs `run` (n,): a run of
    one edge as start + t (end - start), a longer one through the edge holding the arc."""
    edge = first[run]
    fraction = t.copy()
    longer = ~single[run]
    if np.any(longer):
        before = np.cumsum(edge_length) - edge_length  # (E,) arc length up to each edge
        arc = before[edge[longer]] + t[longer] * length[run[longer]]
        last = np.append(first[1:], len(a))[run[longer]] - 1
        holder = np.clip(np.searchsorted(before, arc, side="right") - 1, edge[longer], last)
        edge[longer] = holder
        fraction[longer] = np.clip((arc - before[holder]) / edge_length[holder], 0.0, 1.0)
    return a[edge] + fraction[:, None] * (b[edge] - a[edge])


def _cumsum_by_run(values: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The cumulative sums of `values` within each run of `counts` consecutive entries, each
    summed in order as np.cumsum of that run alone: runs of lengths in one octave padded into
    one (runs, longest) array."""
    out = np.empty(len(values))
    offsets = np.cumsum(counts) - counts
    octave = np.ceil(np.log2(np.maximum(counts, 1))).astype(int)
    for level in np.unique(octave[counts > 0]):  # a few octaves of run lengths
        rows = np.flatnonzero((octave == level) & (counts > 0))
        columns = np.arange(counts[rows].max())
        valid = columns[None, :] < counts[rows, None]  # (runs, longest)
        index = offsets[rows, None] + columns[None, :]
        padded = np.where(valid, values[np.where(valid, index, 0)], 0.0)
        out[index[valid]] = np.cumsum(padded, axis=1)[valid]
    return out


def _interp_by_run(x: np.ndarray, x_run: np.ndarray, xp: np.ndarray, fp: np.ndarray, xp_run: np.ndarray) -> np.ndarray:
    """np.interp(x, xp, fp) within each run (xp increasing within a run, runs in order, x at
    or after its run's first xp), with np.interp's arithmetic: the same numbers run by run."""
    kind = np.concatenate([np.zeros(len(xp), dtype=int), np.ones(len(x), dtype=int)])
    order = np.lexsort((kind, np.concatenate([xp, x]), np.concatenate([xp_run, x_run])))
    at_or_below = np.cumsum(kind[order] == 0)  # xp entries sorted at or before each position
    j = np.empty(len(x), dtype=int)
    is_x = kind[order] == 1
    j[order[is_x] - len(xp)] = at_or_below[is_x] - 1  # the last xp <= x of its run
    last = np.append(np.flatnonzero(np.diff(xp_run)), len(xp) - 1)[x_run]
    following = np.minimum(j + 1, len(xp) - 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = (fp[following] - fp[j]) / (xp[following] - xp[j])
        value = slope * (x - xp[j]) + fp[j]
    return np.where((j == last) | (xp[j] == x), fp[j], value)


def region_index(tissue: Tissue, points: np.ndarray) -> np.ndarray:
    """Index of the region holding each point (n,): the first that holds it, -1 for the
    tissue's own material."""
    index = np.full(len(points), -1)
    for k in range(len(tissue.regions) - 1, -1, -1):  # the first region wins: assign it last
        vertices = tissue.regions[k].vertices()
        region = PolygonDomain(vertices if _ccw(vertices) else vertices[::-1].copy())
        index[region._inside_strict(points)] = k
    return index


def _ccw(vertices: np.ndarray) -> bool:
    x, y = vertices[:, 0], vertices[:, 1]
    return float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)) > 0
