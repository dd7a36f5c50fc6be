"""Stability of a constrained equilibrium: the tangent's least stiffness on the needle's constraints.

An equilibrium of eq. 3.62 is stable when the tangent K + H is positive definite on the
displacements the constraints allow, G^T v = 0. Where a step's load cannot be carried
(needle/equilibrium.py), this tells a physical failure from a numerical one: the tissue's
least stiffness falling toward zero over the step (a limit point: the tissue has no
equilibrium beyond it under the needle's load) or below it (a bifurcation: the state
Newton found is unstable, the tissue buckles or creases), or holding (Newton's failure).

The least stiffness is the smallest eigenvalue of K + H on null(G^T), found as the
smallest of K + H + c G G^T (shift-invert Lanczos): for any c >= 0 that matrix positive
definite proves K + H positive definite on null(G^T), and its eigenvector v projected on
null(G^T) gives the Rayleigh quotient reported, an upper bound on the smallest eigenvalue
there that proves indefiniteness when negative (tight as c grows; c is PENALTY x K's mean
diagonal over G G^T's largest).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from ..errors import NumericalFailure
from ..tissue.factorization import factorize

PENALTY = 1e4  # c G G^T against K's mean diagonal: the constraints' directions far stiffer than any other
MODES = 3  # eigenpairs nearest the shift: a negative one beside the small positive ones
# the shift, x K's mean diagonal: just below zero, where an eigenvalue crossing zero along a load
# path shows first (the loads carried arrive there in small increments); one far below it could
# be missed, and a shift far from the spectrum's low end slows Lanczos down
SHIFT = -1e-3
# Lanczos restarts before the eigensolver gives up (no answer: the message goes without it), ~17
# solves each: the tests' calls take 2-52 solves, a 10 mm x 0.5 mm strip's ~70; a 100 mm x 0.5 mm
# strip's lowest modes (~1e-10 of K's diagonal) crowd together against the shift and took 17 358
# solves, 168 s
RESTARTS = 20


@dataclass(frozen=True)
class SoftestMode:
    """The least stiffness of a constrained tangent and its mode."""

    stiffness: float  # v^T K v / v^T v on null(G^T), relative to K's mean |diagonal|
    mode: np.ndarray  # v, (2 n_free,) interleaved over (particle, direction)


def softest_mode(tangent: sp.spmatrix, constraints: sp.spmatrix) -> SoftestMode | None:
    """The least stiffness of `tangent` (K + H, 2 n_free square) on the displacements the
    constraint columns (G, 2 n_free x m) allow; None where the eigensolver does not answer
    (no convergence, a singular shifted matrix, no memory for its factor): the caller's
    message then goes without it."""
    import scipy.sparse.linalg as sla  # here: only a failing step asks, and the import costs every run's start-up

    tangent = sp.csr_matrix(tangent)
    scale = float(np.abs(tangent.diagonal()).mean())
    if not np.isfinite(scale) or scale <= 0.0:
        return None
    constraints = sp.csc_matrix(constraints)
    penalized = tangent
    if constraints.shape[1]:
        coupling = (constraints @ constraints.T).tocsr()
        largest = float(np.abs(coupling.diagonal()).max())
        if largest > 0.0:
            penalized = tangent + (PENALTY * scale / largest) * coupling
    penalized = (0.5 * (penalized + penalized.T)).tocsc()
    count = min(MODES, penalized.shape[0] - 1)
    if count < 1:
        return None
    shift = SHIFT * scale
    try:
        # shift-invert through the runs' own factorization (a symmetric fill-reducing ordering):
        # eigsh's default splu orders by COLAMD, 14.5 s a factor against CHOLMOD's 0.12 s on a
        # 10 mm x 0.5 mm strip's 10 850 unknowns
        factor = factorize(penalized - shift * sp.identity(penalized.shape[0], format="csc"),
                           symmetric_positive=True)
        inverse = sla.LinearOperator(penalized.shape, matvec=factor.solve, dtype=float)
        values, vectors = sla.eigsh(penalized, k=count, sigma=shift, which="LM", OPinv=inverse, maxiter=RESTARTS)
    except (sla.ArpackNoConvergence, sla.ArpackError, RuntimeError, ValueError, MemoryError, NumericalFailure):
        return None  # the diagnosis never turns a failure it explains into another
    mode = vectors[:, int(np.argmin(values))]
    if constraints.shape[1]:  # onto G^T v = 0 exactly
        gram = (constraints.T @ constraints).toarray()
        try:
            mode = mode - constraints @ np.linalg.lstsq(gram, constraints.T @ mode, rcond=None)[0]
        except np.linalg.LinAlgError:
            return None
    norm = float(mode @ mode)
    if not np.isfinite(norm) or norm <= 0.0:
        return None
    return SoftestMode(float(mode @ (tangent @ mode)) / norm / scale, mode / np.sqrt(norm))


def mode_peak(mode: SoftestMode, free_map: sp.spmatrix) -> int:
    """The particle the mode moves most (free_map: the particles' coefficients from the free ones)."""
    moved = free_map @ mode.mode.reshape(-1, 2)
    return int(np.argmax(np.linalg.norm(moved, axis=1)))
