"""Sparse direct factorizations: scipy's SuperLU always; CHOLMOD's Cholesky when the
optional `fast` extra (the `cvxopt` wheel, which carries CHOLMOD and OpenBLAS) is installed
and the matrix is symmetric positive definite; without it, LAPACK's banded Cholesky (through
scipy) for such a matrix whose rows reverse Cuthill-McKee brings into a narrow band.

The needle's saddle-point solves reuse one factor of K + H over hundreds of Newton
iterations, and every run factors K0 once: on the SH 1/2 scene (1900 dofs, 175 000
nonzeros) CHOLMOD's Cholesky factors K0 in ~17 ms and solves in ~0.17 ms, against SuperLU's
~26 ms and ~0.34 ms (symmetric mode); on its model at half the spacing (the plan's
verification, 7170 dofs) in ~0.12 s and ~3.6 ms against ~0.33 s and ~6.3 ms
(benchmarks/results/model_build_speed.md). SuperLU is the fallback of every other factor.

A symmetric matrix the Cholesky finds not positive definite (the needle's constraint
curvature H, or Saint Venant-Kirchhoff's tangent under strong compression, can make K + H
indefinite) gets CHOLMOD's simplicial L D L^T: no pivoting beyond the fill-reducing
ordering, so one solve's residual is checked (LDL_CHECK) and SuperLU factors the matrix
where it fails. It keeps the indefinite K + H of the SH 1/2 100 x 30 and 100 x 40 blocks
on CHOLMOD, so those runs import no scipy.sparse.linalg (~0.07 s; tests/test_factorization.py;
benchmarks/plan_speed.py's levers table times them with SuperLU instead).

Without CHOLMOD, a small model's K0 and K + H are factored faster in a band than by SuperLU:
reverse Cuthill-McKee leaves the needle20 scenes' K0 (1100-1200 dofs) a band 230-330 rows
wide, which LAPACK's dpbtrf factors in 4-6 ms and dpbtrs solves in 0.09-0.14 ms, against
SuperLU's 10 ms and 0.18-0.21 ms (benchmarks/results/banded_factor.md). A band holds
n x (bandwidth + 1) numbers whatever the fill a sparse factor would have, and its solves take
their columns one at a time, so where it is wide (sh12_100x100's K0, 1900 dofs, a band 403
wide, 4.4 times K's stored entries) a planned run is slower with it; it is used only where it
holds at most BANDED_STORAGE times K's stored entries. CHOLMOD's solves are faster still, so
it stays off where CHOLMOD runs.

STITCHPLAN_LINEAR_BACKEND=scipy turns CHOLMOD off (the path without the `fast` extra),
STITCHPLAN_LINEAR_BACKEND=superlu CHOLMOD and the band; any other value is an InputError (raised
as this module is imported, which the commands do after checking their options).
Every factor says which backend made it (`backend`), and the run summaries record it.
"""

from __future__ import annotations

import os

import numpy as np
import scipy.sparse as sp

from ..errors import InputError, NumericalFailure

try:  # the `fast` extra; imported with the module, as scipy is, not within a run
    from cvxopt import cholmod, matrix as dense, spmatrix
except (ImportError, OSError):
    cholmod = None

SUPERLU = "scipy SuperLU (splu, MMD_AT_PLUS_A ordering, symmetric mode)"
BANDED = "LAPACK banded Cholesky (scipy dpbtrf, reverse Cuthill-McKee ordering)"
CHOLMOD = "CHOLMOD Cholesky (cvxopt)"
CHOLMOD_LDL = "CHOLMOD LDL^T (cvxopt, simplicial)"
LDL_CHECK = 1e-10  # |A x - b| / |b| an L D L^T factor's solve must reach on a test vector
BACKEND_VARIABLE = "STITCHPLAN_LINEAR_BACKEND"  # the factorizations the runs may use (module docstring)
BACKEND_SWITCHES = {"scipy": "no CHOLMOD, as without the fast extra", "superlu": "scipy's SuperLU alone"}
BANDED_STORAGE = 4.0  # the band (n x (bandwidth + 1) numbers) at most this many times K's stored
# entries: 2.1-3.6 on the shipped needle scenes' K0 whose planned runs it makes faster, 4.4 on
# sh12_100x100's, whose it makes slower (benchmarks/banded_factor.py)


class SingularMatrix(NumericalFailure):
    """SuperLU met a zero pivot: the matrix is singular to rounding (scipy raises a bare
    RuntimeError, which would end a command with a traceback)."""


class BandedCholeskyFactor:
    """L L^T of a symmetric positive definite matrix held as a band (LAPACK dpbtrf / dpbtrs
    through scipy), its rows and columns renumbered by reverse Cuthill-McKee to narrow the
    band; made from `narrow_band`. Raises ValueError where the matrix is not positive definite
    (or not finite)."""

    backend = BANDED

    def __init__(self, band: tuple[np.ndarray, np.ndarray]):
        from scipy.linalg.lapack import dpbtrf, dpbtrs  # imported at start-up without CHOLMOD (below)

        lower, self._order = band
        self._dpbtrs = dpbtrs
        self._factor, info = dpbtrf(lower, lower=1, overwrite_ab=1)
        if info != 0 or not np.isfinite(self._factor[0]).all():  # the factor's diagonal
            raise ValueError("not positive definite")
        self._position = np.empty_like(self._order)  # row i of the matrix is row position[i] of the band
        self._position[self._order] = np.arange(len(self._order))

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        solution, _info = self._dpbtrs(self._factor, rhs[self._order], lower=1, overwrite_b=1)
        return solution[self._position]

    def solve_columns(self, columns: sp.spmatrix) -> np.ndarray:
        """The solutions (n, k) for the k sparse right-hand sides `columns` (n, k)."""
        return self.solve(columns.toarray())


