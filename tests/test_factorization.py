"""Sparse direct factorizations (stitchplan/tissue/factorization.py): SuperLU always, CHOLMOD's
Cholesky from the optional `fast` extra for symmetric positive definite matrices, its L D L^T
for symmetric indefinite ones (checked, and SuperLU where it fails), LAPACK's banded Cholesky
without CHOLMOD where the band is narrow, and the switches that turn them off."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import scipy.sparse as sp

from stitchplan.errors import InputError
from stitchplan.tissue.factorization import (CHOLMOD, CHOLMOD_LDL, SUPERLU, SuperLUFactor, band_allowed,
                                              cholesky_available, condition_estimate, factorize)


def spd_matrix(n: int = 40, seed: int = 2) -> sp.csr_matrix:
    rng = np.random.default_rng(seed)
    a = sp.random(n, n, density=0.1, random_state=rng)
    return (a @ a.T + n * sp.eye(n)).tocsr()


def test_the_condition_estimate_follows_the_condition_number_to_a_singular_matrix():
    """Within 3x of the eigenvalue ratio from 1e2 to 1e14 (1.9x here: Gershgorin's bound over
    three inverse iterations); above 1e15 where the smallest eigenvalue is lost to rounding."""
    basis = np.linalg.qr(np.random.default_rng(3).standard_normal((60, 60)))[0]
    for condition in (1e2, 1e8, 1e14, 1e20):
        eigenvalues = np.geomspace(1.0, 1.0 / condition, 60)
        matrix = sp.csr_matrix(basis @ np.diag(eigenvalues) @ basis.T)
        estimate = condition_estimate(matrix, SuperLUFactor(matrix))
        if condition < 1e15:
            assert condition / 3 < estimate < 3 * condition, (condition, estimate)
        else:
            assert estimate > 1e15, estimate


def test_superlu_solves_one_and_several_right_hand_sides():
    matrix = spd_matrix()
    factor = factorize(matrix)  # not declared symmetric: always SuperLU
    assert isinstance(factor, SuperLUFactor) and factor.backend == SUPERLU
    rhs = np.random.default_rng(1).standard_normal((40, 3))
    np.testing.assert_allclose(matrix @ factor.solve(rhs), rhs, atol=1e-10)
    np.testing.assert_allclose(matrix @ factor.solve(rhs[:, 0]), rhs[:, 0], atol=1e-10)


def test_sparse_columns_solve_like_their_dense_right_hand_sides():
    """solve_columns (the needle's new constraint rows, needle/saddle_point.py) gives what solve
    gives for the same columns made dense, on every backend, one column or several."""
    matrix = spd_matrix()
    columns = sp.random(40, 3, density=0.2, random_state=np.random.default_rng(4), format="csc")
    indefinite = matrix - 2.0 * 40 * sp.eye(40)
    factors = [SuperLUFactor(matrix)]
    if cholesky_available():
        factors += [factorize(matrix, symmetric_positive=True), factorize(indefinite, symmetric_positive=True)]
        assert [f.backend for f in factors[1:]] == [CHOLMOD, CHOLMOD_LDL]
    for factor in factors:
        for block in (columns, columns[:, :1]):
            solved = factor.solve_columns(block)
            assert solved.shape == block.shape
            np.testing.assert_allclose(solved, factor.solve(block.toarray()), rtol=0, atol=1e-13)


def test_the_switch_turns_the_cholesky_off(monkeypatch):
    monkeypatch.setenv("STITCHPLAN_LINEAR_BACKEND", "superlu")
    assert not cholesky_available()
    assert factorize(spd_matrix(), symmetric_positive=True).backend == SUPERLU


def test_an_unknown_switch_value_is_refused_naming_the_variable(monkeypatch):
    """A misspelt backend used to run the default silently: the run then says it, and the
    switch's values are taken whatever their case and surrounding blanks."""
    monkeypatch.setenv("STITCHPLAN_LINEAR_BACKEND", "cholmodd")
    with pytest.raises(InputError, match=r"STITCHPLAN_LINEAR_BACKEND: got 'cholmodd', expected scipy .* or superlu"):
        cholesky_available()
    monkeypatch.setenv("STITCHPLAN_LINEAR_BACKEND", " SuperLU ")
    assert not cholesky_available() and not band_allowed()


@pytest.mark.skipif(not cholesky_available(), reason="the optional `fast` extra (cvxopt) is not installed")
def test_cholesky_solves_like_superlu_and_falls_back_silently_where_not_positive_definite(capfd):
    """Positive definite: the Cholesky. Indefinite: the L D L^T, as accurate as SuperLU. A
    zero pivot whatever the ordering ([[0, 1], [1, 0]] blocks), or one so small that the
    L D L^T solve is NaN: SuperLU."""
    matrix = spd_matrix()
    rhs = np.random.default_rng(3).standard_normal((40, 2))
    cholesky = factorize(matrix, symmetric_positive=True)
    assert cholesky.backend == CHOLMOD
    np.testing.assert_allclose(cholesky.solve(rhs), SuperLUFactor(matrix).solve(rhs), rtol=0, atol=1e-12)
    np.testing.assert_allclose(cholesky.solve(rhs[:, 0]), SuperLUFactor(matrix).solve(rhs[:, 0]), rtol=0, atol=1e-12)
    indefinite = matrix - 2.0 * 40 * sp.eye(40)  # symmetric, negative eigenvalues
    factor = factorize(indefinite, symmetric_positive=True)
    assert factor.backend == CHOLMOD_LDL
    np.testing.assert_allclose(factor.solve(rhs), SuperLUFactor(indefinite).solve(rhs), rtol=0, atol=1e-12)
    swaps = sp.block_diag([np.array([[0.0, 1.0], [1.0, 0.0]])] * 20, format="csr")
    factor = factorize(swaps, symmetric_positive=True)
    assert factor.backend == SUPERLU
    np.testing.assert_allclose(swaps @ factor.solve(rhs), rhs, atol=1e-12)
    # a pivot so small that L D L^T's solve is not finite (NaN): refused as inaccurate too
    tiny_pivot = sp.csr_matrix(np.array([[1e-310, 1.0], [1.0, 1.0]]))
    factor = factorize(tiny_pivot, symmetric_positive=True)
    assert factor.backend == SUPERLU
    np.testing.assert_allclose(factor.solve(np.array([1.0, 2.0])), [1.0, 1.0], rtol=1e-12)
    assert capfd.readouterr().err == ""  # CHOLMOD's own warning does not reach the user


@pytest.mark.skipif(not cholesky_available(), reason="the optional `fast` extra (cvxopt) is not installed")
def test_cholmods_matrix_is_the_lower_triangle_in_column_order():
    """cholmod_matrix stores tril(A) as CHOLMOD keeps it (columns, rows ascending in each), the
    values as given: for a canonical matrix and for one with unsorted and duplicate entries
    (summed), which is left as it was."""
    from stitchplan.tissue.factorization import cholmod_matrix

    canonical = spd_matrix(30)
    rng = np.random.default_rng(5)
    # each row's entries given twice, as halves, in a shuffled order: CSR arrays as they are
    row_of = np.repeat(np.arange(canonical.shape[0]), np.diff(canonical.indptr))
    doubled = np.concatenate([np.arange(canonical.nnz)] * 2)
    doubled = doubled[np.lexsort((rng.random(len(doubled)), row_of[doubled]))]
    duplicated = sp.csr_matrix((canonical.data[doubled] / 2, canonical.indices[doubled], 2 * canonical.indptr),
                               shape=canonical.shape)
    assert duplicated.nnz == 2 * canonical.nnz and not duplicated.has_canonical_format
    given = (duplicated.data.copy(), duplicated.indices.copy(), duplicated.indptr.copy())
    for matrix in (canonical, duplicated):
        stored = cholmod_matrix(matrix)
        expected = sp.tril(matrix, format="csc")
        expected.sum_duplicates()
        colptr, rows, values = (np.array(part).ravel() for part in stored.CCS)
        assert np.array_equal(colptr, expected.indptr) and np.array_equal(rows, expected.indices)
        np.testing.assert_allclose(values, expected.data, rtol=1e-15, atol=0)
    assert all(np.array_equal(a, b) for a, b in zip(given, (duplicated.data, duplicated.indices, duplicated.indptr)))


@pytest.mark.skipif(not cholesky_available(), reason="the optional `fast` extra (cvxopt) is not installed")
def test_an_indefinite_factor_imports_no_scipy_sparse_linalg():
    """With CHOLMOD a symmetric indefinite matrix (K + H of the narrow SH 1/2 blocks) is
    factored without SuperLU, whose scipy.sparse.linalg costs ~0.07 s of start-up."""
    script = ("import sys, numpy as np, scipy.sparse as sp\n"
              "from stitchplan.tissue.factorization import factorize\n"
              "matrix = sp.diags(np.linspace(-1.0, 1.0, 40) + 0.01).tocsr()\n"
              "factorize(matrix, symmetric_positive=True)\n"
              "print('scipy.sparse.linalg' in sys.modules)\n")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert result.stdout == "False\n"


@pytest.mark.skipif(not cholesky_available(), reason="the optional `fast` extra (cvxopt) is not installed")
def test_cholmods_warning_reaches_neither_stream_of_a_process_whose_output_is_a_pipe():
    """Nothing of CHOLMOD's not-positive-definite case reaches the streams, also where C's
    stdout is buffered until exit (stdout a pipe: a `plan` piped into a file)."""
    script = ("import numpy as np, scipy.sparse as sp\n"
              "from stitchplan.tissue.factorization import factorize\n"
              "matrix = sp.diags(np.linspace(-1.0, 1.0, 40) + 0.01).tocsr()\n"
              "print('backend', factorize(matrix, symmetric_positive=True).backend)\n")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True)
    assert result.stdout == f"backend {CHOLMOD_LDL}\n"
    assert result.stderr == ""


