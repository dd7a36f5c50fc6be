"""Sparse direct factorizations: scipy's SuperLU always; CHOLMOD's Cholesky when the
optional `fast` extra (the `cvxopt` wheel, which carries CHOLMOD and OpenBLAS) is installed
and the matrix is symmetric positive definite.

The needle's saddle-point solves reuse one factor of K + H over hundreds of Newton
iterations, and every run factors K0 once: on the SH 1/2 scene (1900 dofs, 175 000
nonzeros) CHOLMOD's Cholesky factors K0 in ~17 ms and solves in ~0.17 ms, against SuperLU's
~26 ms and ~0.34 ms (symmetric mode); on its model at half the spacing (the plan's
verification, 7170 dofs) in ~0.12 s and ~3.6 ms against ~0.33 s and ~6.3 ms
(benchmarks/results/model_build_speed.md). SuperLU stays the default and the fallback.

A symmetric matrix the Cholesky finds not positive definite (the needle's constraint
curvature H, or Saint Venant-Kirchhoff's tangent under strong compression, can make K + H
indefinite) gets CHOLMOD's simplicial L D L^T: no pivoting beyond the fill-reducing
ordering, so one solve's residual is checked (LDL_CHECK) and SuperLU factors the matrix
where it fails. It keeps the indefinite K + H of the SH 1/2 100 x 30 and 100 x 40 blocks
on CHOLMOD, so those runs import no scipy.sparse.linalg (~0.07 s; tests/test_factorization.py;
benchmarks/plan_speed.py's levers table times them with SuperLU instead).
STITCHPLAN_LINEAR_BACKEND=superlu turns CHOLMOD off.
Every factor says which backend made it (`backend`), and the run summaries record it.
"""

from __future__ import annotations

import os

import numpy as np
import scipy.sparse as sp

from ..errors import NumericalFailure

try:  # the `fast` extra; imported with the module, as scipy is, not within a run
    from cvxopt import cholmod, matrix as dense, spmatrix
except (ImportError, OSError):
    cholmod = None

SUPERLU = "scipy SuperLU (splu, MMD_AT_PLUS_A ordering, symmetric mode)"
CHOLMOD = "CHOLMOD Cholesky (cvxopt)"
CHOLMOD_LDL = "CHOLMOD LDL^T (cvxopt, simplicial)"
LDL_CHECK = 1e-10  # |A x - b| / |b| an L D L^T factor's solve must reach on a test vector


class SingularMatrix(NumericalFailure):
    """SuperLU met a zero pivot: the matrix is singular to rounding (scipy raises a bare
    RuntimeError, which would end a command with a traceback)."""