def narrow_band(matrix: sp.spmatrix) -> tuple[np.ndarray, np.ndarray] | None:
    """The lower band of a symmetric matrix in reverse Cuthill-McKee order, as LAPACK's
    banded Cholesky takes it ((bandwidth + 1, n), Fortran order: row d holds the d-th
    subdiagonal), and that order; None where the band would hold more than BANDED_STORAGE
    times the matrix's stored entries."""
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    matrix = sp.csr_matrix(matrix)
    if not matrix.has_canonical_format:  # summed in a copy: the caller's arrays stay as they are
        matrix = matrix.copy()
        matrix.sum_duplicates()
    n = matrix.shape[0]
    order = reverse_cuthill_mckee(matrix, symmetric_mode=True)
    position = np.empty(n, dtype=np.intp)
    position[order] = np.arange(n)
    rows = np.repeat(position, np.diff(matrix.indptr))
    columns = position[matrix.indices]
    lower = rows >= columns
    diagonal = rows[lower] - columns[lower]  # which subdiagonal each lower entry is on
    bandwidth = int(diagonal.max()) if len(diagonal) else 0
    if n * (bandwidth + 1) > BANDED_STORAGE * max(matrix.nnz, 1):
        return None
    band = np.zeros((bandwidth + 1, n), order="F")
    band[diagonal, columns[lower]] = matrix.data[lower]
    return band, order


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

    @property
    def stored_entries(self) -> int:
        """Entries of the factors L and U (the fill, benchmarks/deform_speed.py)."""
        return self._lu.L.nnz + self._lu.U.nnz


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


Factor = SuperLUFactor | BandedCholeskyFactor | CholeskyFactor


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


def _switch() -> str:
    """BACKEND_VARIABLE's value ("" unset); an InputError for a value it does not take."""
    given = os.environ.get(BACKEND_VARIABLE, "")
    switch = given.strip().lower()
    if switch and switch not in BACKEND_SWITCHES:
        raise InputError(f"{BACKEND_VARIABLE}: got {given!r}, expected "
                         + " or ".join(f"{name} ({what})" for name, what in BACKEND_SWITCHES.items())
                         + ", or unset for the default")
    return switch


def _path() -> str:
    """What factors a symmetric positive definite matrix: "cholmod" (the `fast` extra, not
    switched off), else "band" where its band is narrow (CHOLMOD's solves are faster), or
    "superlu" with STITCHPLAN_LINEAR_BACKEND=superlu. The switch is checked with or without
    CHOLMOD: a value it does not take is refused as this module is imported."""
    switch = _switch()
    if cholmod is not None and switch not in ("superlu", "scipy"):
        return "cholmod"
    return "superlu" if switch == "superlu" else "band"


def cholesky_available() -> bool:
    return _path() == "cholmod"


def band_allowed() -> bool:
    """Whether a narrow band's Cholesky factors what CHOLMOD would."""
    return _path() == "band"


# scipy.sparse.linalg (with scipy.linalg ~70 ms) and the band's modules are imported with this
# module where scipy factors every matrix, so that a run's time is its own; with CHOLMOD
# SuperLU's are imported the first time it runs (an indefinite matrix whose L D L^T fails the
# check: none of the shipped needle scenes')
if not cholesky_available():
    import scipy.linalg.lapack  # noqa: F401
    import scipy.sparse.csgraph  # noqa: F401
    import scipy.sparse.linalg  # noqa: F401


def factorize(matrix: sp.spmatrix, symmetric_positive: bool = False) -> Factor:
    """A factor of `matrix` with `.solve(rhs)` (rhs (n,) or (n, k)) and `.backend`: where the
    caller knows the matrix is symmetric (`symmetric_positive`) and CHOLMOD is available, its
    Cholesky, or its L D L^T where the matrix is not positive definite (the needle's
    constraint curvature H can make K + H indefinite); without CHOLMOD, the banded Cholesky
    where the matrix is symmetric positive definite and its band narrow (narrow_band);
    SuperLU otherwise, or where the L D L^T is not accurate."""
    path = _path() if symmetric_positive else "superlu"
    if path == "cholmod":
        stored = cholmod_matrix(matrix)
        try:
            return CholeskyFactor(stored)
        except ValueError:  # not positive definite
            pass
        try:
            return LDLFactor(matrix, stored)
        except ValueError:  # a pivot near zero
            pass
    elif path == "band":
        band = narrow_band(matrix)
        if band is not None:
            try:
                return BandedCholeskyFactor(band)
            except ValueError:  # not positive definite
                pass
    return SuperLUFactor(matrix)