def test_the_largest_row_sum_is_gershgorins_bound_with_empty_rows_and_duplicates():
    """The condition estimate's largest eigenvalue bound, max_i sum_j |A_ij|, from the stored
    values by row: rows without entries count zero (reduceat alone would give them the next
    row's first value), duplicate entries each count."""
    from stitchplan.tissue.factorization import _largest_row_sum

    matrix = sp.csr_matrix((np.array([-3.0, 1.0, 2.0, -0.5]), np.array([0, 2, 1, 1]), np.array([0, 2, 2, 4, 4])),
                           shape=(4, 3))  # rows 1 and 3 empty; row 2 holds column 1 twice
    assert _largest_row_sum(matrix) == 4.0
    assert _largest_row_sum(-matrix) == float(abs(matrix).sum(axis=1).max())
    assert _largest_row_sum(sp.csr_matrix((3, 3))) == 0.0
    dense = np.random.default_rng(5).standard_normal((30, 30))
    dense[7] = 0.0
    assert np.isclose(_largest_row_sum(sp.csr_matrix(dense)), np.abs(dense).sum(axis=1).max(), rtol=1e-15)


def lattice_matrix(m: int = 12, seed: int = 6) -> sp.csr_matrix:
    """A positive definite 5-point stencil on an m x m lattice with its rows shuffled: a
    matrix whose band is narrow once reordered (2.2x its stored entries), wide as given."""
    step = sp.diags([-1.0, 2.5, -1.0], [-1, 0, 1], shape=(m, m))
    lattice = (sp.kron(step, sp.eye(m)) + sp.kron(sp.eye(m), step)).tocsr()
    shuffle = np.random.default_rng(seed).permutation(m * m)
    return lattice[shuffle][:, shuffle].tocsr()


