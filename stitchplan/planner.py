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
from dataclasses import dataclass

import numpy as np

from .config import Scenario
from .simulation import InsertionFailure, InsertionResult, NeedleInsertion, run_insertion

log = logging.getLogger(__name__)


class PlanningFailure(InsertionFailure):
    """The planner's convergence condition (eq. 4.2) fails."""


@dataclass(frozen=True)
class PlannerSettings:
    tolerance: float = 1e-4  # mm: centre change that ends the iterations within a step
    max_iterations: int = 30
    strict: bool = False  # raise PlanningFailure when eq. 4.2 fails instead of recording it


def exit_tracking_update(settings: PlannerSettings):
    """The centre update of Algorithm 2 as a callback for run_insertion.

    Within a step the fixed point O = O(t_0) + u(X_exit; O) (eq. 4.1) is iterated until the
    centre moves less than `tolerance`. The plain iteration contracts by the factor
    ||du(X_exit)|| / ||dO|| of eq. 4.2, often 0.9 or more here, so the updates are
    accelerated by a secant (Broyden) estimate B of du(X_exit)/dO: O <- O + (I - B)^-1 m,
    m = O(t_0) + u(X_exit) - O, with B = 0 the thesis's plain update. If the exit point moved
    as much as the centre or more (eq. 4.2 fails), the step keeps its centre and the failure
    is recorded as an event (raised with `strict`). That happens when the needle is deep in
    the tissue: the material enclosed by the arc and the free edge then follows the needle
    almost rigidly and no centre move changes their relative position.
    """
    state = {"jacobian": np.zeros((2, 2))}

    def update(insertion: NeedleInsertion, step: int, rotation: float, center: np.ndarray):
        origin = insertion.geometry.center
        target = insertion.geometry.desired_exit
        jacobian = state["jacobian"]
        exit_displacement = insertion.displacement(target)[0]
        for iteration in range(1, settings.max_iterations + 1):
            mismatch = origin + exit_displacement - center
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
                message = (f"planning: eq. 4.2 fails at step {step} (needle rotation {rotation:.3f} rad): "
                           f"moving the centre by {size:.3g} mm moved the desired exit point by "
                           f"{moved_exit:.3g} mm, so iterating within the step cannot converge; "
                           "the step keeps this centre")
                if settings.strict:
                    raise PlanningFailure(message.replace("planning: ", "planning failed: ", 1))
                insertion.events.append(message)
                log.warning(message)
                state["jacobian"] = np.zeros((2, 2))
                return center, iteration
        message = (f"planning: no convergence at step {step} (needle rotation {rotation:.3f} rad) in "
                   f"{settings.max_iterations} iterations, the centre still moves {size:.3g} mm; "
                   "the step keeps this centre")
        if settings.strict:
            raise PlanningFailure(message.replace("planning: ", "planning failed: ", 1))
        insertion.events.append(message)
        log.warning(message)
        state["jacobian"] = jacobian
        return center, settings.max_iterations

    return update


@dataclass
class PlanResult:
    planned: InsertionResult
    unplanned: InsertionResult | None

    @property
    def center_trajectory(self) -> np.ndarray:
        """O(t_n) for n = 0 .. N (row 0: the entry centre)."""
        centers = [self.planned.geometry.center] + [s.center for s in self.planned.steps]
        return np.asarray(centers)


def run_plan(scenario: Scenario, settings: PlannerSettings | None = None, compare: bool = True,
             on_step=None, **options) -> PlanResult:
    """Planned insertion, and (compare=True) the unplanned one of the same scene."""
    planned = run_insertion(scenario, center_update=exit_tracking_update(settings or PlannerSettings()),
                            on_step=on_step, **options)
    unplanned = run_insertion(scenario, **options) if compare else None
    return PlanResult(planned, unplanned)
