"""The needle's saddle-point solves by block elimination (SaddlePointSolver.solve_direct, eq.
3.62) against the whole system solved densely, on both of its ways to form the Schur
complement: from the kept E K^-1 E^T while the constraint quadrature has at most as many
rows as K has unknowns (2Q <= n), from E K^-1 and a sparse B beyond."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from stitchplan.needle.saddle_point import SaddlePointSolver
from stitchplan.tissue.factorization import factorize


def track_weights(points: int, multipliers: int, rng) -> np.ndarray:
    """B (2 points, m) as the mortar coupling makes it: each point weights the two ends of
    its element (hats along the track) by its normal's two components."""
    along = np.linspace(0.0, multipliers - 1.0, points) + rng.uniform(-0.1, 0.1, points)  # every hat holds points
    along = np.clip(along, 0.0, multipliers - 1.0)
    element = np.minimum(along.astype(int), multipliers - 2)
    upper = along - element
    shares = np.zeros((points, multipliers))
    shares[np.arange(points), element] = 1.0 - upper
    shares[np.arange(points), element + 1] += upper
    angle = rng.uniform(0.0, 2.0 * np.pi, points)
    normal = np.column_stack([np.cos(angle), np.sin(angle)])
    return (shares[:, None, :] * normal[:, :, None]).reshape(2 * points, multipliers)


def dense_saddle_solution(stiffness: np.ndarray, rows: np.ndarray, weights: np.ndarray, rhs: np.ndarray):
    constraints = rows.T @ weights  # G = E^T B
    m = weights.shape[1]
    matrix = np.block([[stiffness, constraints], [constraints.T, np.zeros((m, m))]])
    return np.linalg.solve(matrix, rhs)


def test_both_schur_forms_solve_the_saddle_system_as_a_dense_solve_does():
    rng = np.random.default_rng(7)
    n = 24  # unknowns
    root = rng.standard_normal((n, n))
    stiffness = root @ root.T + n * np.eye(n)
    factor = factorize(sp.csc_matrix(stiffness), symmetric_positive=True)
    solver = SaddlePointSolver(lambda: factor)
    solver.start_at_rest(made_here=True)
    all_rows = sp.random(40, n, density=0.3, random_state=3, format="csr") + sp.eye(40, n, format="csr")
    routes = []
    for points, multipliers in ((4, 3), (10, 5), (16, 7), (20, 9)):  # 2Q = 8, 20 <= n < 32, 40
        rows = all_rows[:2 * points].tocsr()  # the quadrature only grows: earlier rows unchanged
        weights = track_weights(points, multipliers, rng)
        rhs = rng.standard_normal(n + multipliers)
        solution = solver.solve_direct(lambda: None, rhs, False, rows, weights)
        expected = dense_saddle_solution(stiffness, rows.toarray(), weights, rhs)
        np.testing.assert_allclose(solution, expected, rtol=1e-9, atol=1e-11)
        routes.append(solver.state()[4] is not None)
    assert routes == [True, True, False, False]  # E K^-1 E^T dropped once 2Q > n
    # a later run taking over an earlier state solves on with that state's block again
    early = SaddlePointSolver(lambda: factor)
    early.start_at_rest(made_here=True)
    rows, weights = all_rows[:20].tocsr(), track_weights(10, 5, rng)
    rhs = rng.standard_normal(n + 5)
    early.solve_direct(lambda: None, rhs, False, rows, weights)
    solver.restore(early.state())
    assert solver.state()[4] is not None
    np.testing.assert_allclose(solver.solve_direct(lambda: None, rhs, False, rows, weights),
                               dense_saddle_solution(stiffness, rows.toarray(), weights, rhs), rtol=1e-9, atol=1e-11)
