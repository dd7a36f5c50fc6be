"""Linear solves of the needle saddle-point system (thesis eq. 3.62, 3.71-3.74).

    [ K + H   G ] [dd]     [r_u]
    [ G^T     0 ] [dl] = - [ g ]

K is the tissue tangent, H the curvature of the needle constraints weighted by their
multipliers, G the constraint rows (eq. 3.65). Two solvers:

- direct: block elimination on a sparse factor of K + H (tissue/factorization.py: CHOLMOD's
  Cholesky or L D L^T, a band, or SuperLU), kept while Newton converges fast (a modified
  Newton step) and renewed when it slows down;
- minres: MINRES with the block-diagonal preconditioner diag(K0^-1, S^-1) of eq. 3.71-3.72,
  K0 the tangent at zero deformation (factorized once, on first use) and S = G^T K0^-1 G:
  K0^-1 N^T is solved once per needle point, S is re-formed with the current normals each
  Newton iteration and kept as a Cholesky factor, built row by row as eq. 3.73-3.74 border
  S. A MINRES run that stagnates, or whose true residual misses its tolerance, falls back
  to the direct solve and says so.

The thesis writes the Schur block as G^T K G; the preconditioner here uses G^T K0^-1 G,
the Schur complement of the saddle matrix, which is what makes diag(K, S) an optimal
preconditioner (Murphy, Golub and Wathen 2000).

Beyond the factor of K + H, the direct solves need numpy's LAPACK alone (the small Schur
matrix); the MINRES path imports scipy.linalg and scipy.sparse.linalg (~70 ms of start-up)
where it runs.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.sparse as sp

from ..tissue.factorization import SUPERLU, Factor, factorize


class SchurPreconditioner:
    """S^-1 for S = G^T K0^-1 G, factored by bordering one constraint at a time (eq. 3.73-3.74).

    S is kept as its Cholesky factor L (S = L L^T), bordered by one row per constraint.
    Needle points a fraction of the particle spacing apart make S very ill-conditioned
    (cond ~1e10 on the SH 1/2 scenario); bordering the explicit inverse S^-1 then loses all
    accuracy after ~30 points and turns indefinite, which breaks MINRES. Bordering the
    Cholesky factor is the row-by-row Cholesky algorithm, backward stable, and applying
    S^-1 by two triangular solves keeps the preconditioner symmetric positive definite.
    """

    def __init__(self, stiffness_at_rest):
        self.stiffness_at_rest = stiffness_at_rest  # factor of K0
        self.columns = np.zeros((0, 0))  # K0^-1 G, (n, k)
        self.constraints = np.zeros((0, 0))  # G, (n, k)
        self.cholesky = np.zeros((0, 0))  # L, lower triangular, S = L L^T, (k, k)
        self._solved_rows = np.zeros((0, 0))  # K0^-1 N^T, two columns per point, (n, 2k)

    @property
    def size(self) -> int:
        return self.cholesky.shape[0]

    def solve(self, x: np.ndarray) -> np.ndarray:
        """S^-1 x by forward and back substitution with L."""
        if self.size == 0:
            return np.zeros_like(x)
        from scipy.linalg import cho_solve

        return cho_solve((self.cholesky, True), x)

    def _border(self, v: np.ndarray, alpha: float) -> None:
        """L <- [[L, 0], [l^T, d]] with L l = v, d^2 = alpha - l^T l (the new Schur pivot)."""
        from scipy.linalg import solve_triangular

        l = solve_triangular(self.cholesky, v, lower=True) if self.size else np.zeros(0)
        # a constraint (nearly) dependent on the earlier ones leaves the pivot at round-off
        # level: factor S + 1e-12 diag(S) instead (pivots then stay >= ~1e-12 alpha, so l
        # stays bounded), and keep the pivot positive so MINRES sees an SPD preconditioner
        alpha = alpha * (1.0 + 1e-12)
        d = np.sqrt(max(alpha - l @ l, 1e-12 * alpha))
        k = self.size
        grown = np.zeros((k + 1, k + 1))
        grown[:k, :k] = self.cholesky
        grown[k, :k] = l
        grown[k, k] = d
        self.cholesky = grown

    def refresh(self, constraints: sp.spmatrix, expanded_rows: sp.csr_matrix, weights: sp.spmatrix) -> None:
        """Re-form S = G^T K0^-1 G with the current normals (each Newton iteration); G = E^T B
        with E the `expanded_rows` of the constraint quadrature and B the `weights` matrix
        (needle/coupling.py, NeedleCoupling.weights_matrix).

        As the tissue slides along the needle the normals turn, and with nearly dependent
        constraints an S formed with the normals each point had when it was added is a poor
        preconditioner (10x more MINRES iterations and direct fallbacks on the SH 1/2
        scenario). K0^-1 N^T (two directions per point) is solved once per point and cached,
        so only the k x k matrix S and its Cholesky factor are renewed: G = N^T n gives
        K0^-1 G = (K0^-1 N^T) n.
        """
        n = constraints.shape[0]
        solved = self._solved_rows if self._solved_rows.shape[0] == n else np.zeros((n, 0))
        q2 = expanded_rows.shape[0]
        if solved.shape[1] < q2:
            new = self.stiffness_at_rest.solve(expanded_rows[solved.shape[1]: q2].T.toarray())
            solved = np.hstack([solved, new.reshape(n, -1)])
            self._solved_rows = solved
        self.factor(constraints.toarray(), np.asarray(weights.T @ solved[:, :q2].T).T)

    def factor(self, constraints: np.ndarray, columns: np.ndarray) -> None:
        """Keep G and K0^-1 G (n, k), column-major (a contiguous column per constraint), and
        factor S = G^T K0^-1 G into L, bordering one constraint at a time."""
        self.constraints, self.columns = np.asfortranarray(constraints), np.asfortranarray(columns)
        schur = self.constraints.T @ self.columns
        self.cholesky = np.zeros((0, 0))
        for j in range(schur.shape[0]):
            self._border(0.5 * (schur[:j, j] + schur[j, :j]), float(schur[j, j]))


class SaddlePointSolver:
    """Solves of eq. 3.62 for one insertion, with the factors and caches they keep between
    Newton iterations, and counts of the work done.

    `factor_at_rest` returns the factor of K0, the tangent at zero deformation (made when
    first asked for, and kept by whoever made it: needle.prepared_tissue.PreparedTissue): the
    MINRES preconditioner, the condition numbers, and the first direct solves of an insertion
    (start_at_rest) use it.
    """

    def __init__(self, factor_at_rest: Callable[[], Factor], minres_rtol: float = 1e-10,
                 minres_maxiter: int = 400, minres_restarts: int = 4, minres_true_rtol: float = 1e-6):
        self._factor_at_rest = factor_at_rest
        self._schur: SchurPreconditioner | None = None
        self.minres_rtol = minres_rtol
        self.minres_maxiter = minres_maxiter
        self.minres_restarts = minres_restarts  # restarts on the true residual, same budget
        # |b - A x| / |b| a MINRES solution must reach: inexact Newton then contracts by ~1e-6
        # per iteration; 1e-8 costs a third more MINRES iterations on the SH 1/2 scenario
        self.minres_true_rtol = minres_true_rtol
        self._factor = None  # the factor of K + H for the direct solves
        # E (K + H)^-1, the transpose of (K + H)^-1 E^T (K + H symmetric), for that factor in
        # the first `_solved_count` rows of a buffer with room to grow (>= 2Q, n): a new
        # quadrature point's rows are appended, and S = B^T E (K + H)^-1 E^T B takes its
        # contiguous rows through a sparse B (solve_direct); sized by the first solve
        self._solved_rows, self._solved_count = None, 0
        # E (K + H)^-1 E^T for that factor in the first (2Q, 2Q) block of a buffer with room to
        # grow: a snapshot per needle step keeps its block as a view (state), not a copy of its
        # own, so a long insertion's snapshots share a few buffers (a fresh (2Q, 2Q) array per
        # step held ~1.2 GB after 305 steps of 0.01 rad on 99 particles). Kept while 2Q <= n
        # only, None beyond (solve_direct)
        self._coupled: np.ndarray | None = np.zeros((0, 0))
        self.factorizations = 0
        self.solves = 0
        self.solved_columns = 0  # right-hand-side columns through the factor (its solves take them one at a time)
        self.backend = SUPERLU  # of the last factor of K + H (tissue/factorization.py)
        self.backends: list[str] = []  # of every factor used, in the order first used
        self.minres_iterations = 0
        self.fallbacks = 0

    @property
    def stiffness_at_rest(self) -> Factor:
        """The factor of K0 (eq. 3.72)."""
        return self._factor_at_rest()

    def start_at_rest(self, made_here: bool) -> None:
        """Take the factor of K0 as the factor of K + H: an insertion starts at rest with no
        multipliers, where K + H = K0, so its first direct solves need no factorization.
        `made_here`: K0's factor is made for this insertion (counted as its factorization)."""
        self._use(self.stiffness_at_rest)
        self.factorizations += int(made_here)

    def precondition_at_rest(self, made_here: bool) -> None:
        """MINRES's preconditioner takes the factor of K0 (made now when not yet made): counted
        and recorded as the direct solves' factors are, for the summaries' solver counts."""
        factor = self.stiffness_at_rest
        self.factorizations += int(made_here)
        self.backend = factor.backend
        if factor.backend not in self.backends:
            self.backends.append(factor.backend)

    def _use(self, factor: Factor) -> None:
        """Solve with `factor` from now on; the caches of the previous one are dropped."""
        self._factor, self.backend = factor, factor.backend
        if factor.backend not in self.backends:
            self.backends.append(factor.backend)
        self._solved_rows, self._solved_count, self._coupled = None, 0, np.zeros((0, 0))  # sized by the next solve

    def state(self) -> tuple:
        """The direct solves' factor and what is kept for it now, for a later run that takes
        this state over (`restore`). Nothing is copied: a kept buffer's first rows are never
        written again for its factor, and only those are handed on."""
        count = self._solved_count
        rows = None if self._solved_rows is None else self._solved_rows[:count]
        coupled = None if self._coupled is None else self._coupled[:count, :count]
        return self._factor, self.backend, rows, count, coupled

    def restore(self, state: tuple) -> None:
        """Solve on from `state` (made by `state()`), as the run that made it did; the next
        rows added grow a buffer of their own."""
        self._factor, self.backend, self._solved_rows, self._solved_count, self._coupled = state

    def forget(self) -> None:
        """Drop the factor of K + H, so the next direct solve factorizes afresh."""
        self._factor = None

    @property
    def schur(self) -> SchurPreconditioner:
        """The S^-1 block of the MINRES preconditioner."""
        if self._schur is None:
            self._schur = SchurPreconditioner(self.stiffness_at_rest)
        return self._schur

    def solve_direct(self, stiffness: Callable[[], sp.spmatrix], rhs: np.ndarray, refactor: bool,
                     rows: sp.csr_matrix, weights: np.ndarray,
                     on_rows: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """Block elimination with a sparse factor of K + H (renewed when `refactor` or missing):

            a = K^-1 (-r_u),  S = G^T K^-1 G,  dl = S^-1 (G^T a + g),  dd = a - K^-1 G dl

        G^T dd = -g holds exactly even with an older factor of K, so the constraints
        converge at once; an older K only slows the equilibrium residual (modified Newton).
        `stiffness` returns the current K + H when a factor is needed. G = E^T B with E the
        interleaved shape-function `rows` of the constraint quadrature (2Q, n) and B the
        dense `weights` (2Q, m) that carry the normals (NeedleCoupling.normal_weights).
        For one factor, E K^-1 (2Q, n) and E K^-1 E^T (2Q, 2Q) are kept and grown by the
        rows of new quadrature points only, so an iteration costs one solve with the factor,
        one sparse product E a and small dense products. Once the constraint quadrature has
        more rows than K has unknowns (2Q > n: long insertions in small needle steps), S is
        formed as B^T E (K^-1 E^T B) instead, in ~n x B's entries operations rather than
        (2Q)^2 m, and E K^-1 E^T, (2Q)^2 floats, is no longer kept. `rhs` may hold several
        columns.

        `on_rows` = (C (2Q, j), h (m, j)): j more right-hand sides [E^T C; h], whose K^-1 E^T C
        comes from the kept rows without a solve (the factor's solves take their columns one
        at a time); their solutions follow rhs's columns.
        """
        n, k = rows.shape[1], weights.shape[1]
        if refactor or self._factor is None:
            self._use(factorize(stiffness(), symmetric_positive=True))  # K + H: symmetric
            self.factorizations += 1
        if self._solved_rows is None:
            self._solved_rows = np.zeros((0, n))
        if rhs.ndim == 2 and rhs.shape[1] == 0:  # only `on_rows` columns
            a = np.zeros((n, 0))
        else:
            a = self._factor.solve(rhs[:n])
            self.solves += 1
            self.solved_columns += 1 if rhs.ndim == 1 else rhs.shape[1]
        if k == 0 and on_rows is None:
            return a
        self._grow(rows)
        count = rows.shape[0]
        solved = self._solved_rows[:count]  # E K^-1 (2Q, n)
        constraint_rhs = rhs[n:]
        if on_rows is not None:
            a = np.column_stack([a, solved.T @ on_rows[0]])
            constraint_rhs = np.column_stack([constraint_rhs, on_rows[1]])
        if k == 0:
            return a
        if self._coupled is not None:
            spread = None
            schur = weights.T @ self._coupled[:count, :count] @ weights  # G^T K^-1 G
        else:
            # K^-1 G (n, m), B taken sparse: a point weights its element's ends only
            spread = (sp.csr_matrix(weights).T @ solved).T
            schur = weights.T @ (rows @ spread)
            schur = 0.5 * (schur + schur.T)
        right = weights.T @ (rows @ a) - constraint_rhs
        try:  # the small Schur matrix: its Cholesky tests that it is positive definite (numpy has
            np.linalg.cholesky(schur)  # no triangular solve to reuse it with; m ~ 20-40: microseconds)
            multipliers = np.linalg.solve(schur, right)
        except np.linalg.LinAlgError:  # not positive definite: nearly dependent constraints, least squares
            multipliers = np.linalg.lstsq(schur, right, rcond=1e-13)[0]
        correction = solved.T @ (weights @ multipliers) if spread is None else spread @ multipliers
        return np.concatenate([a - correction, multipliers])

    def _grow(self, rows: sp.csr_matrix) -> None:
        """Extend E K^-1 and E K^-1 E^T by the rows added since the last solve (the
        constraint quadrature only grows during an insertion, its earlier rows unchanged). The
        latter is dropped (None) once the rows outnumber the unknowns (solve_direct), and stays
        so while they grow, until a new factor (_use) or a kept state (restore) replaces both."""
        have, count = self._solved_count, rows.shape[0]
        if have >= count:
            return
        first = rows.indptr[have]  # the new rows, from the CSR arrays (cheaper than slicing)
        added = sp.csr_matrix((rows.data[first:], rows.indices[first:], rows.indptr[have:] - first),
                              shape=(count - have, rows.shape[1]))
        new = self._factor.solve_columns(added.T)  # (n, new)
        self.solved_columns += count - have
        if len(self._solved_rows) < count:  # room for the next steps' rows too
            grown = np.empty((max(count, 2 * len(self._solved_rows)), len(new)))
            grown[:have] = self._solved_rows[:have]
            self._solved_rows = grown
        self._solved_rows[have:count] = new.T
        self._solved_count = count
        if count > rows.shape[1]:
            self._coupled = None
            return
        cross = rows @ new  # E K^-1 E_new^T, (count, new)
        if self._coupled.shape[0] < count:  # room for the next steps' rows too
            grown = np.empty((max(count, 2 * self._coupled.shape[0]),) * 2)
            grown[:have, :have] = self._coupled[:have, :have]
            self._coupled = grown
        coupled = self._coupled  # written past the first `have` rows and columns only
        coupled[:count, have:count] = cross
        coupled[have:count, :have] = cross[:have].T
        coupled[have:count, have:count] = 0.5 * (cross[have:] + cross[have:].T)

    def solve_minres(self, stiffness_product: Callable[[np.ndarray], np.ndarray], constraints: sp.spmatrix,
                     rhs: np.ndarray, expanded_rows: sp.csr_matrix,
                     weights: sp.spmatrix) -> tuple[np.ndarray | None, int]:
        """MINRES on the saddle system with diag(K0^-1, S^-1), S re-formed from the current
        G = N^T n (SchurPreconditioner.refresh). Returns (solution or None, iterations)."""
        import scipy.sparse.linalg as spla

        n, k = constraints.shape
        g_t = constraints.T.tocsr()
        if k:
            self.schur.refresh(constraints, expanded_rows, weights)

        def matvec(x):
            return np.concatenate([stiffness_product(x[:n]) + constraints @ x[n:], g_t @ x[:n]])

        def precondition(x):
            return np.concatenate([self.stiffness_at_rest.solve(x[:n]), self.schur.solve(x[n:])])

        operator = spla.LinearOperator((n + k, n + k), matvec=matvec, dtype=float)
        preconditioner = spla.LinearOperator((n + k, n + k), matvec=precondition, dtype=float)
        count = [0]
        # scipy's MINRES stops on the backward-error test |r| <= rtol (|A| |x| + |b|) in the
        # preconditioned norm; with nearly dependent needle constraints |A| is huge and the
        # test passes while the true |r| / |b| is 1e-4 ... 1 (Newton then stalls). Check the
        # true residual and restart MINRES on it, within the same iteration budget.
        solution, target, converged = np.zeros_like(rhs), self.minres_true_rtol * np.linalg.norm(rhs), False
        for restart in range(self.minres_restarts + 1):
            remainder = rhs - matvec(solution) if restart else rhs
            converged = bool(np.linalg.norm(remainder) <= max(target, 1e-300))
            if converged or restart == self.minres_restarts or count[0] >= self.minres_maxiter:
                break
            try:
                correction, _info = spla.minres(operator, remainder, M=preconditioner, rtol=self.minres_rtol,
                                               maxiter=self.minres_maxiter - count[0],
                                               callback=lambda _x: count.__setitem__(0, count[0] + 1))
            except ValueError:  # MINRES met a non-positive preconditioner inner product
                break
            solution = solution + correction
        self.minres_iterations += count[0]
        return (solution if converged else None), count[0]


def saddle_matrix(stiffness: sp.spmatrix, constraints: sp.spmatrix) -> sp.csc_matrix:
    """[[K + H, G], [G^T, 0]] of eq. 3.62."""
    k = constraints.shape[1]
    return sp.bmat([[stiffness, constraints], [constraints.T, sp.csr_matrix((k, k))]], format="csc")


def condition_numbers(stiffness: sp.spmatrix, constraints: sp.spmatrix, stiffness_at_rest) -> tuple[float, float]:
    """cond of the saddle matrix and of the block-preconditioned one (dense; small systems only).

    The preconditioner is P = diag(K0, S), S = G^T K0^-1 G, as MINRES uses it; S is applied
    through its Cholesky factor, which stays positive definite where an explicit inverse
    would not (needle points closer than the particle spacing).
    """
    saddle = saddle_matrix(stiffness, constraints).toarray()
    eigenvalues = np.abs(np.linalg.eigvalsh(saddle))
    n, k = constraints.shape
    k0_inverse = stiffness_at_rest.solve(np.eye(n))
    # P^-1 = Z Z^T with Z = diag(C, L^-T), K0^-1 = C C^T and S = L L^T; the eigenvalues of
    # P^-1 A equal those of Z^T A Z
    c = np.linalg.cholesky(0.5 * (k0_inverse + k0_inverse.T))
    g = constraints.toarray()
    schur = SchurPreconditioner(stiffness_at_rest)
    schur.factor(g, k0_inverse @ g)
    from scipy.linalg import solve_triangular

    off = solve_triangular(schur.cholesky, (g.T @ c), lower=True).T if k else np.zeros((n, 0))
    top = c.T @ saddle[:n, :n] @ c
    transformed = np.block([[top, off], [off.T, np.zeros((k, k))]])
    preconditioned = np.abs(np.linalg.eigvalsh(0.5 * (transformed + transformed.T)))
    return float(eigenvalues.max() / eigenvalues.min()), float(preconditioned.max() / preconditioned.min())
