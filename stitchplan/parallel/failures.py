"""What ends a run and is recorded (RUN_FAILURES), and what ends the cluster's work (ClusterFailure)."""

from __future__ import annotations

import numpy as np

from ..errors import StitchplanError

# what a run may end with because of its input (recorded, never raised):
RUN_FAILURES = (
    # the project's own errors: a discretization the scenario checks refuse (InputError, e.g. a
    # quadratic basis with too small a dilation, or a replayed centre path that ends before the
    # tip exits) and numerical failures of an accepted one (SolverDivergence, InvertedMaterial,
    # SingularMomentMatrix, TipTrackingJump, InsertionFailure)
    StitchplanError,
    # dense linear algebra on a degenerate model: numpy's solves and factorizations
    np.linalg.LinAlgError,
    # SuperLU (scipy.sparse.linalg.splu) raises a bare RuntimeError on an exactly singular factor
    # (too few particles or quadrature points to pin the tissue down)
    RuntimeError,
    # a model too fine for the machine: the sweep records it and goes on with the coarser runs
    MemoryError,
)


class ClusterFailure(StitchplanError):
    """The Dask cluster lost tasks (a worker killed again and again, the scheduler gone)."""

    exit_code = 1