def test_without_cholmod_a_narrow_band_is_factored_by_lapacks_banded_cholesky(monkeypatch):
    """STITCHPLAN_LINEAR_BACKEND=scipy (the path without the `fast` extra): a positive definite
    matrix that reverse Cuthill-McKee brings into a narrow band gets the banded Cholesky, which
    solves one and several right-hand sides and sparse columns as SuperLU does."""
    from stitchplan.tissue.factorization import BANDED, BandedCholeskyFactor

    monkeypatch.setenv("STITCHPLAN_LINEAR_BACKEND", "scipy")
    assert not cholesky_available()
    matrix = lattice_matrix()
    factor = factorize(matrix, symmetric_positive=True)
    assert isinstance(factor, BandedCholeskyFactor) and factor.backend == BANDED
    rng = np.random.default_rng(7)
    rhs = rng.standard_normal((matrix.shape[0], 3))
    given = rhs.copy()
    reference = SuperLUFactor(matrix)
    np.testing.assert_allclose(factor.solve(rhs), reference.solve(rhs), rtol=0, atol=1e-13)
    np.testing.assert_allclose(factor.solve(rhs[:, 1]), reference.solve(rhs[:, 1]), rtol=0, atol=1e-13)
    assert factor.solve(rhs[:, 1]).shape == (matrix.shape[0],)
    assert np.array_equal(rhs, given)  # the right-hand side is not overwritten
    columns = sp.random(matrix.shape[0], 4, density=0.1, random_state=rng, format="csc")
    np.testing.assert_allclose(factor.solve_columns(columns), reference.solve(columns.toarray()), rtol=0, atol=1e-13)
    assert factorize(matrix).backend == SUPERLU  # not declared symmetric


