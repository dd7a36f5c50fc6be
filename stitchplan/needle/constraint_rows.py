"""The shape-function rows of the needle track's points as the track grows (needle/coupling.py):
rows are appended, never changed, to buffers with room to grow (AppendedRows), with their
interleaved form E and its transpose (GrowingRows); a needle step's kept state shares its
rows with the coupling until the next append.
"""

from __future__ import annotations

import copy

import numpy as np
import scipy.sparse as sp

from ..tissue.shape_functions import rows_csr

# Rows of the track's sparse matrices are handled as blocks (data, indices, entries per row):
# joining arrays and building one CSR matrix per change costs less than scipy's slicing and
# stacking of these few rows.
RowBlock = tuple[np.ndarray, np.ndarray, np.ndarray]


def row_block(rows: sp.csr_matrix, start: int, stop: int) -> RowBlock:
    """rows[start:stop] as a block."""
    first, last = rows.indptr[start], rows.indptr[stop]
    return rows.data[first:last], rows.indices[first:last], np.diff(rows.indptr[start:stop + 1])


def empty_row_block(count: int) -> RowBlock:
    """`count` rows of zeros."""
    return np.zeros(0), np.zeros(0, dtype=np.int32), np.zeros(count, dtype=np.int64)


def _interleaved(block: RowBlock) -> RowBlock:
    """N T acting on interleaved dofs: row q becomes rows (q, 0) and (q, 1) with columns
    (p, 0) and (p, 1) (a row's columns stay in their order)."""
    data, indices, counts = block
    row = np.repeat(np.arange(len(counts)), counts)
    order = np.argsort(np.concatenate([2 * row, 2 * row + 1]), kind="stable")
    return (np.concatenate([data, data])[order], np.concatenate([2 * indices, 2 * indices + 1])[order],
            np.repeat(counts, 2))


def joined_rows(*matrices: sp.csr_matrix) -> sp.csr_matrix:
    """CSR matrices of one width one under the other, as one new matrix."""
    offsets = np.cumsum([0] + [matrix.nnz for matrix in matrices[:-1]])
    indptr = np.concatenate([[0]] + [matrix.indptr[1:] + offset for matrix, offset in zip(matrices, offsets)])
    return rows_csr(np.concatenate([matrix.data for matrix in matrices]),
                    np.concatenate([matrix.indices for matrix in matrices]), indptr, matrices[0].shape[1])


def row_block_matrix(block: RowBlock, columns: int) -> sp.csr_matrix:
    """The block's rows as a CSR matrix of `columns` columns."""
    data, indices, counts = block
    return rows_csr(data, indices, np.concatenate([[0], np.cumsum(counts)]), columns)


class AppendedRows:
    """A CSR matrix whose rows are only ever appended, in buffers with room to grow: each
    append writes past the rows before it, and `matrix` is the rows so far as views of the
    buffers. A copy (a kept state) shares the buffers with the original; the first append
    after a copy moves to buffers of its own, so a state's rows are never written again."""

    def __init__(self, columns: int):
        self.columns = columns
        self._data, self._indices = np.zeros(0), np.zeros(0, dtype=np.int32)
        self._indptr = np.zeros(1, dtype=np.int32)
        self._rows, self._owned = 0, True
        self.matrix = rows_csr(self._data, self._indices, self._indptr, columns)

    def __copy__(self) -> AppendedRows:
        other = object.__new__(AppendedRows)
        other.__dict__.update(self.__dict__)
        other._owned = False  # its next append must not write into buffers the original fills
        return other

    def append(self, block: RowBlock) -> None:
        data, indices, counts = block
        nnz, rows = int(self._indptr[self._rows]), self._rows
        new_nnz, new_rows = nnz + len(data), rows + len(counts)
        if not self._owned or new_nnz > len(self._data) or new_rows + 1 > len(self._indptr):
            self._data = _grown(self._data, nnz, new_nnz)
            self._indices = _grown(self._indices, nnz, new_nnz)
            self._indptr = _grown(self._indptr, rows + 1, new_rows + 1)
            self._owned = True
        self._data[nnz:new_nnz] = data
        self._indices[nnz:new_nnz] = indices
        self._indptr[rows + 1:new_rows + 1] = nnz + np.cumsum(counts)
        self._rows = new_rows
        self.matrix = rows_csr(self._data[:new_nnz], self._indices[:new_nnz], self._indptr[:new_rows + 1],
                               self.columns)


def _grown(buffer: np.ndarray, kept: int, needed: int) -> np.ndarray:
    """A new buffer of at least `needed` entries (twice the old size, for the appends to come)
    holding the first `kept` entries of `buffer`."""
    grown = np.empty(max(needed, 2 * len(buffer), 16), dtype=buffer.dtype)
    grown[:kept] = buffer[:kept]
    return grown


class GrowingRows:
    """Shape-function rows N(X_q) T of points that are only ever appended (the track's and
    its constraint quadrature's), with their interleaved form E (`interleaved`), each in
    AppendedRows; E^T is formed once per change, when first asked for (and not kept in a
    copy: a kept state's)."""

    def __init__(self, columns: int, interleaved: bool = False):
        self._matrix = AppendedRows(columns)  # N_q T, (Q, n_free)
        self._expanded = AppendedRows(2 * columns) if interleaved else None  # E, (2Q, 2 n_free)
        self._expanded_t: sp.csr_matrix | None = None

    def __copy__(self) -> GrowingRows:
        other = object.__new__(GrowingRows)
        other._matrix = copy.copy(self._matrix)
        other._expanded = None if self._expanded is None else copy.copy(self._expanded)
        other._expanded_t = None
        return other

    @property
    def matrix(self) -> sp.csr_matrix:
        return self._matrix.matrix

    @property
    def expanded(self) -> sp.csr_matrix | None:
        return None if self._expanded is None else self._expanded.matrix

    def __len__(self) -> int:
        return self.matrix.shape[0]

    def append(self, block: RowBlock) -> None:
        self._matrix.append(block)
        if self._expanded is not None:
            self._expanded.append(_interleaved(block))
            self._expanded_t = None

    @property
    def expanded_t(self) -> sp.csr_matrix:
        """E^T (2 n_free, 2Q), kept until the rows grow."""
        if self._expanded_t is None:
            self._expanded_t = self.expanded.T.tocsr()
        return self._expanded_t
