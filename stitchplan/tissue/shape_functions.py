"""Reproducing-kernel shape functions and their exact gradients (thesis eq. 3.18-3.23).

Shape functions are evaluated in the reference configuration once per discretization and
stored as sparse (points x particles) matrices, so the Total-Lagrangian solver only ever
multiplies by them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .kernel import tensor_kernel
from .neighbours import CellGrid
from ..errors import SingularMomentMatrix


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
class Visibility:
    """The visibility criterion on a non-convex tissue: a particle does not interact with a
    point when the straight segment between them leaves the tissue (crosses the boundary of
    a hole or a notch), so material across a gap never shares shape functions.

    `clearance` (NP,) is each particle's distance to the boundary: a segment shorter than
    it cannot reach the boundary, only the others are tested."""

    domain: object  # geometry.PolygonDomain
    clearance: np.ndarray

    @classmethod
    def of(cls, domain, particles: np.ndarray) -> Visibility:
        return cls(domain, domain.distance(particles))

    def keep(self, points: np.ndarray, particles: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Mask of the pairs (rows: points, cols: particles) that see each other."""
        length = np.linalg.norm(points[rows] - particles[cols], axis=1)
        test = np.flatnonzero(length >= self.clearance[cols])
        keep = np.ones(len(rows), dtype=bool)
        if len(test):
            keep[test] = ~self.domain.blocked(points[rows[test]], particles[cols[test]])
        return keep


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
        merged = np.sort(np.concatenate([rows * count + cols for rows, cols in pairs]))  # by point, then particle
        return merged // count, merged % count

    def nearest(self, points: np.ndarray) -> np.ndarray:
        """The index of each point's nearest particle, (n,)."""
        return self.everyone.nearest(points)


def neighbour_pairs(
    points: np.ndarray, particles: np.ndarray, support: np.ndarray, search: ParticleSearch | None = None,
    visibility: Visibility | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All (point, particle) pairs with |X - X_I|_inf < a_I, grouped by point; with
    `visibility`, only the pairs that see each other through the tissue.

    Returns (point_index, particle_index, indptr) where indptr delimits each point's pairs.
    """
    search = search if search is not None else ParticleSearch.of(particles, support)
    rows, cols = search.candidates(points)
    # the kernel vanishes at |z| = 1; a relative margin keeps particles that sit on the
    # support edge (dilation 2 on a regular grid) out regardless of rounding
    keep = np.abs(points[rows] - particles[cols]).max(axis=1) < support[cols] * (1.0 - 1e-9)
    rows, cols = rows[keep], cols[keep]
    if visibility is not None:
        keep = visibility.keep(points, particles, rows, cols)
        rows, cols = rows[keep], cols[keep]
    indptr = np.zeros(len(points) + 1, dtype=np.int64)
    np.cumsum(np.bincount(rows, minlength=len(points)), out=indptr[1:])
    return rows, cols, indptr


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
        starts = self.indptr[:-1]
        d = coefficients[self.cols]  # (pairs, 2)
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
    rows, cols, indptr = neighbour_pairs(points, particles, support, search, visibility)
    counts = indptr[1:] - indptr[:-1]
    m = basis_size(order)
    if (counts < m).any():
        bad = int(np.argmin(counts))
        raise SingularMomentMatrix(
            f"point ({points[bad, 0]:.4g}, {points[bad, 1]:.4g}) mm is covered by "
            f"{counts[bad]} particles; the order-{order} basis needs at least {m}: "
            "increase the dilation or refine the spacing"
        )
    scale = float(basis_scale if basis_scale is not None else support.mean())
    offset = points[rows] - particles[cols]  # (pairs, 2)
    volume = volumes[cols]
    phi, dphi = tensor_kernel(offset, support[cols], gradients)
    phi = phi * volume
    h = _basis(offset / scale, order)  # (pairs, m)

    # M(X) = sum H H^T phi from its upper triangle: (pairs, m (m + 1) / 2) products, not m^2
    starts = indptr[:-1]
    upper, full = _TRIANGLES[order]
    hh = h[:, upper[0]] * h[:, upper[1]]  # (pairs, u)
    moment = np.add.reduceat(hh * phi[:, None], starts, axis=0)[:, full]  # (n, m, m)
    eigenvalues = np.linalg.eigvalsh(moment)  # (n, m), ascending
    rcond = eigenvalues[:, 0] / eigenvalues[:, -1]
    if (rcond < 1e-12).any():
        bad = int(np.argmin(rcond))
        raise SingularMomentMatrix(
            f"moment matrix M(X) is singular at ({points[bad, 0]:.4g}, {points[bad, 1]:.4g}) mm "
            f"(reciprocal condition {rcond[bad]:.2e}): increase the dilation"
        )
    inverse = np.linalg.inv(moment)  # (n, m, m); well conditioned, checked above
    b = inverse[:, :, 0]  # M^-1 H(0), H(0) = e_1 (M symmetric), (n, m)
    corrected = np.einsum("pm,pm->p", b[rows], h)  # H(0)^T M^-1 H, (pairs,)
    shape = corrected * phi
    if not gradients:
        return ShapePairs(rows, cols, indptr, shape, None)

    # dH/dX_k = D_k H / s, so sum (dH H^T + H dH^T) phi = (D_k M + M D_k^T) / s and only
    # sum H H^T dphi_k is a new sum over the pairs; then dM^-1 H(0) = -M^-1 dM b and
    # grad N_I = (dM^-1 H(0) + D_k^T b / s) . H phi + H(0)^T M^-1 H dphi_k
    dphi = dphi * volume[:, None]
    maps = _MAPS[order] / scale
    grad = np.empty((len(rows), 2))
    for k in range(2):
        dmoment = np.add.reduceat(hh * dphi[:, k, None], starts, axis=0)[:, full]
        spread = maps[k] @ moment  # D_k M / s, (n, m, m)
        dmoment += spread + spread.transpose(0, 2, 1)
        db = -(inverse @ (dmoment @ b[:, :, None]))[:, :, 0]
        weights = db + b @ maps[k]  # (n, m): dM^-1 H(0) + D_k^T b / s
        grad[:, k] = np.einsum("pm,pm->p", weights[rows], h) * phi + corrected * dphi[:, k]
    return ShapePairs(rows, cols, indptr, shape, grad)