class SuperLUFactor:
    """Sparse LU with a symmetric fill-reducing ordering. SymmetricMode keeps the rows in the
    columns' order where the diagonal is an acceptable pivot (partial pivoting stays on),
    which the tangents here always allow: same fill, ~40 % faster solves than the default
    (benchmarks/plan_speed.py)."""

    backend = SUPERLU

    def __init__(self, matrix: sp.spmatrix):
        from scipy.sparse.linalg import splu  # imported at start-up where SuperLU is the backend (below)

        try:
            self._lu = splu(sp.csc_matrix(matrix), permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
        except RuntimeError as error:  # "Factor is exactly singular"
            raise SingularMatrix(
                f"the {matrix.shape[0]} x {matrix.shape[1]} stiffness matrix is singular: SuperLU met a zero "
                f"pivot ({error}); the particles' coefficients are dependent, as where particles crowd "
                "together or tissue is thinner than the particle spacing resolves") from None

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        return self._lu.solve(rhs)

    def solve_columns(self, columns: sp.spmatrix) -> np.ndarray:
        """The solutions (n, k) for the k sparse right-hand sides `columns` (n, k)."""
        return self._lu.solve(columns.toarray())


def cholmod_matrix(matrix: sp.spmatrix):
    """The lower triangle of a symmetric scipy matrix as cvxopt's sparse matrix."""
    lower = sp.tril(matrix, format="csc")
    lower.sum_duplicates()
    lower.sort_indices()
    triplets = lower.tocoo()  # in column order, as CHOLMOD keeps it
    n = lower.shape[0]
    return spmatrix(dense(triplets.data), dense(triplets.row.astype(np.int64)),
                    dense(triplets.col.astype(np.int64)), (n, n))


class CholeskyFactor:
    """The supernodal L L^T of a symmetric positive definite matrix by CHOLMOD (cvxopt's
    build, with its own OpenBLAS); raises ValueError when the matrix is not positive definite.
    `matrix`: a scipy matrix, or its cholmod_matrix."""

    backend = CHOLMOD
    SUPERNODAL = None  # cvxopt's cholmod.options["supernodal"] while factoring: None CHOLMOD's own
    # choice (supernodal L L^T for these matrices), 0 the simplicial L D L^T

    def __init__(self, matrix):
        stored = matrix if isinstance(matrix, spmatrix) else cholmod_matrix(matrix)
        previous = cholmod.options.get("supernodal")
        if self.SUPERNODAL is not None:
            cholmod.options["supernodal"] = self.SUPERNODAL
        try:
            self._factor = cholmod.symbolic(stored, uplo="L")
            cholmod.numeric(stored, self._factor)
        except ArithmeticError:
            raise ValueError("not positive definite") from None
        finally:
            if previous is not None:
                cholmod.options["supernodal"] = previous
            else:
                cholmod.options.pop("supernodal", None)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        solution = dense(np.asfortranarray(rhs, dtype=float))
        cholmod.solve(self._factor, solution)
        return np.array(solution).reshape(np.shape(rhs))

    def solve_columns(self, columns: sp.spmatrix) -> np.ndarray:
        """The solutions (n, k) for the k sparse right-hand sides `columns` (n, k), by CHOLMOD's
        sparse solve, which takes them in blocks (cvxopt's dense solve takes one column at a
        time): the verification replays of sh12_100x100 (3642 particles) and wound_closure
        (4963) in 0.93x the time, those of ~1400 particles within the noise
        (benchmarks/results/replay_solves.md)."""
        triplets = sp.coo_matrix(columns)
        stored = spmatrix(dense(triplets.data.astype(float)), dense(triplets.row.astype(np.int64)),
                          dense(triplets.col.astype(np.int64)), triplets.shape)
        return np.array(dense(cholmod.spsolve(self._factor, stored)))


class LDLFactor(CholeskyFactor):
    """CHOLMOD's simplicial L D L^T of a symmetric (indefinite) matrix, pivoting only by its
    fill-reducing ordering: a pivot near zero would spoil it, so a solve with it must reach
    LDL_CHECK on a test vector; raises ValueError otherwise (or on a zero pivot)."""

    backend = CHOLMOD_LDL
    SUPERNODAL = 0

    def __init__(self, matrix: sp.spmatrix, stored=None):
        super().__init__(stored if stored is not None else cholmod_matrix(matrix))
        if not solve_residual(matrix, self) <= LDL_CHECK:  # NaN included
            raise ValueError("inaccurate without pivoting")


Factor = SuperLUFactor | CholeskyFactor


def _probe(n: int) -> np.ndarray:
    return np.cos(np.arange(n))  # a test vector not special to any matrix here


def solve_residual(matrix: sp.spmatrix, factor) -> float:
    """|A x - p| / |p| for x = factor.solve(p) and a fixed test vector p: ~1e-15 for a
    well-conditioned A, growing like the rounding error times its condition number."""
    probe = _probe(matrix.shape[0])
    return float(np.linalg.norm(matrix @ factor.solve(probe) - probe) / np.linalg.norm(probe))


def condition_estimate(matrix: sp.spmatrix, factor, iterations: int = 3) -> float:
    """An estimate of the condition number of a symmetric positive definite `matrix` from its
    `factor`: Gershgorin's bound on the largest eigenvalue over the Rayleigh quotient after
    `iterations` inverse iterations from a test vector (an upper bound on the smallest);
    inf where that quotient is not positive (singular to rounding), NaN where the iterations
    overflow (a matrix scaled near the floating-point range: no estimate). 1.1-2.7x eigsh's
    largest over smallest on the needle scenes' K0 at dilations 2-6, where that ranges from 1e3
    to 2e15 (benchmarks/results/dilation_conditioning.md); inf where eigsh gives 1e18."""
    vector = _probe(matrix.shape[0])
    with np.errstate(all="ignore"):
        for _ in range(iterations):
            vector = factor.solve(vector)
            vector = vector / np.linalg.norm(vector)
        smallest = float(vector @ (matrix @ vector))
        largest = _largest_row_sum(matrix)
        if not (np.isfinite(smallest) and np.isfinite(largest) and largest > 0):
            return np.nan
        return largest / smallest if smallest > 0 else np.inf


def _largest_row_sum(matrix: sp.spmatrix) -> float:
    """max_i sum_j |A_ij| (Gershgorin's bound), from a CSR matrix's stored values by row:
    abs(A).sum(axis=1) builds a second matrix and checks its format first, which on a K0
    just assembled costs several times the sum itself."""
    matrix = sp.csr_matrix(matrix)
    magnitudes = np.abs(matrix.data)
    counts = np.diff(matrix.indptr)
    if not len(magnitudes):
        return 0.0
    sums = np.add.reduceat(magnitudes, np.minimum(matrix.indptr[:-1], len(magnitudes) - 1))
    return float(np.where(counts > 0, sums, 0.0).max())


def cholesky_available() -> bool:
    return cholmod is not None and os.environ.get("STITCHPLAN_LINEAR_BACKEND", "").lower() != "superlu"


# scipy.sparse.linalg (with scipy.linalg ~70 ms) is imported with this module where SuperLU
# factors every matrix, so that a run's time is its own; with CHOLMOD it is imported the
# first time SuperLU runs (an indefinite matrix whose L D L^T fails the check: none of the
# shipped needle scenes')
if not cholesky_available():
    import scipy.sparse.linalg  # noqa: F401


def factorize(matrix: sp.spmatrix, symmetric_positive: bool = False) -> Factor:
    """A factor of `matrix` with `.solve(rhs)` (rhs (n,) or (n, k)) and `.backend`: where the
    caller knows the matrix is symmetric (`symmetric_positive`) and CHOLMOD is available, its
    Cholesky, or its L D L^T where the matrix is not positive definite (the needle's
    constraint curvature H can make K + H indefinite); SuperLU otherwise or where the L D L^T
    is not accurate."""
    if symmetric_positive and cholesky_available():
        stored = cholmod_matrix(matrix)
        try:
            return CholeskyFactor(stored)
        except ValueError:  # not positive definite
            pass
        try:
            return LDLFactor(matrix, stored)
        except ValueError:  # a pivot near zero
            pass
    return SuperLUFactor(matrix)
