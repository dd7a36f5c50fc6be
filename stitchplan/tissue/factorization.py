"""Sparse direct factorizations: scipy's SuperLU always, CHOLMOD's supernodal Cholesky when
the optional `fast` extra (the `cholespy` wheel) is installed and the matrix is symmetric
positive definite.

The needle's saddle-point solves reuse one factor of K + H over hundreds of Newton
iterations, so the solve dominates: on the SH 1/2 scene (1900 dofs, 175 000 nonzeros)
CHOLMOD solves in ~0.27 ms against SuperLU's ~0.44 ms (symmetric mode). SuperLU stays the
default and the fallback: a matrix the Cholesky finds not positive definite (the needle's
constraint curvature H can make K + H indefinite) is factorized by SuperLU instead.
STITCHPLAN_LINEAR_BACKEND=superlu turns the Cholesky off. Every factor says which backend
made it (`backend`), and the run summaries record it.
"""

from __future__ import annotations

import os
import sys

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

SUPERLU = "scipy SuperLU (splu, MMD_AT_PLUS_A ordering, symmetric mode)"
CHOLMOD = "CHOLMOD supernodal Cholesky (cholespy)"


class SuperLUFactor:
    """Sparse LU with a symmetric fill-reducing ordering. SymmetricMode keeps the rows in the
    columns' order where the diagonal is an acceptable pivot (partial pivoting stays on),
    which the tangents here always allow: same fill, ~40 % faster solves than the default
    (benchmarks/plan_speed.py)."""

    backend = SUPERLU

    def __init__(self, matrix: sp.spmatrix):
        self._lu = spla.splu(sp.csc_matrix(matrix), permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        return self._lu.solve(rhs)


class CholeskyFactor:
    """L L^T of a symmetric positive definite matrix by CHOLMOD (cholespy); raises
    ValueError when the matrix is not positive definite."""

    backend = CHOLMOD

    def __init__(self, matrix: sp.spmatrix):
        from cholespy import CholeskySolverD, MatrixType

        csr = sp.csr_matrix(matrix)
        csr.sum_duplicates()
        csr.sort_indices()
        self._solver = _quiet(lambda: CholeskySolverD(csr.shape[0], csr.indptr.astype(np.int32),
                                                      csr.indices.astype(np.int32),
                                                      np.ascontiguousarray(csr.data, dtype=float), MatrixType.CSR))

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        rhs = np.ascontiguousarray(rhs, dtype=float)
        solution = np.empty_like(rhs)
        self._solver.solve(rhs, solution)
        return solution


Factor = SuperLUFactor | CholeskyFactor


def cholesky_available() -> bool:
    if os.environ.get("STITCHPLAN_LINEAR_BACKEND", "").lower() == "superlu":
        return False
    try:
        import cholespy  # noqa: F401
    except ImportError:
        return False
    return True


def factorize(matrix: sp.spmatrix, symmetric_positive: bool = False) -> Factor:
    """A factor of `matrix` with `.solve(rhs)` (rhs (n,) or (n, k)) and `.backend`: CHOLMOD's
    Cholesky when the caller knows the matrix is symmetric (`symmetric_positive`) and it is
    available and succeeds, SuperLU otherwise."""
    if symmetric_positive and cholesky_available():
        try:
            return CholeskyFactor(matrix)
        except ValueError:  # not positive definite
            pass
    return SuperLUFactor(matrix)


def _quiet(make):
    """Run `make` with the process's stdout and stderr closed: CHOLMOD prints a warning of its
    own for a matrix that is not positive definite (which the fallback handles), through C's
    buffered stdout, so C's buffers are flushed before the descriptors come back."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
        return make()
    finally:
        _flush_c_streams()
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for descriptor in (*saved, devnull):
            os.close(descriptor)


def _flush_c_streams() -> None:
    """fflush(NULL): C's stdio buffers of this process."""
    import ctypes

    try:
        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError):  # no C library to reach: nothing buffered there to lose
        pass
