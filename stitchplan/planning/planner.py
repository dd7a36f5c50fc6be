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

from ..config import Scenario
from ..errors import PlanningFailure
from ..events import Event, EventKind
from ..needle.insertion import InsertionResult, NeedleInsertion, run_insertion

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PlannerSettings:
    tolerance: float = 1e-3  # mm: centre change that ends the iterations within a step
    max_iterations: int = 10
    strict: bool = False  # raise PlanningFailure when eq. 4.2 fails instead of recording it
    exit_tolerance: float = 0.005  # mm: planned exit error that ends the passes
    max_passes: int = 4
    exact_sensitivity: bool = True  # Newton with du(X_exit)/dO from the linearised equilibrium


def exit_tracking_update(settings: PlannerSettings, offset: np.ndarray | None = None):
    """The centre update of Algorithm 2 and its predictor, as callbacks for run_insertion.

    Within a step the fixed point O = O(t_0) + u(X_exit; O) (eq. 4.1) is iterated until the
    centre moves less than `tolerance`. The plain iteration contracts by the factor
    ||du(X_exit)|| / ||dO|| of eq. 4.2, often 0.9 or more here, so the updates are Newton
    steps O <- O + (I - B)^-1 m, m = O(t_0) + u(X_exit) - O, with B = du(X_exit)/dO from
    the linearised constrained equilibrium (NeedleInsertion.center_sensitivity; with
    exact_sensitivity off, a secant (Broyden) estimate; B = 0 is the thesis's plain update). If the exit point moved
    as much as the centre or more (eq. 4.2 fails), the step keeps its centre and the failure
    is recorded as an event (raised with `strict`). That happens when the needle is deep in
    the tissue: the material enclosed by the arc and the free edge then follows the needle
    almost rigidly and no centre move changes their relative position.
    """
    state = {"jacobian": np.zeros((2, 2)), "centers": []}
    shift = np.zeros(2) if offset is None else np.asarray(offset, dtype=float)

    def predict(center: np.ndarray) -> np.ndarray:
        """Start of the step's iterations: the centre extrapolated from the last two steps, so
        the first mismatch is the change of the centre's velocity, not of its position."""
        centers = state["centers"]
        if len(centers) < 2:
            return center
        return center + (centers[-1] - centers[-2])

    def update(insertion: NeedleInsertion, step: int, rotation: float, center: np.ndarray):
        new_center, iterations = iterate(insertion, step, rotation, center)
        state["centers"].append(np.array(new_center, dtype=float))
        return new_center, iterations

    def iterate(insertion: NeedleInsertion, step: int, rotation: float, center: np.ndarray):
        origin = insertion.geometry.center - shift  # target: O - x_exit = O(t0) - X_exit - offset
        target = insertion.geometry.desired_exit
        jacobian = state["jacobian"]
        exit_displacement = insertion.displacement(target)[0]
        best = None  # (|mismatch|, centre, tissue state) of the best centre tried in this step

        def keep_best():
            norm = float(np.linalg.norm(origin + exit_displacement - center))
            if best is None or norm < best[0]:
                return (norm, center.copy(), insertion.free.copy(), insertion.multipliers.copy())
            return best

        def restore_best():
            insertion.free, insertion.multipliers = best[2], best[3]
            insertion.center = best[1]
            return best[1]

        for iteration in range(1, settings.max_iterations + 1):
            best = keep_best()
            mismatch = origin + exit_displacement - center
            if settings.exact_sensitivity:
                jacobian = insertion.center_sensitivity(center, target)
            try:
                move = np.linalg.solve(np.eye(2) - jacobian, mismatch)
            except np.linalg.LinAlgError:
                move = mismatch
            # safeguard: (I - B) nearly singular when the exit follows the centre rigidly
            limit = min(10.0 * float(np.linalg.norm(mismatch)), insertion.geometry.insertion_step)
            if float(np.linalg.norm(move)) > limit:
                move = move * (limit / float(np.linalg.norm(move)))
            size = float(np.linalg.norm(move))
            if size <= settings.tolerance:
                state["jacobian"] = jacobian
                return center, iteration - 1
            new_center = center + move
            insertion.center = new_center
            insertion.equilibrate(new_center, rotation, step)
            new_exit = insertion.displacement(target)[0]
            moved_exit = float(np.linalg.norm(new_exit - exit_displacement))
            jacobian = jacobian + np.outer(new_exit - exit_displacement - jacobian @ move, move) / (move @ move)
            center, exit_displacement = new_center, new_exit
            if moved_exit >= size:  # eq. 4.2 fails
                best = keep_best()
                message = (f"planning: eq. 4.2 fails at step {step} (needle rotation {rotation:.3f} rad): "
                           f"moving the centre by {size:.3g} mm moved the desired exit point by "
                           f"{moved_exit:.3g} mm, so iterating within the step cannot converge; "
                           f"the step keeps the best centre tried (mismatch {best[0]:.3g} mm)")
                if settings.strict:
                    raise PlanningFailure(  # strict: nothing is kept, drop that clause
                        message.replace("planning: ", "planning failed: ", 1).split("; the step keeps")[0])
                insertion.events.append(Event(EventKind.PLANNER_EQ42_FAILED, message, step, rotation))
                log.warning(message)
                state["jacobian"] = np.zeros((2, 2))
                return restore_best(), iteration
        best = keep_best()
        message = (f"planning: no convergence at step {step} (needle rotation {rotation:.3f} rad) in "
                   f"{settings.max_iterations} iterations, the centre still moves {size:.3g} mm; "
                   f"the step keeps the best centre tried (mismatch {best[0]:.3g} mm)")
        if settings.strict:
            raise PlanningFailure(message.replace("planning: ", "planning failed: ", 1).split("; the step keeps")[0])
        insertion.events.append(Event(EventKind.PLANNER_NOT_CONVERGED, message, step, rotation))
        log.warning(message)
        state["jacobian"] = jacobian
        return restore_best(), settings.max_iterations

    return update, predict


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


