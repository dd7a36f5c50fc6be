"""Reproducing-kernel shape functions and their exact gradients (thesis eq. 3.18-3.23).

Shape functions are evaluated in the reference configuration once per discretization and
stored as sparse (points x particles) matrices, so the Total-Lagrangian solver only ever
multiplies by them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp

from .kernel import tensor_kernel
from .neighbours import CellGrid
from ..errors import SingularMomentMatrix
from ..geometry.polygons import around_convex, is_round, round_extent, segments_enter_convex


class SingularMomentAt(SingularMomentMatrix):
    """A singular moment matrix at `point` (mm), which the model's build looks at to say why
    (too few particles, or particles on one line across tissue thinner than the spacing)."""

    def __init__(self, message: str, point: np.ndarray):
        super().__init__(message)
        self.point = np.asarray(point, dtype=float).copy()

    def __reduce__(self):  # pickled as it was made: replays send their failures between processes
        return type(self), (str(self), self.point)


@dataclass(frozen=True)
class ShapeFunctions:
    """RK shape functions N_I(X) at a set of points; each matrix is (n_points, n_particles)."""

    values: sp.csr_matrix
    grad_x: sp.csr_matrix | None = None
    grad_y: sp.csr_matrix | None = None


def basis_size(order: int) -> int:
    return {1: 3, 2: 6}[order]


def _basis(y: np.ndarray, order: int) -> np.ndarray:
    """Basis H(Y) of eq. 3.21; y (n, 2) -> H (n, m). Filled by columns: few array
    operations, as tip tracking evaluates single points."""
    n, m = len(y), basis_size(order)
    y1, y2 = y[:, 0], y[:, 1]
    h = np.empty((n, m))
    h[:, 0] = 1.0
    h[:, 1:3] = y
    if order == 2:
        h[:, 3], h[:, 4], h[:, 5] = y1 * y1, y1 * y2, y2 * y2
    return h


def _derivative_maps(order: int) -> np.ndarray:
    """D (2, m, m) with dH/dY_k = D[k] H: the monomial basis is closed under
    differentiation, so the basis gradient is a constant map of the basis itself."""
    m = basis_size(order)
    d = np.zeros((2, m, m))
    d[0, 1, 0] = d[1, 2, 0] = 1.0  # d y1/d y1, d y2/d y2
    if order == 2:  # y1^2, y1 y2, y2^2
        d[0, 3, 1], d[0, 4, 2] = 2.0, 1.0
        d[1, 4, 1], d[1, 5, 2] = 1.0, 2.0
    return d


def _triangle(order: int) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray]:
    """The upper triangle of an m x m symmetric matrix: its (row, column) indices, and for
    each of the m x m entries the index of its triangle entry."""
    m = basis_size(order)
    rows, cols = np.triu_indices(m)
    full = np.empty((m, m), dtype=np.int64)
    full[rows, cols] = full[cols, rows] = np.arange(len(rows))
    return (rows, cols), full


_TRIANGLES = {order: _triangle(order) for order in (1, 2)}
_MAPS = {order: _derivative_maps(order) for order in (1, 2)}


@dataclass(frozen=True, eq=False)
class RoundHole:
    """A round hole (geometry.polygons.is_round) as the visibility criterion weighs the
    pairs through it and the particles are graded toward it (tissue.shapes.hole_zones): a
    counter-clockwise `loop` (k, 2) about `center`, within `radius` of it, and no edge nearer
    than `inradius`."""

    loop: np.ndarray
    center: np.ndarray  # (2,) its vertices' mean
    radius: float
    inradius: float

    @classmethod
    def of(cls, hole) -> RoundHole | None:
        """The hole (k, 2) as a round one, or None where it is not round."""
        loop = np.asarray(hole, dtype=float)
        if not is_round(loop):
            return None
        return cls(loop, *round_extent(loop))

    def crossing(self, starts: np.ndarray, ends: np.ndarray, tol: float) -> np.ndarray:
        """Mask of the segments (n, 2)-(n, 2) that pass through the hole: those passing
        nearer its centre than its nearest edge do, those passing no nearer than its farthest
        vertex do not, the others are clipped against its edges (crossed)."""
        along = ends - starts
        t = np.clip(np.einsum("nd,nd->n", self.center - starts, along)
                    / np.maximum(np.einsum("nd,nd->n", along, along), 1e-300), 0.0, 1.0)
        closest = starts + t[:, None] * along - self.center
        distance = np.sqrt(np.einsum("nd,nd->n", closest, closest))
        crossing = distance < self.inradius - tol
        band = np.flatnonzero(~crossing & (distance < self.radius))
        if len(band):
            crossing[band] = self.crossed(starts[band], ends[band], tol)
        return crossing

    def crossed(self, starts: np.ndarray, ends: np.ndarray, tol: float) -> np.ndarray:
        """Mask of the segments (n, 2)-(n, 2) that pass through the hole, made in parts of at
        most PAIRS_AT_ONCE segment-edge entries."""
        crossed = np.empty(len(starts), dtype=bool)
        for part in np.array_split(np.arange(len(starts)), max(1, -(-len(starts) * len(self.loop) // PAIRS_AT_ONCE))):
            crossed[part] = segments_enter_convex(starts[part], ends[part], self.loop, tol)
        return crossed


PAIRS_AT_ONCE = 2_000_000  # pair x edge entries of a round hole's crossing test made at once


@dataclass(frozen=True, eq=False)
class Visibility:
    """The visibility criterion on a non-convex tissue: a particle does not interact with a
    point when the straight segment between them leaves the tissue (crosses the boundary of
    a hole or a notch), so material across a gap never shares shape functions.

    A round hole (geometry.polygons.is_round: convex, no corner; a circle, an ellipse) blocks
    no pair: a pair whose segment passes through it is weighed by the way round it
    (`stretch`: the kernel of the offset stretched by that way over the straight length), so
    that the shape functions stay continuous where a segment starts to cross the hole and
    fade as the way round grows past the support (the diffraction method's idea, with the
    wall's tangents). Blocking such pairs made the functions jump along every line that
    grazes the wall: tested for every pair, the wall hid its own particles from the points
    next to it (a plate with a 5 mm circular hole was 0.80 and 0.55 % off scikit-fem at the
    wall at spacings 1 and 0.5 mm, and had a singular moment matrix at 0.45 mm); tested for the
    pairs at least as long as a circle is wide, a 3 mm hole among particles 2 mm apart was
    3.22 % off at its wall, 2.17 % weighed, and a 10 x 1.5 mm ellipse, blocked, 21 % at 2 mm
    and refused at 1.5 mm (a singular moment matrix), 7.8 % weighed
    (benchmarks/results/small_holes.md). A hole with a corner blocks every pair through it:
    the solution is singular at the corner, and the criterion keeps the functions from
    reaching round it (a plate with an 8 mm square hole was 0.101 % off scikit-fem so,
    0.197 % weighed by the way round its corners: benchmarks/results/cornered_holes.md).

    `clearance` (NP,) is each particle's distance to `domain` (the outline and the holes with
    a corner): a segment shorter than it cannot reach them, only the others are tested."""

    domain: object  # geometry.polygon_domain.PolygonDomain, or None when it has only round holes
    clearance: np.ndarray
    round_holes: tuple[RoundHole, ...] = ()
    tol: float = 0.0  # mm, how far a segment must pass into a round hole to cross it

    @classmethod
    def of(cls, domain, particles: np.ndarray, tested: np.ndarray | None = None) -> Visibility | None:
        """The criterion on `domain` (a Rectangle or a PolygonDomain) for `particles` (NP, 2),
        their clearance computed for the indices `tested` only where given (the others 0,
        every pair of theirs tested); None on a convex tissue."""
        holes = getattr(domain, "holes", ())
        if getattr(domain, "convex", True):
            return None
        rounds = [RoundHole.of(hole) for hole in holes]
        round_holes = tuple(hole for hole in rounds if hole is not None)
        cornered = replace(domain, holes=tuple(hole for hole, as_round in zip(holes, rounds) if as_round is None))
        clearance = np.full(len(particles), np.inf)
        if cornered.convex:
            cornered = None
        else:
            chosen = np.arange(len(particles)) if tested is None else tested
            clearance[:] = 0.0
            clearance[chosen] = cornered.distance(particles[chosen])
        return cls(cornered, clearance, round_holes, 1e-7 * max(domain.width, domain.height))

    def keep(self, points: np.ndarray, particles: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Mask of the pairs (rows: points, cols: particles) that see each other."""
        starts, ends = points[rows], particles[cols]
        length = np.linalg.norm(ends - starts, axis=1)
        keep = np.ones(len(rows), dtype=bool)
        if self.domain is not None:
            test = np.flatnonzero(length >= self.clearance[cols])
            if len(test):
                keep[test] = ~self.domain.blocked(starts[test], ends[test])
        return keep

    def stretch(self, points: np.ndarray, particles: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                offset: np.ndarray, reach: float) -> Stretch | None:
        """The pairs (rows: points, cols: particles, offset X - X_I) whose segment crosses a
        round hole, each with the way round the hole over its straight length (Stretch);
        None where none does. `reach`: the longest pair's length, which bounds the points
        looked at."""
        if not self.round_holes:
            return None
        crossed = extra = extra_gradient = None  # each pair's way round the holes less its length, and its gradient
        for hole in self.round_holes:  # the pairs whose point is near enough to the hole, and not inside it
            squared = np.einsum("nd,nd->n", points - hole.center, points - hole.center)
            close = (squared < (hole.radius + reach) ** 2) & (squared >= hole.inradius ** 2)
            test = np.flatnonzero(close[rows])
            if not len(test):
                continue
            starts, ends = points[rows[test]], particles[cols[test]]
            crossing = hole.crossing(starts, ends, self.tol)
            if not crossing.any():
                continue
            test = test[crossing]
            around, around_gradient = around_convex(starts[crossing], ends[crossing], hole.loop, hole.center)
            length = np.linalg.norm(offset[test], axis=1)
            if crossed is None:  # lazily: most tissues' pairs cross no hole
                crossed, extra, extra_gradient = np.zeros(len(rows), bool), np.zeros(len(rows)), np.zeros((len(rows), 2))
            crossed[test] = True
            extra[test] += around - length
            extra_gradient[test] += around_gradient - offset[test] / length[:, None]
        if crossed is None:
            return None
        crossing = np.flatnonzero(crossed)
        length = np.linalg.norm(offset[crossing], axis=1)
        unit = offset[crossing] / length[:, None]
        # s = way / length, ds/dX = (dway/dX - s unit) / length, dway/dX = unit + the extra's gradient
        ratio = (length + extra[crossing]) / length
        return Stretch(crossing, ratio, (unit + extra_gradient[crossing] - ratio[:, None] * unit) / length[:, None])


