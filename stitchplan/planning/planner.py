"""Deformation-compensating needle-centre planning (thesis Algorithm 2, eq. 4.1-4.2).

Each time a needle point is added, the needle centre is moved with the displacement of the
desired exit point, O(t_{n+1}) = O(t_0) + u(X_exit), and the constrained equilibrium is solved
again with the moved needle; within the step this repeats until the centre and the exit
displacement agree to `tolerance`. The fixed-point iteration converges when the exit point
moves less than the centre that drags it (eq. 4.2, ||du(X_exit)|| < ||dO||); when it does
not, planning stops with a message naming the step instead of diverging silently.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np

from ..config import Planner, Scenario
from ..errors import PlanningFailure
from ..events import Event, EventKind
from ..needle.equilibrium import NeedleInsertion, Snapshot
from ..needle.insertion import run_insertion
from ..needle.results import InsertionResult

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CenterTry:
    """A centre tried within a step, and the equilibrium it gave."""

    mismatch: float  # |O(t0) - c + u(X_exit) - O|, mm
    state: Snapshot


class ExitTracker:
    """The centre update of Algorithm 2 within each step, and the start of each step's
    iterations (a CenterControl for run_insertion).

    Within a step the fixed point O = O(t_0) - c + u(X_exit; O) (eq. 4.1, c the pass's
    `offset`) is iterated until the centre moves less than `tolerance`. The plain iteration
    contracts by the factor ||du(X_exit)|| / ||dO|| of eq. 4.2, often 0.9 or more here, so
    the updates are Newton steps O <- O + (I - B)^-1 m, m = O(t_0) - c + u(X_exit) - O, with
    B = du(X_exit)/dO from the linearised constrained equilibrium
    (NeedleInsertion.center_sensitivity; B = 0 is the thesis's plain update). If the exit
    point moved as much as the centre or more (eq. 4.2 fails), the step keeps the best
    centre tried and the failure is recorded as an event (raised with `strict`). That
    happens when the needle is deep in the tissue: the material enclosed by the arc and the
    free edge then follows the needle almost rigidly and no centre move changes their
    relative position.
    """

    def __init__(self, settings: Planner, offset: np.ndarray | None = None, extrapolate: bool = True):
        self.settings = settings
        self.offset = np.zeros(2) if offset is None else np.asarray(offset, dtype=float)
        self.extrapolate = extrapolate
        self.centers: list[np.ndarray] = []  # O(t_n) of the steps so far

    def predict(self, center: np.ndarray, step: int) -> np.ndarray:
        """The centre extrapolated from the last two steps (with `extrapolate`), so the first
        mismatch of a step is the change of the centre's velocity, not of its position."""
        if not self.extrapolate or len(self.centers) < 2:
            return center
        return center + (self.centers[-1] - self.centers[-2])

    def correct(self, insertion: NeedleInsertion, step: int, rotation: float) -> int:
        """Iterate the step's centre (eq. 4.1); returns the iterations."""
        iterations = self._iterate(insertion, step, rotation)
        self.centers.append(insertion.center.copy())
        return iterations

    def _iterate(self, insertion: NeedleInsertion, step: int, rotation: float) -> int:
        settings = self.settings
        origin = insertion.geometry.center - self.offset  # aim: O - x_exit = O(t0) - X_exit - c
        target = insertion.geometry.desired_exit
        exit_displacement = insertion.displacement(target)[0]
        best = None
        for iteration in range(1, settings.max_iterations + 1):
            center = insertion.center
            mismatch = origin + exit_displacement - center
            best = self._better(best, mismatch, insertion)
            move = self._newton_move(insertion, mismatch, target)
            size = float(np.linalg.norm(move))
            log.debug("planning step %d, iteration %d: mismatch %.3g mm, centre move %.3g mm",
                     step, iteration, float(np.linalg.norm(mismatch)), size)
            if size <= settings.tolerance:
                return iteration - 1
            insertion.move_center(center + move)
            insertion.equilibrate(rotation, step)
            new_exit = insertion.displacement(target)[0]
            moved_exit = float(np.linalg.norm(new_exit - exit_displacement))
            exit_displacement = new_exit
            if moved_exit >= size:  # eq. 4.2 fails
                best = self._better(best, origin + exit_displacement - insertion.center, insertion)
                self._give_up(insertion, best, EventKind.PLANNER_EQ42_FAILED, step, rotation,
                              f"eq. 4.2 fails at step {step} (needle rotation {rotation:.3f} rad): moving the "
                              f"centre by {size:.3g} mm moved the desired exit point by {moved_exit:.3g} mm, "
                              "so iterating within the step cannot converge")
                return iteration
        best = self._better(best, origin + exit_displacement - insertion.center, insertion)
        self._give_up(insertion, best, EventKind.PLANNER_NOT_CONVERGED, step, rotation,
                      f"no convergence at step {step} (needle rotation {rotation:.3f} rad) in "
                      f"{settings.max_iterations} iterations, the centre still moves {size:.3g} mm")
        return settings.max_iterations

    @staticmethod
    def _better(best: CenterTry | None, mismatch: np.ndarray, insertion: NeedleInsertion) -> CenterTry:
        """The better of the best try so far and the insertion's current state."""
        norm = float(np.linalg.norm(mismatch))
        if best is None or norm < best.mismatch:
            return CenterTry(norm, insertion.snapshot())
        return best

    @staticmethod
    def _newton_move(insertion: NeedleInsertion, mismatch: np.ndarray, target: np.ndarray) -> np.ndarray:
        """(I - B)^-1 m, no longer than 10 |m| nor one insertion step: (I - B) is nearly
        singular when the exit follows the centre rigidly."""
        jacobian = insertion.center_sensitivity(target)
        try:
            move = np.linalg.solve(np.eye(2) - jacobian, mismatch)
        except np.linalg.LinAlgError:
            move = mismatch
        limit = min(10.0 * float(np.linalg.norm(mismatch)), insertion.geometry.insertion_step)
        if float(np.linalg.norm(move)) > limit:
            move = move * (limit / float(np.linalg.norm(move)))
        return move

    def _give_up(self, insertion: NeedleInsertion, best: CenterTry, kind: EventKind, step: int,
                 rotation: float, reason: str) -> None:
        """End the step's iterations on the best centre tried, recording why (strict: raise)."""
        if self.settings.strict:
            raise PlanningFailure(f"planning failed: {reason}")
        message = f"planning: {reason}; the step keeps the best centre tried (mismatch {best.mismatch:.3g} mm)"
        insertion.events.append(Event(kind, message, step, rotation))
        log.info(message)  # the user sees it once, as a `note:` from the event
        insertion.restore(best.state)


@dataclass
class PlanResult:
    planned: InsertionResult
    unplanned: InsertionResult | None
    passes: list[dict]

    @property
    def center_trajectory(self) -> np.ndarray:
        """O(t_n) for n = 0 .. N (row 0: the entry centre)."""
        centers = [self.planned.geometry.center] + [s.center for s in self.planned.steps]
        return np.asarray(centers)


def final_mismatch(result: InsertionResult) -> np.ndarray:
    """O(t0) + u(X_exit) - O at the last step: what Algorithm 2 drives to zero."""
    last = result.steps[-1]
    return result.geometry.center + last.exit_displacement - last.center


class PassOffsets:
    """The offsets c_k of the planning passes: c_1 = 0, c_{k+1} = c_k - S^-1 m_k, with m_k the
    final mismatch of pass k and S a secant (Broyden) estimate of dm/dc started at I."""

    def __init__(self):
        self.offset = np.zeros(2)
        self.sensitivity = np.eye(2)
        self._previous: tuple[np.ndarray, np.ndarray] | None = None  # (c, m) of the last pass

    def advance(self, mismatch: np.ndarray) -> None:
        if self._previous is not None:  # Broyden update of dm/dc from the last two passes
            change, response = self.offset - self._previous[0], mismatch - self._previous[1]
            if change @ change > 0:
                self.sensitivity = self.sensitivity + (np.outer(response - self.sensitivity @ change, change)
                                                       / (change @ change))
        self._previous = (self.offset.copy(), mismatch)
        try:
            self.offset = self.offset - np.linalg.solve(self.sensitivity, mismatch)
        except np.linalg.LinAlgError:
            self.offset = self.offset - mismatch


def run_plan(scenario: Scenario, compare: bool = True, on_step=None, **options) -> PlanResult:
    """Planned insertion with the scenario's planner settings, and (compare=True) the
    unplanned one of the same scene; `options` go to run_insertion.

    Algorithm 2 controls the exit only while the exit point does not follow the needle
    rigidly (eq. 4.2). Late in a stitch the material enclosed by the arc and the free edge
    follows the needle, and the loads can still shift the exit relative to the centre by a
    drift that no centre move undoes then. The planner therefore shoots over whole passes:
    pass k aims the centre at O(t0) + u(X_exit) - c_k (PassOffsets), so the early,
    controllable steps pre-compensate the late drift. Passes stop when the planned exit
    error is below exit_tolerance, or below 2 % of the unplanned error, or after max_passes;
    the best pass is returned.
    """
    settings = scenario.planner
    unplanned = run_insertion(scenario, on_step=on_step, **options) if compare else None
    target = settings.exit_tolerance
    if unplanned is not None:
        target = max(target, 0.02 * unplanned.exit_error_mm)
    start = time.perf_counter()
    offsets = PassOffsets()
    passes = []
    best = None
    for number in range(1, settings.max_passes + 1):
        planned = run_insertion(scenario, control=ExitTracker(settings, offsets.offset), on_step=on_step,
                                **options)
        mismatch = final_mismatch(planned)
        passes.append({"pass": number, "offset_mm": offsets.offset.copy(), "exit_error_mm": planned.exit_error_mm,
                       "final_mismatch_mm": mismatch, "wall_seconds": planned.wall_seconds})
        log.info("planning pass %d: offset (%.4g, %.4g) mm, exit error %.4g mm", number, *offsets.offset,
                 planned.exit_error_mm)
        if best is None or planned.exit_error_mm < best.exit_error_mm:
            best = planned
        if planned.exit_error_mm <= target:
            break
        offsets.advance(mismatch)
    best.wall_seconds = time.perf_counter() - start
    return PlanResult(best, unplanned, passes)
