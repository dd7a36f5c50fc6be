"""Internal force and consistent tangent stiffness (thesis eq. 3.44-3.57).

With the gradient operator B (4 nq x 2 n_free) of the discretized tissue,

    f_int = B^T (w P)              P = F S, first Piola-Kirchhoff stress
    K     = B^T diag(w A) B        A_iJkL = dP_iJ / dF_kL = K_H + K_G of eq. 3.45-3.53

With variationally consistent integration the test side uses corrected gradients B~
(TissueModel.test_gradient): f_int = B~^T (w P), K = B~^T diag(w A) B.

B is built once per discretization; the block-diagonal material-point stiffness diag(w A)
keeps a fixed sparsity pattern and only its values are refilled. Newton iterations
mostly need K only as a product K v = B^T (diag(w A) (B v)), three sparse mat-vecs; the
explicit K (a sparse-sparse product) is formed only when a factorization is wanted.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from .model import TissueModel
from .material import first_piola, first_piola_and_tangent, lame_at_rest


class Assembler:
    def __init__(self, model: TissueModel):
        self.model = model
        self.gradient = model.gradient
        self._test = model.gradient if model.test_gradient is None else model.test_gradient
        # B^T (or B~^T of the corrected test functions) as the CSC view of B: a product with a
        # vector adds each entry's terms in the order the CSR transpose does, to the last bit,
        # from the arrays of B itself, one matrix less in memory beside the factor (the refined
        # replay of sh12_100x100 in 0.94x the time, benchmarks/results/transposed_gradient.md);
        # the CSR transpose is made for the explicit K only (tangent_matrix)
        self.gradient_t = self._test.T
        self._gradient_t_rows: sp.csr_matrix | None = None
        n_points = len(model.quadrature_weights)
        # block-diagonal (4 x 4 per point) as CSR with a fixed pattern: data order is (q, r, c)
        cols = (4 * np.arange(n_points)[:, None, None] + np.zeros((1, 4, 1), int) + np.arange(4)).ravel()
        self._pointwise = sp.csr_matrix(
            (np.zeros(16 * n_points), cols, np.arange(0, 16 * n_points + 1, 4)),
            shape=(4 * n_points, 4 * n_points),
        )
        self._deformation_gradient: np.ndarray | None = None
        self._tangent_current = False
        self.tangent_products = 0

    def update(self, deformation_gradient: np.ndarray) -> np.ndarray:
        """Evaluate the stress at F (nq, 2, 2); returns f_int (2 n_free,). The material
        tangent at this F is evaluated only if a tangent product or matrix is asked for."""
        piola = first_piola(self.model.material, deformation_gradient)
        self._deformation_gradient = deformation_gradient
        self._tangent_current = False
        weights = self.model.quadrature_weights
        return self.gradient_t @ (piola * weights[:, None, None]).reshape(-1)

    def _refresh_tangent(self) -> None:
        if self._tangent_current:
            return
        _, tangent = first_piola_and_tangent(self.model.material, self._deformation_gradient)
        weights = self.model.quadrature_weights
        n_points = len(weights)
        self._pointwise.data[:] = (tangent.reshape(n_points, 4, 4) * weights[:, None, None]).ravel()
        self._tangent_current = True

    def tangent_product(self, vector: np.ndarray) -> np.ndarray:
        self._refresh_tangent()
        self.tangent_products += 1
        return self.gradient_t @ (self._pointwise @ (self.gradient @ vector))

    def tangent_matrix(self) -> sp.csr_matrix:
        """Explicit K at the last update (eq. 3.45)."""
        self._refresh_tangent()
        if self._gradient_t_rows is None:
            self._gradient_t_rows = self._test.T.tocsr()
        return (self._gradient_t_rows @ (self._pointwise @ self.gradient)).tocsr()

    def force_and_tangent(self, deformation_gradient: np.ndarray) -> tuple[np.ndarray, sp.csr_matrix]:
        internal = self.update(deformation_gradient)
        return internal, self.tangent_matrix()


def stiffness_at_rest(model: TissueModel) -> sp.csr_matrix:
    """K0, the tangent at zero deformation (eq. 3.45 at F = I).

    There A_iJkL = lambda d_iJ d_kL + mu (d_ik d_JL + d_iL d_Jk) (material.lame_at_rest), so
    the 2 x 2 block of K0 between particles p and r is

        K0_pr = M^lambda_pr + (M^mu_pr)^T + tr(M^mu_pr) I,  M^c_pr,JL = sum_q w c dPsi_p/dX_J dPsi_r/dX_L,

    two products of the (nq, 2 n_free) direction gradients (one for a single material)
    instead of B^T diag(w A) B over the 4 nq rows of B: 2-3x faster (benchmarks/plan_speed.py).
    With corrected test functions (vci) K0 is not symmetric and is assembled as B~^T diag(w A) B.
    """
    weights = model.quadrature_weights
    direction = model.direction_gradient
    if model.test_gradient is not None:
        assembler = Assembler(model)
        assembler.update(np.broadcast_to(np.eye(2), (len(weights), 2, 2)).copy())
        return assembler.tangent_matrix()
    lam, mu = lame_at_rest(model.material, len(weights))
    transposed = direction.T.tocsr()

    def weighted(values: np.ndarray) -> sp.bsr_matrix:  # M^c for values w c, (nq,)
        scaled = direction.copy()
        scaled.data *= np.repeat(values, np.diff(direction.indptr))
        return (transposed @ scaled).tobsr(blocksize=(2, 2))

    by_mu = weighted(weights * mu)
    blocks = by_mu.data
    trace = blocks[:, 0, 0] + blocks[:, 1, 1]
    stiffness = blocks.transpose(0, 2, 1).copy()
    stiffness[:, 0, 0] += trace
    stiffness[:, 1, 1] += trace
    if np.ptp(lam) == 0.0 and np.ptp(mu) == 0.0:  # one material: M^lambda = (lambda / mu) M^mu
        stiffness += (lam[0] / mu[0]) * blocks
        return sp.bsr_matrix((stiffness, by_mu.indices, by_mu.indptr), shape=by_mu.shape).tocsr()
    shear = sp.bsr_matrix((stiffness, by_mu.indices, by_mu.indptr), shape=by_mu.shape).tocsr()
    return (shear + weighted(weights * lam).tocsr()).tocsr()