def test_the_band_holds_the_reordered_lower_triangle_and_leaves_the_matrix_as_given():
    """narrow_band's (bandwidth + 1, n) array is the lower triangle of P A P^T by subdiagonal,
    for a canonical matrix and one with unsorted and duplicate entries (summed in a copy)."""
    from stitchplan.tissue.factorization import narrow_band

    canonical = lattice_matrix()
    n = canonical.shape[0]
    band, order = narrow_band(canonical)
    assert sorted(order) == list(range(n)) and band.shape == (13, n)  # the lattice's 12 + 1
    permuted = canonical[order][:, order].toarray()
    rebuilt = np.zeros((n, n))
    for d in range(band.shape[0]):
        rebuilt[np.arange(d, n), np.arange(n - d)] = band[d, :n - d]
    np.testing.assert_array_equal(rebuilt, np.tril(permuted))
    assert all(not band[d, n - d:].any() for d in range(1, band.shape[0]))  # the padding past the end
    rng = np.random.default_rng(5)  # each row's entries given twice, as halves, shuffled
    row_of = np.repeat(np.arange(n), np.diff(canonical.indptr))
    doubled = np.concatenate([np.arange(canonical.nnz)] * 2)
    doubled = doubled[np.lexsort((rng.random(len(doubled)), row_of[doubled]))]
    duplicated = sp.csr_matrix((canonical.data[doubled] / 2, canonical.indices[doubled], 2 * canonical.indptr),
                               shape=canonical.shape)
    assert not duplicated.has_canonical_format
    given = (duplicated.data.copy(), duplicated.indices.copy(), duplicated.indptr.copy())
    again, same_order = narrow_band(duplicated)
    assert np.array_equal(same_order, order)
    np.testing.assert_allclose(again, band, rtol=1e-15, atol=0)
    assert all(np.array_equal(a, b) for a, b in zip(given, (duplicated.data, duplicated.indices, duplicated.indptr)))


def test_a_wide_band_an_indefinite_matrix_and_the_superlu_switch_go_to_superlu(monkeypatch):
    """No band where it would hold more than BANDED_STORAGE times the stored entries (a
    random sparse matrix), nor where the Cholesky meets a non-positive pivot (indefinite, or not
    finite), nor with STITCHPLAN_LINEAR_BACKEND=superlu: SuperLU, as accurate."""
    from stitchplan.tissue.factorization import BandedCholeskyFactor, narrow_band

    monkeypatch.setenv("STITCHPLAN_LINEAR_BACKEND", "scipy")
    scattered = sp.random(200, 200, density=0.01, random_state=np.random.default_rng(8))
    wide = (scattered + scattered.T + 10.0 * sp.eye(200)).tocsr()  # a random graph: no narrow ordering
    assert narrow_band(wide) is None
    assert factorize(wide, symmetric_positive=True).backend == SUPERLU
    indefinite = lattice_matrix() - 3.0 * sp.eye(144)
    with pytest.raises(ValueError, match="not positive definite"):
        BandedCholeskyFactor(narrow_band(indefinite))
    factor = factorize(indefinite, symmetric_positive=True)
    assert factor.backend == SUPERLU
    rhs = np.cos(np.arange(144.0))
    np.testing.assert_allclose(indefinite @ factor.solve(rhs), rhs, atol=1e-11)
    broken = lattice_matrix().tolil()
    broken[5, 5] = np.nan
    with pytest.raises(ValueError, match="not positive definite"):
        BandedCholeskyFactor(narrow_band(broken))
    monkeypatch.setenv("STITCHPLAN_LINEAR_BACKEND", "superlu")
    assert factorize(lattice_matrix(), symmetric_positive=True).backend == SUPERLU