@dataclass(frozen=True)
class Stretch:
    """The pairs whose segment crosses a round hole: their indices (c,), the way round the
    hole over the straight length s (c,) >= 1, and ds/dX (c, 2). Their kernel is that of the
    offset stretched by s, so that a pair's weight falls continuously to 0 as the segment
    starts to cross a hole and the way round grows (diffraction of the visibility criterion)."""

    pairs: np.ndarray
    ratio: np.ndarray
    gradient: np.ndarray


MANY_POINTS = 64  # from here on neighbour_pairs searches each support group on its own cells
SUPPORT_GROUPS_PER_OCTAVE = 2  # ParticleSearch: particles whose supports differ by < 2^(1/2) share cells


@dataclass(frozen=True, eq=False)
class ParticleSearch:
    """The particles on square cells (neighbours.CellGrid) by kernel support. A graded
    arrangement has supports from the coarse spacing down to a fraction of the finest one;
    searching every point's neighbours within the largest support would return, where the
    particles are fine, hundreds of particles whose own supports do not reach the point. For
    many points each group of similar supports (within a factor 2^(1 / SUPPORT_GROUPS_PER_OCTAVE))
    is searched on cells of its own largest support; a few points (tip tracking asks for one)
    search the cells of all particles, which costs fewer calls."""

    everyone: CellGrid  # all particles, cells of the largest support
    groups: tuple[CellGrid, ...]  # per group its particles, on cells of the group's largest support

    @classmethod
    def of(cls, particles: np.ndarray, support: np.ndarray) -> ParticleSearch:
        octaves = np.log2(support.max() / support)
        group = np.floor(octaves * SUPPORT_GROUPS_PER_OCTAVE + 1e-9).astype(np.int64)
        groups = []
        for label in np.unique(group):
            members = np.flatnonzero(group == label)
            groups.append(CellGrid.of(particles, float(support[members].max()), members))
        return cls(CellGrid.of(particles, float(support.max())), tuple(groups))

    def candidates(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(point, particle) index pairs with |X - X_I|_inf <= the largest support of I's
        group (of all particles, for a few points), sorted by point, then particle."""
        if len(points) <= MANY_POINTS or len(self.groups) == 1:
            grid = self.everyone if len(points) <= MANY_POINTS else self.groups[0]
            return grid.within(points, grid.size)  # ordered so already
        count = len(self.everyone.x)
        pairs = [grid.within(points, grid.size) for grid in self.groups]
        # by point, then particle: a merge of the groups' sorted runs (timsort finds them)
        merged = np.sort(np.concatenate([rows * count + cols for rows, cols in pairs]), kind="stable")
        return merged // count, merged % count

    def nearest(self, points: np.ndarray) -> np.ndarray:
        """The index of each point's nearest particle, (n,)."""
        return self.everyone.nearest(points)

    def around(self, point: np.ndarray, support: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The particles I whose support reaches one point, |X - X_I|_inf < a_I (with
        _pairs_and_offsets' margin), ascending, and their offsets X - X_I (k, 2): the
        candidates' filter and the support test in one pass (tip tracking asks for one point
        at a time)."""
        grid = self.everyone
        x, y = point.tolist()
        start, end = grid.block(x, y)
        candidates = grid.blocks[start:end]
        offset = np.empty((end - start, 2))
        np.subtract(x, grid.block_x[start:end], out=offset[:, 0])
        np.subtract(y, grid.block_y[start:end], out=offset[:, 1])
        keep = np.flatnonzero((np.abs(offset) < (support[candidates] * (1.0 - 1e-9))[:, None]).all(axis=1))
        return candidates[keep], offset[keep]


def neighbour_pairs(
    points: np.ndarray, particles: np.ndarray, support: np.ndarray, search: ParticleSearch | None = None,
    visibility: Visibility | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All (point, particle) pairs with |X - X_I|_inf < a_I, grouped by point; with
    `visibility`, only the pairs that see each other through the tissue.

    Returns (point_index, particle_index, indptr) where indptr delimits each point's pairs.
    """
    rows, cols, indptr, _, _ = _pairs_and_offsets(points, particles, support, search, visibility)
    return rows, cols, indptr


def _pairs_and_offsets(points, particles, support, search, visibility):
    """neighbour_pairs, and each pair's offset X - X_I (pairs, 2)."""
    search = search if search is not None else ParticleSearch.of(particles, support)
    if len(points) == 1:
        cols, offset = search.around(points[0], support)
        rows = np.zeros(len(cols), dtype=np.int64)
        if visibility is not None:
            keep = visibility.keep(points, particles, rows, cols)
            rows, cols, offset = rows[keep], cols[keep], offset[keep]
        rows, cols, offset, stretch = _stretched(points, particles, support, visibility, rows, cols, offset)
        return rows, cols, np.array([0, len(cols)]), offset, stretch
    rows, cols = search.candidates(points)
    offset = np.take(points, rows, axis=0) - np.take(particles, cols, axis=0)  # take: faster than [] here
    # the kernel vanishes at |z| = 1; a relative margin keeps particles that sit on the
    # support edge (dilation 2 on a regular grid) out regardless of rounding
    reach = support[cols] * (1.0 - 1e-9)
    keep = (np.abs(offset[:, 0]) < reach) & (np.abs(offset[:, 1]) < reach)
    if not keep.all():
        rows, cols, offset = rows[keep], cols[keep], offset[keep]
    if visibility is not None:
        keep = visibility.keep(points, particles, rows, cols)
        rows, cols, offset = rows[keep], cols[keep], offset[keep]
    rows, cols, offset, stretch = _stretched(points, particles, support, visibility, rows, cols, offset)
    indptr = np.zeros(len(points) + 1, dtype=np.int64)
    np.cumsum(np.bincount(rows, minlength=len(points)), out=indptr[1:])
    return rows, cols, indptr, offset, stretch


def _stretched(points, particles, support, visibility, rows, cols, offset):
    """The pairs without those whose way round a round hole leaves the kernel's support, and
    the remaining ones' Stretch (None where no pair crosses a round hole)."""
    if visibility is None or not visibility.round_holes or not len(rows):
        return rows, cols, offset, None
    reach = float(np.sqrt(2.0) * support.max())
    stretch = visibility.stretch(points, particles, rows, cols, offset, reach)
    if stretch is None:
        return rows, cols, offset, None
    index = stretch.pairs
    outside = np.max(np.abs(offset[index]), axis=1) * stretch.ratio >= support[cols[index]] * (1.0 - 1e-9)
    if outside.any():
        keep = np.ones(len(rows), dtype=bool)
        keep[index[outside]] = False
        renumbered = np.cumsum(keep) - 1
        inside = ~outside
        stretch = Stretch(renumbered[index[inside]], stretch.ratio[inside], stretch.gradient[inside])
        rows, cols, offset = rows[keep], cols[keep], offset[keep]
    return rows, cols, offset, stretch


@dataclass(frozen=True)
class ShapePairs:
    """RK shape functions as (point, particle) pair lists, grouped by point: the sparse
    matrices' data before they are built. `grad` is (pairs, 2) or None."""

    rows: np.ndarray
    cols: np.ndarray
    indptr: np.ndarray
    values: np.ndarray
    grad: np.ndarray | None

    def field(self, coefficients: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """u(X) = sum_I N_I(X) d_I (n, 2) and, with gradients, du_i/dX_J (n, 2, 2).

        Cheaper than building the sparse matrices when only a few points are evaluated once
        (tip tracking evaluates one point per call)."""
        d = coefficients[self.cols]  # (pairs, 2)
        if len(self.indptr) == 2:  # one point: two small products
            return (self.values @ d)[None], None if self.grad is None else (d.T @ self.grad)[None]
        starts = self.indptr[:-1]
        u = np.add.reduceat(self.values[:, None] * d, starts, axis=0)
        if self.grad is None:
            return u, None
        grad = np.add.reduceat(d[:, :, None] * self.grad[:, None, :], starts, axis=0)
        return u, grad

    def matrices(self, n_points: int, n_particles: int) -> ShapeFunctions:
        def csr(data: np.ndarray) -> sp.csr_matrix:
            return sp.csr_matrix((data, self.cols, self.indptr), shape=(n_points, n_particles))

        if self.grad is None:
            return ShapeFunctions(csr(self.values))
        return ShapeFunctions(csr(self.values), csr(self.grad[:, 0]), csr(self.grad[:, 1]))


def rows_csr(data: np.ndarray, indices: np.ndarray, indptr: np.ndarray, columns: int) -> sp.csr_matrix:
    """A CSR matrix of a few points' rows (a needle track's, a few thousand entries at most)
    with 32-bit index arrays, as scipy keeps them: scipy then takes them as they are instead
    of checking and converting 64-bit ones at each construction."""
    return sp.csr_matrix((data, indices.astype(np.int32, copy=False), indptr.astype(np.int32, copy=False)),
                         shape=(len(indptr) - 1, columns))


def rk_shape_functions(points: np.ndarray, particles: np.ndarray, *args, **kwargs) -> ShapeFunctions:
    """The RK shape functions of `rk_shape_pairs` (same arguments) as sparse
    (n_points x n_particles) matrices."""
    points = np.atleast_2d(np.asarray(points, dtype=float))
    pairs = rk_shape_pairs(points, particles, *args, **kwargs)
    return pairs.matrices(len(points), len(particles))


def rk_shape_pairs(
    points: np.ndarray,
    particles: np.ndarray,
    support: np.ndarray,
    volumes: np.ndarray,
    order: int = 1,
    gradients: bool = True,
    search: ParticleSearch | None = None,
    basis_scale: float | None = None,
    visibility: Visibility | None = None,
) -> ShapePairs:
    """N_I(X) = H(0)^T M(X)^-1 H((X - X_I)/a) phi_a(X - X_I) dV_I (eq. 3.19-3.20) and grad N_I.

    points (n, 2) evaluation points; particles (NP, 2); support (NP,) kernel half-widths a_I;
    volumes (NP,) particle volumes dV_I. The basis argument is scaled by one length for all
    particles (basis_scale, default the mean support) so that reproduction holds when the
    supports vary between particles. `search`: the particles' ParticleSearch (made here
    when not given). `visibility` drops the pairs whose segment leaves the tissue (see
    Visibility).
    """
    points = np.atleast_2d(np.asarray(points, dtype=float))
    rows, cols, indptr, offset, stretch = _pairs_and_offsets(points, particles, support, search, visibility)
    counts = indptr[1:] - indptr[:-1]
    m = basis_size(order)
    if (counts < m).any():
        bad = int(np.argmin(counts))
        raise SingularMomentAt(
            f"point ({points[bad, 0]:.4g}, {points[bad, 1]:.4g}) mm is covered by "
            f"{counts[bad]} particles; the order-{order} basis needs at least {m}: "
            "increase the dilation or refine the spacing", points[bad])
    scale = float(basis_scale if basis_scale is not None else support.mean())
    volume = volumes[cols]
    phi, dphi = tensor_kernel(offset, support[cols], gradients)
    if stretch is not None:  # the kernel of the way round a hole: the offset stretched, by the chain rule
        index, ratio = stretch.pairs, stretch.ratio
        phi[index], stretched = tensor_kernel(offset[index] * ratio[:, None], support[cols[index]], gradients)
        if dphi is not None:
            dphi[index] = (stretched * ratio[:, None]
                           + np.einsum("nd,nd->n", stretched, offset[index])[:, None] * stretch.gradient)
    phi = phi * volume
    h = _basis(offset / scale, order)  # (pairs, m)
    dphi = None if dphi is None else dphi * volume[:, None]
    maps = _MAPS[order] / scale  # D / s, (2, m, m)
    if len(points) == 1:  # tip tracking: one point per call, where numpy's call overhead is the cost
        shape, grad = _one_point(h, phi, dphi, maps, points)
    else:
        shape, grad = _many_points(h, phi, dphi, maps, rows, indptr, order, points)
    return ShapePairs(rows, cols, indptr, shape, grad)


def _many_points(h: np.ndarray, phi: np.ndarray, dphi: np.ndarray | None, maps: np.ndarray, rows: np.ndarray,
                 indptr: np.ndarray, order: int, points: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """rk_shape_pairs' values (pairs,) and gradients (pairs, 2) at many points (`points`, their
    pairs grouped by `rows` and `indptr`) from the pairs' basis H (pairs, m), kernel phi dV
    (pairs,) and kernel gradient dphi dV (pairs, 2) (None: no gradients), with the derivative
    maps D / s (2, m, m): each point's moment matrix M(X) (eq. 3.20) summed over its pairs."""
    # M(X) = sum H H^T phi from its upper triangle, (pairs, m (m + 1) / 2) products, not m^2
    upper, full = _TRIANGLES[order]
    hh = _upper_products(h, upper)  # (pairs, u)

    def moment_sum(weights: np.ndarray) -> np.ndarray:  # (n, m, m)
        return _pair_sums(hh, weights, indptr)[:, full]

    moment = moment_sum(phi)
    inverse = _checked_inverse(moment, points)  # (n, m, m)
    b = inverse[:, :, 0]  # M^-1 H(0), H(0) = e_1 (M symmetric), (n, m)
    corrected = _row_dot(b, rows, h)  # H(0)^T M^-1 H, (pairs,)
    shape = corrected * phi
    if dphi is None:
        return shape, None

    # dH/dX_k = D_k H / s, so sum (dH H^T + H dH^T) phi = (D_k M + M D_k^T) / s and only
    # sum H H^T dphi_k is a new sum over the pairs; then dM^-1 H(0) = -M^-1 dM b and
    # grad N_I = (dM^-1 H(0) + D_k^T b / s) . H phi + H(0)^T M^-1 H dphi_k
    grad = np.empty((len(rows), 2))
    for k in range(2):
        dmoment = moment_sum(dphi[:, k])
        spread = maps[k] @ moment  # D_k M / s, (n, m, m)
        dmoment += spread + spread.transpose(0, 2, 1)
        db = -(inverse @ (dmoment @ b[:, :, None]))[:, :, 0]
        weights = db + b @ maps[k]  # (n, m): dM^-1 H(0) + D_k^T b / s
        grad[:, k] = _row_dot(weights, rows, h) * phi + corrected * dphi[:, k]
    return shape, grad


def _one_point(h: np.ndarray, phi: np.ndarray, dphi: np.ndarray | None, maps: np.ndarray,
               point: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """rk_shape_pairs' values and gradients at one point from its pairs' basis H (k, m),
    kernel phi dV (k,) and kernel gradient dphi dV (k, 2) (None: no gradients), with the
    derivative maps D / s (2, m, m): the same sums as for many points, each direction's
    gradient in one batched product."""
    moment = (h.T * phi) @ h  # M = sum H H^T phi, (m, m)
    _check_condition(np.linalg.eigvalsh(moment)[None], np.zeros(1, dtype=np.int64), point)
    inverse = np.linalg.inv(moment)
    b = inverse[:, 0]  # M^-1 H(0)
    corrected = h @ b  # H(0)^T M^-1 H, (k,)
    if dphi is None:
        return corrected * phi, None
    # as in rk_shape_pairs: dM_k = sum H H^T dphi_k + D_k M + M D_k^T, dM^-1 H(0) = -M^-1 dM_k b
    spread = maps @ moment  # (2, m, m)
    dmoment = (h.T * dphi.T[:, None, :]) @ h + spread + spread.transpose(0, 2, 1)
    weights = (maps.transpose(0, 2, 1) @ b - dmoment @ b @ inverse).T  # dM^-1 H(0) + D_k^T b / s, (m, 2)
    return corrected * phi, (h @ weights) * phi[:, None] + corrected[:, None] * dphi


def _pair_sums(values: np.ndarray, weights: np.ndarray, indptr: np.ndarray) -> np.ndarray:
    """sum_p w_p v_p over each point's pairs (grouped by point, `indptr`), (n, columns): a
    sparse product for many points (a third of reduceat's time), reduceat for a few (one
    point's moments are one product in rk_shape_pairs)."""
    if len(indptr) <= MANY_POINTS + 1:
        return np.add.reduceat(values * weights[:, None], indptr[:-1], axis=0)
    summed = sp.csr_matrix((weights, np.arange(len(weights)), indptr), shape=(len(indptr) - 1, len(weights)))
    return summed @ values


def _upper_products(h: np.ndarray, upper: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """H_a H_b for the upper triangle's (a, b), (pairs, u); by columns (H_0 = 1: no product)."""
    out = np.empty((len(h), len(upper[0])))
    for j, (a, b) in enumerate(zip(*upper)):
        out[:, j] = h[:, b] if a == 0 else h[:, a] * h[:, b]
    return out


def _row_dot(per_point: np.ndarray, rows: np.ndarray, h: np.ndarray) -> np.ndarray:
    """per_point[rows[p]] . h[p] for every pair p, (pairs,)."""
    if len(per_point) == 1:
        return h @ per_point[0]
    gathered = np.take(per_point, rows, axis=0)
    out = gathered[:, 0] * h[:, 0]
    for j in range(1, h.shape[1]):
        out += gathered[:, j] * h[:, j]
    return out


def _checked_inverse(moment: np.ndarray, points: np.ndarray) -> np.ndarray:
    """M^-1 of each moment matrix (n, m, m), after checking that none is singular: a
    reciprocal condition lambda_min / lambda_max below 1e-12 raises SingularMomentMatrix.

    For many points the eigenvalues are computed only where the cheap 1-norm estimate
    1 / (|M|_1 |M^-1|_1) falls below m x 1e-12: for symmetric positive semidefinite M the two
    differ by at most the factor m, so every other point passes the eigenvalue test."""
    m = moment.shape[1]
    if len(moment) <= MANY_POINTS:  # a few points: two LAPACK calls cost less than the estimate
        _check_condition(np.linalg.eigvalsh(moment), np.arange(len(moment)), points)
        return np.linalg.inv(moment)
    inverse = _inverse3(moment) if m == 3 else _inverse_or_nan(moment)
    norm = np.abs(moment).sum(axis=1).max(axis=1)
    norm_inverse = np.abs(inverse).sum(axis=1).max(axis=1)
    doubtful = np.flatnonzero(~(1.0 / (norm * norm_inverse) >= m * 1e-12))  # NaN (singular) included
    if len(doubtful):
        _check_condition(np.linalg.eigvalsh(moment[doubtful]), doubtful, points)
    return inverse


def _check_condition(eigenvalues: np.ndarray, which: np.ndarray, points: np.ndarray) -> None:
    """Raise SingularMomentMatrix where lambda_min / lambda_max < 1e-12 (eigenvalues
    ascending, of the moment matrices at points[which])."""
    rcond = eigenvalues[:, 0] / eigenvalues[:, -1]
    if (~(rcond >= 1e-12)).any():
        worst = int(np.argmin(np.nan_to_num(rcond, nan=-np.inf)))
        bad = int(which[worst])
        raise SingularMomentAt(
            f"moment matrix M(X) is singular at ({points[bad, 0]:.4g}, {points[bad, 1]:.4g}) mm "
            f"(reciprocal condition {rcond[worst]:.2e}): the particles covering it lie nearly on one "
            "line; increase the dilation or refine the spacing there", points[bad])


def _inverse3(moment: np.ndarray) -> np.ndarray:
    """Inverses of symmetric 3 x 3 matrices (n, 3, 3) by cofactors (NaN where singular):
    a tenth of np.linalg.inv's time for the batches here."""
    a, b, c = moment[:, 0, 0], moment[:, 0, 1], moment[:, 0, 2]
    d, e, f = moment[:, 1, 1], moment[:, 1, 2], moment[:, 2, 2]
    cof = np.empty_like(moment)
    cof[:, 0, 0] = d * f - e * e
    cof[:, 0, 1] = cof[:, 1, 0] = c * e - b * f
    cof[:, 0, 2] = cof[:, 2, 0] = b * e - c * d
    cof[:, 1, 1] = a * f - c * c
    cof[:, 1, 2] = cof[:, 2, 1] = b * c - a * e
    cof[:, 2, 2] = a * d - b * b
    determinant = (a * cof[:, 0, 0] + b * cof[:, 0, 1] + c * cof[:, 0, 2])[:, None, None]
    return np.divide(cof, determinant, out=np.full_like(cof, np.nan), where=determinant > 0.0)


def _inverse_or_nan(moment: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.inv(moment)
    except np.linalg.LinAlgError:  # an exactly singular one: the check names it
        return np.full_like(moment, np.nan)