def run_plan(scenario: Scenario, settings: PlannerSettings | None = None, compare: bool = True,
             on_step=None, **options) -> PlanResult:
    """Planned insertion, and (compare=True) the unplanned one of the same scene.

    Algorithm 2 controls the exit only while the exit point does not follow the needle
    rigidly (eq. 4.2). Late in a stitch the material enclosed by the arc and the free edge
    follows the needle, and the loads can still shift the exit relative to the centre by a
    drift that no centre move undoes then. The planner therefore shoots over whole passes:
    pass k aims the centre at O(t0) + u(X_exit) - c_k, with c_1 = 0 and c_{k+1} = c_k - S^-1 m_k,
    m_k the mismatch O(t0) + u(X_exit) - O left at the end of pass k and S a secant
    (Broyden) estimate of dm/dc started at the identity, so the early, controllable steps
    pre-compensate the late drift. Passes stop when the planned exit error
    is below exit_tolerance, or below 2 % of the unplanned error, or after max_passes; the
    best pass is returned.
    """
    if settings is None:
        settings = PlannerSettings(scenario.planner.tolerance, scenario.planner.max_iterations,
                                   scenario.planner.strict, scenario.planner.exit_tolerance,
                                   scenario.planner.max_passes)
    unplanned = run_insertion(scenario, on_step=on_step, **options) if compare else None
    target = settings.exit_tolerance
    if unplanned is not None:
        target = max(target, 0.02 * unplanned.exit_error_mm)
    start = time.perf_counter()
    offset = np.zeros(2)
    sensitivity = np.eye(2)  # secant estimate of d m / d c over the passes
    previous = None
    passes = []
    best = None
    for number in range(1, settings.max_passes + 1):
        update, predict = exit_tracking_update(settings, offset)
        planned = run_insertion(scenario, center_update=update, center_predictor=predict,
                                on_step=on_step, **options)
        mismatch = final_mismatch(planned)
        passes.append({"pass": number, "offset_mm": offset.copy(), "exit_error_mm": planned.exit_error_mm,
                       "final_mismatch_mm": mismatch, "wall_seconds": planned.wall_seconds})
        log.info("planning pass %d: exit error %.4g mm", number, planned.exit_error_mm)
        if best is None or planned.exit_error_mm < best.exit_error_mm:
            best = planned
        if planned.exit_error_mm <= target:
            break
        if previous is not None:  # Broyden update of d m / d c from the last two passes
            change, response = offset - previous[0], mismatch - previous[1]
            if change @ change > 0:
                sensitivity = sensitivity + np.outer(response - sensitivity @ change, change) / (change @ change)
        previous = (offset.copy(), mismatch)
        try:
            offset = offset - np.linalg.solve(sensitivity, mismatch)
        except np.linalg.LinAlgError:
            offset = offset - mismatch
    best.wall_seconds = time.perf_counter() - start
    return PlanResult(best, unplanned, passes)
