"""What a needle insertion keeps per step for a later run to take over (run_insertion's
states): the saddle-point solver's E K^-1 and E K^-1 E^T and the coupling's growing track
rows (its constraint quadrature's and its loads') are views of a few shared buffers, not an
array of their own per step, and the coupling's W is kept sparse. Kept per step, they made
the memory grow with the cube of the steps: 1.4 GB after 305 steps of 0.01 rad on 99
particles, an out-of-memory kill at 0.0025 rad."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from stitchplan.config.scenario import parse_scenario
from stitchplan.needle.insertion import run_insertion

PHANTOM = {"model": "saint-venant-kirchhoff", "lame_lambda": 0.189151, "lame_mu": 0.147688}


def buffer_bytes(arrays) -> tuple[int, int]:
    """Bytes of the distinct buffers under `arrays`, and of the largest of them."""
    buffers = {}
    for array in arrays:
        base = array if array.base is None else array.base
        buffers[id(base)] = base.nbytes
    return sum(buffers.values()), max(buffers.values())


def test_the_states_of_a_long_insertion_share_their_buffers():
    raw = {"tissue": {"size": [40.0, 30.0], "thickness": 10.0, "clamped": ["right"], "material": PHANTOM},
           "discretization": {"spacing": 5.0},
           "needle": {"radius": 8.0, "entry": [0.0, 22.0], "turn": "cw", "step": 0.04, "friction": 0.0602,
                      "cutting_force": 0.7}}
    result = run_insertion(parse_scenario(raw))
    states = [state for state in result.states if state.solver is not None]
    assert len(states) > 60
    coupled = [state.solver[4] for state in states if state.solver[4] is not None and state.solver[4].size]
    total, largest = buffer_bytes(coupled)
    # doubling buffers: at most 1 + 1/4 + 1/16 + ... of the largest, whatever the steps
    assert total <= 1.5 * largest, (total, largest, len(coupled))
    # E K^-1 E^T, (2Q, 2Q), is kept while 2Q <= n only: the later states hold none, and the
    # largest buffer of it is at most (2n)^2
    unknowns = result.model.n_free * 2
    rows_kept = [state.solver[3] for state in states]
    assert [block is None for block in (state.solver[4] for state in states)] == [count > unknowns
                                                                                  for count in rows_kept]
    assert rows_kept[-1] > unknowns and len(coupled) > 10
    assert largest <= 8 * (2 * unknowns) ** 2
    # E K^-1, (2Q, n): doubling buffers too (at most 1 + 1/2 + 1/4 + ... of the largest)
    total, largest = buffer_bytes([state.solver[2] for state in states])
    assert total <= 2.0 * largest, (total, largest)
    # the coupling's W (Q, m): sparse in every state, at most two entries a row (dense, the
    # states' W grew with the cube of the steps)
    weights = [state.coupling["weights"] for state in states]
    assert all(sp.issparse(matrix) and matrix.nnz <= 2 * matrix.shape[0] for matrix in weights)
    assert weights[-1].shape[1] > 2 and weights[-1].nnz < weights[-1].shape[0] * weights[-1].shape[1] / 2
    rows = [state.coupling["_quadrature_rows"].matrix.data for state in states]
    total, largest = buffer_bytes(rows)
    assert total <= 2.5 * largest, (total, largest)
    # a state's rows are the rows its step had, unchanged by the steps after it
    counts = [state.coupling["_quadrature_rows"].matrix.shape[0] for state in states]
    assert counts == sorted(counts) and counts[0] < counts[-1]
    last = states[-1].coupling["_quadrature_rows"].matrix
    for state in states[::10]:
        matrix = state.coupling["_quadrature_rows"].matrix
        assert np.array_equal(matrix.toarray(), last[:matrix.shape[0]].toarray())
    # the load rows: the track's part shares those buffers; a state's own part holds only the
    # rows of its partly covered segment's points (one matrix of all the rows per state, new in
    # each, grew with the square of the steps: 1.52 GB -> 1.24 GB at 0.0025 rad on SH 1/2)
    loads = [state.coupling["loads"] for state in states]
    assert sum(len(load.row_parts) > 1 for load in loads) > len(loads) // 2  # the cutting zone ends inside a segment
    total, largest = buffer_bytes([load.row_parts[0].data for load in loads])
    assert total <= 2.5 * largest, (total, largest)
    assert max(part.shape[0] for load in loads for part in load.row_parts[1:]) <= 2
    for load in loads[::10]:
        assert np.array_equal(load.rows.toarray()[:load.row_parts[0].shape[0]], load.row_parts[0].toarray())


def test_a_kept_copy_and_its_original_append_without_writing_into_each_other():
    """A kept state's rows share the buffers with the coupling's until one of them appends:
    the copy's first append must move to buffers of its own, or it writes over the rows the
    original appended after the copy (and the other way round)."""
    import copy

    import scipy.sparse as sp

    from stitchplan.needle.constraint_rows import GrowingRows, row_block

    rng = np.random.default_rng(3)
    blocks = [sp.random(2, 6, density=0.5, format="csr", random_state=rng) for _ in range(4)]
    original = GrowingRows(6, interleaved=True)
    original.append(row_block(blocks[0], 0, 2))
    kept = copy.copy(original)
    original.append(row_block(blocks[1], 0, 2))
    kept.append(row_block(blocks[2], 0, 2))
    original.append(row_block(blocks[3], 0, 2))

    def interleaved(matrix: sp.csr_matrix) -> np.ndarray:  # row q -> rows (q, 0), (q, 1) on dofs (p, 0), (p, 1)
        return np.kron(matrix.toarray(), np.eye(2))

    for rows, own in ((original, [0, 1, 3]), (kept, [0, 2])):
        expected = sp.vstack([blocks[k] for k in own]).toarray()
        np.testing.assert_array_equal(rows.matrix.toarray(), expected)
        np.testing.assert_array_equal(rows.expanded.toarray(), interleaved(sp.csr_matrix(expected)))
