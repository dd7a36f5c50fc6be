"""Essential boundary conditions by the transformation method (thesis eq. 3.24-3.38).

RK shape functions lack the Kronecker-delta property, so prescribing a particle
coefficient does not prescribe the displacement there. The transformation method
enforces u(X_I) = g_I at every boundary particle exactly:

    d_b = (D^b)^-1 g - (D^b)^-1 D^nb d_nb               (eq. 3.33 solved for d_b)

so the full coefficient vector is d = T d_nb + T_g g with sparse T and T_g, and the
transformed shape functions N T and N T_g are those of eq. 3.37-3.38.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..config import Tissue
from ..errors import InputError
from ..geometry.segments import on_segment

CLAMPED = -1


@dataclass(frozen=True)
class ConstrainedParticles:
    indices: np.ndarray  # (Nb,) particle indices on the essential boundary
    group: np.ndarray  # (Nb,) CLAMPED or the index of the prescribed-displacement segment


@dataclass(frozen=True)
class EssentialBoundary:
    indices: np.ndarray  # (Nb,)
    group: np.ndarray  # (Nb,)
    free_indices: np.ndarray  # (n_free,)
    free_map: sp.csr_matrix  # T (NP, n_free)
    prescribed_map: sp.csr_matrix  # T_g (NP, Nb)
    free_column: np.ndarray  # (NP,) each free particle's column in T (its row of T is that unit row), -1 on the boundary

    @property
    def n_free(self) -> int:
        return len(self.free_indices)

    def full(self, free: np.ndarray, prescribed: np.ndarray) -> np.ndarray:
        """d = T d_nb + T_g g; free (n_free, 2), prescribed (Nb, 2) -> (NP, 2)."""
        return self.free_map @ free + self.prescribed_map @ prescribed


def boundary_particles(
    particles: np.ndarray,
    tissue: Tissue,
    prescribed_segments: tuple,
    spacing: float,
) -> ConstrainedParticles:
    """Particles on clamped edges (group CLAMPED) and on prescribed-displacement segments.

    A particle that is both clamped and on a segment stays clamped: the clamp holds the corner.
    """
    domain = tissue.domain
    tol = domain.tolerance
    group = np.full(len(particles), -2)
    for k, (start, end) in enumerate(prescribed_segments):
        group[on_segment(particles, start, end, tol)] = k
    for item, (start, end) in zip(tissue.clamped, tissue.clamped_pieces()):
        if isinstance(item, str):
            group[domain.edge_mask(particles, item, tol)] = CLAMPED
        else:
            group[on_segment(particles, start, end, tol)] = CLAMPED
    for k, (start, end) in enumerate(prescribed_segments):
        if not np.any(group == k):
            raise InputError(
                f"loads: the displacement segment {list(start)}-{list(end)} holds no particle at "
                f"spacing {spacing:g} mm: lengthen it or refine the spacing"
            )
    indices = np.flatnonzero(group > -2)
    # clamps or displacement segments that hold fewer than two particles leave the tissue free to
    # turn about the one (a tissue given none is a Python caller's unconstrained model: files refuse it)
    if len(indices) < 2 and (tissue.clamped or prescribed_segments):
        held = "no particle" if len(indices) == 0 else f"one particle ({particles[indices[0]].round(6).tolist()})"
        raise InputError(
            f"tissue.clamped: got clamped pieces{' and displacement segments' if prescribed_segments else ''} "
            f"holding {held} of the model; expected at least two held particles, or the tissue "
            "moves or turns rigidly (no unique solution): lengthen the clamp or refine the spacing")
    return ConstrainedParticles(indices, group[indices])


def transformation(
    at_boundary: sp.csr_matrix, constrained: ConstrainedParticles, n_particles: int
) -> EssentialBoundary:
    """Build T and T_g from N(X_b), the RK functions evaluated at the boundary particles."""
    b = constrained.indices
    is_free = np.ones(n_particles, dtype=bool)
    is_free[b] = False
    free = np.flatnonzero(is_free)
    column_of_free = np.full(n_particles, -1)
    column_of_free[free] = np.arange(len(free))

    identity_rows = sp.csr_matrix(
        (np.ones(len(free)), (free, np.arange(len(free)))), shape=(n_particles, len(free))
    )
    if len(b) == 0:
        empty = sp.csr_matrix((n_particles, 0))
        return EssentialBoundary(b, constrained.group, free, identity_rows, empty, column_of_free)

    at_boundary = at_boundary.tocsc()
    d_b = at_boundary[:, b].toarray()  # D^b (Nb, Nb), eq. 3.31
    d_nb = at_boundary[:, free]  # D^nb (Nb, n_free), eq. 3.32
    touched = np.flatnonzero(np.diff(d_nb.indptr) > 0)  # free particles seen by the boundary
    # (D^b)^-1 D^nb and (D^b)^-1 from one LU of D^b
    solved = np.linalg.solve(d_b, np.hstack([d_nb[:, touched].toarray(), np.eye(len(b))]))
    coupling, inverse = solved[:, :len(touched)], solved[:, len(touched):]
    # (D^b)^-1 decays exponentially away from the diagonal: entries below 1e-13 x the
    # largest are round-off, and keeping them would couple every boundary particle to
    # every other (dense rows in the gradient operator, super-linear assembly cost)
    coupling[np.abs(coupling) < 1e-13 * np.abs(coupling).max(initial=0.0)] = 0.0
    inverse[np.abs(inverse) < 1e-13 * np.abs(inverse).max()] = 0.0

    rows_b = np.repeat(b, len(touched))
    cols = np.tile(touched, len(b))
    free_map = identity_rows + sp.csr_matrix(
        (-coupling.ravel(), (rows_b, cols)), shape=(n_particles, len(free))
    )
    prescribed_map = sp.csr_matrix(
        (inverse.ravel(), (np.repeat(b, len(b)), np.tile(np.arange(len(b)), len(b)))),
        shape=(n_particles, len(b)),
    )
    free_map.eliminate_zeros()
    prescribed_map.eliminate_zeros()
    return EssentialBoundary(b, constrained.group, free, free_map.tocsr(), prescribed_map.tocsr(), column_of_free)
