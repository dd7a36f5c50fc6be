"""Sparse direct factorizations: scipy's SuperLU always; CHOLMOD's Cholesky when the
optional `fast` extra (the `cvxopt` wheel, which carries CHOLMOD and OpenBLAS) is installed
and the matrix is symmetric positive definite.

The needle's saddle-point solves reuse one factor of K + H over hundreds of Newton
iterations, and every run factors K0 once: on the SH 1/2 scene (1900 dofs, 175 000
nonzeros) CHOLMOD's Cholesky factors K0 in ~17 ms and solves in ~0.17 ms, against SuperLU's
~26 ms and ~0.34 ms (symmetric mode); on its model at half the spacing (the plan's
verification, 7170 dofs) in ~0.12 s and ~3.6 ms against ~0.33 s and ~6.3 ms
(benchmarks/results/model_build_speed.md). SuperLU stays the default and the fallback: a
matrix the Cholesky finds not positive definite (the needle's constraint curvature H can
make K + H indefinite) is factorized by SuperLU instead. STITCHPLAN_LINEAR_BACKEND=superlu
turns CHOLMOD off. Every factor says which backend made it (`backend`), and the run
summaries record it.
"""

from __future__ import annotations

import os

import numpy as np
import scipy.sparse as sp

try:  # the `fast` extra; imported with the module, as scipy is, not within a run
    from cvxopt import cholmod, matrix as dense, spmatrix
except (ImportError, OSError):
    cholmod = None

SUPERLU = "scipy SuperLU (splu, MMD_AT_PLUS_A ordering, symmetric mode)"
CHOLMOD = "CHOLMOD Cholesky (cvxopt)"


class SuperLUFactor:
    """Sparse LU with a symmetric fill-reducing ordering. SymmetricMode keeps the rows in the
    columns' order where the diagonal is an acceptable pivot (partial pivoting stays on),
    which the tangents here always allow: same fill, ~40 % faster solves than the default
    (benchmarks/plan_speed.py)."""

    backend = SUPERLU

    def __init__(self, matrix: sp.spmatrix):
        from scipy.sparse.linalg import splu  # imported at start-up where SuperLU is the backend (below)

        self._lu = splu(sp.csc_matrix(matrix), permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        return self._lu.solve(rhs)


class CholeskyFactor:
    """The supernodal L L^T of a symmetric positive definite matrix by CHOLMOD (cvxopt's
    build, with its own OpenBLAS); raises ValueError when the matrix is not positive definite."""

    backend = CHOLMOD

    def __init__(self, matrix: sp.spmatrix):
        lower = sp.tril(matrix, format="csc")
        lower.sum_duplicates()
        lower.sort_indices()
        triplets = lower.tocoo()  # in column order, as CHOLMOD keeps it
        n = lower.shape[0]
        stored = spmatrix(dense(triplets.data), dense(triplets.row.astype(np.int64)),
                          dense(triplets.col.astype(np.int64)), (n, n))
        try:
            self._factor = cholmod.symbolic(stored, uplo="L")
            cholmod.numeric(stored, self._factor)
        except ArithmeticError:
            raise ValueError("not positive definite") from None

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        solution = dense(np.asfortranarray(rhs, dtype=float))
        cholmod.solve(self._factor, solution)
        return np.array(solution).reshape(np.shape(rhs))


Factor = SuperLUFactor | CholeskyFactor


def cholesky_available() -> bool:
    return cholmod is not None and os.environ.get("STITCHPLAN_LINEAR_BACKEND", "").lower() != "superlu"


# scipy.sparse.linalg (with scipy.linalg ~70 ms) is imported with this module where SuperLU
# factors every matrix, so that a run's time is its own; with CHOLMOD it is imported the
# first time a matrix is not positive definite (on most needle commands never)
if not cholesky_available():
    import scipy.sparse.linalg  # noqa: F401


def factorize(matrix: sp.spmatrix, symmetric_positive: bool = False) -> Factor:
    """A factor of `matrix` with `.solve(rhs)` (rhs (n,) or (n, k)) and `.backend`: CHOLMOD's
    Cholesky when the caller knows the matrix is symmetric (`symmetric_positive`) and it is
    available and succeeds, SuperLU otherwise (the needle's constraint curvature H can make
    K + H indefinite)."""
    if symmetric_positive and cholesky_available():
        try:
            return CholeskyFactor(matrix)
        except ValueError:  # not positive definite
            pass
    return SuperLUFactor(matrix)
