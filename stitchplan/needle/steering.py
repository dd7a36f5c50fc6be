"""The needle centre as a third unknown of the equilibrium Newton (thesis eq. 4.1-4.2).

Algorithm 2 asks, within each needle step, for the centre O that satisfies

    m(d, O) = O(t_0) - c + u(X_exit; d) - O = 0                   (Algorithm 2's update)

with the tissue in equilibrium about O. Solved as a fixed point (move O, re-solve the
equilibrium, repeat) it costs a whole equilibrium solve per centre try. Here O joins the
Newton system of eq. 3.62 instead: each Newton iteration solves the saddle system for the
residual and for the two columns -d(r_u, g)/dO (one factor; the columns' K^-1 part comes from
the kept K^-1 E^T where the loads sit on the constraint quadrature, needle/equilibrium.py
_center_columns),

    [dd, dl] = [dd_0, dl_0] + [D, L] dO,

and the update linearised, m + N_exit (dd_0 + D dO) - dO = 0, gives the centre move

    dO = (I - B)^-1 (m + N_exit dd_0),    B = N_exit D = du(X_exit)/dO.

The move is limited to 10 |m| and one insertion step, and projected onto the move limits
of the centre path (`feasible`). The centre is settled when the tissue is in equilibrium
and the next move is below `tolerance`; it is held where it is, and the equilibrium
finished about it, after `max_updates` moves.

Eq. 4.2 (|du(X_exit)| < |dO|, i.e. ||B|| < 1) is the convergence condition of the thesis's
plain update O <- O(t_0) - c + u(X_exit). The Newton update needs only I - B to be
invertible, so it goes on where eq. 4.2 fails (late in a stitch, where the material
enclosed by the arc follows the needle almost rigidly and ||B|| reaches 1); ||B||_2 at
the step's last iteration, the largest |B m| / |m| over plain updates m, is kept
(`eq42_ratio`) so the summary can say where the plain update would have stalled.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..events import EventKind
from .geometry import IDENTITY, length


def spectral_norm(matrix: np.ndarray) -> float:
    """||B||_2 of a 2 x 2 matrix in closed form, the larger singular value:
    sigma^2 = (|B|_F^2 + sqrt(|B|_F^4 - 4 det(B)^2)) / 2 (np.linalg.norm(B, 2) runs an SVD)."""
    frobenius = float(np.sum(matrix * matrix))
    determinant = float(matrix[0, 0] * matrix[1, 1] - matrix[0, 1] * matrix[1, 0])
    return math.sqrt(0.5 * (frobenius + math.sqrt(max(frobenius**2 - 4.0 * determinant**2, 0.0))))


@dataclass
class CenterAim:
    """What the planner asks of the centre within one needle step, and what came of it."""

    origin: np.ndarray  # O(t_0) - c: the centre asked for is origin + u(X_exit)
    exit_point: np.ndarray  # X_exit, reference, (2,)
    feasible: Callable[[np.ndarray], np.ndarray]  # the admissible centre nearest a wanted one
    tolerance: float  # mm: settled when the next move is smaller
    max_updates: int  # centre moves per step before the centre is held
    max_move: float  # mm: one insertion step
    step: int
    rotation: float  # rad
    updates: int = 0  # centre moves made
    limited: bool = False  # the move limits held the settled centre back
    held: tuple[EventKind, str] | None = None  # why the centre stopped moving before settling
    eq42_ratio: float = float("nan")  # ||B||_2 at the last iteration (eq. 4.2 holds below 1)

    def restart(self) -> None:
        """Forget the moves made, for a solve that starts again."""
        self.updates, self.limited, self.held = 0, False, None
        self.eq42_ratio = float("nan")

    def update(self, free: np.ndarray, center: np.ndarray, solution: np.ndarray, exit_row: np.ndarray,
               balanced: bool) -> np.ndarray | None:
        """The centre move of one Newton iteration, or None: settled (when `balanced`) or
        held. `free` (2 n_free,: x, y interleaved) and `center` are the iterate, `solution`
        (2 n_free, 3) the saddle solve's displacement columns [dd_0, D], `exit_row`
        N(X_exit) T, dense (n_free,)."""
        def at_exit(column: np.ndarray) -> np.ndarray:
            return exit_row @ column.reshape(-1, 2)

        mismatch = self.origin + at_exit(free) - center
        predicted = mismatch + at_exit(solution[:, 0])  # after this iteration's equilibrium update
        jacobian = np.column_stack([at_exit(solution[:, 1]), at_exit(solution[:, 2])])  # B
        self.eq42_ratio = spectral_norm(jacobian)  # the plain update dO = m moves X_exit by B m
        try:
            wanted = np.linalg.solve(IDENTITY - jacobian, predicted)
        except np.linalg.LinAlgError:
            wanted = predicted
        limit = min(10.0 * length(predicted), self.max_move)
        if length(wanted) > limit:
            wanted = wanted * (limit / length(wanted))
        move = self.feasible(center + wanted) - center
        size = length(move)
        # held at the limit (as the step settles: the last iteration's verdict counts), the
        # mismatch carries to the next steps
        self.limited = size <= self.tolerance < length(wanted) - size
        if size <= self.tolerance:
            return None if balanced else move
        if self.updates >= self.max_updates:
            self.held = (EventKind.PLANNER_NOT_CONVERGED,
                         f"no convergence at step {self.step} (needle rotation {self.rotation:.3f} rad) in "
                         f"{self.max_updates} centre {'iteration' if self.max_updates == 1 else 'iterations'} "
                         f"(planner.max_iterations), the centre still moves {size:.3g} mm")
            return None
        self.updates += 1
        return move
