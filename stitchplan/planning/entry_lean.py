"""The planner's choice of the needle's lean at entry (planner.aim_entry_tilt).

Where the tissue carries the desired exit further than the move limits let the centre follow,
no pass offset reaches it; leaning the needle before it enters moves its whole path at no
move at all. The search finds the lean (within planner.max_entry_tilt) at which the planner's
first pass exits at its aim; planning.planner then runs its passes from that lean. The
planner hands in its first pass and its exit error (this module does not import the planner).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..config import Scenario
from ..errors import InputError, NumericalFailure, PlanningFailure
from ..needle.geometry import leaning, length, scenario_needle
from ..needle.results import InsertionResult


# first passes the search may run after its start; the lean step (rad) of the undeformed
# exit's move that starts its secant, and the least lean change a lean the geometry refuses
# may be halved to (at most LEAN_HALVINGS times) toward the lean run last
LEAN_RUNS = 6
LEAN_STEP = 1e-3
LEAN_HALVINGS = 30


@dataclass
class LeanSearch:
    """The lean chosen (rad from the orthogonal entry), the first pass run there and the
    steps a move limit held back in it, and every first pass the search ran: (lean, exit
    error vector)."""

    tilt: float
    run: InsertionResult
    limited_steps: list[int]
    tries: list[tuple[float, np.ndarray]]
    reason: str  # why the search stopped

    def after(self, earlier: LeanSearch) -> LeanSearch:
        """This search with an earlier round's tries before its own; its first, the pass the
        earlier round chose (kept, not run again), listed once."""
        tilt, error = self.tries[0] if self.tries else (None, None)
        again = any(t == tilt and np.array_equal(e, error) for t, e in earlier.tries)
        return replace(self, tries=earlier.tries + self.tries[1 if again else 0:])

    def as_record(self) -> dict:
        return {"entry_tilt_rad": self.tilt, "stopped": self.reason,
                "tries": [{"entry_tilt_rad": tilt, "exit_error_vector_mm": error} for tilt, error in self.tries]}


def lean_for_exit(scenario: Scenario, aim: np.ndarray, tolerance: float, first_pass,
                  known: InsertionResult | None, tilt: float | None) -> LeanSearch:
    """The lean of the needle at entry whose first planner pass (`first_pass(scenario)`:
    Algorithm 2 with the move limits, offset zero) exits at `aim` (its exit_error_vector_mm),
    within planner.max_entry_tilt.

    Where the tissue carries the desired exit further than the move limits let the centre
    follow (thesis figure 5.10: 12 mm of centre travel, 0.35 mm a step allowed), no pass
    offset reaches it; leaning the needle before it enters moves its whole path at no move
    at all. The exit error's component along the first miss, g(lean), is driven to zero by a
    secant started from the undeformed exit's move with the lean, from `tilt` (the passes'
    lean so far, whose first pass is `known`; else the scenario's needle.entry_tilt), at most
    LEAN_RUNS runs; the lean whose first pass came nearest is kept. A lean the needle's
    geometry refuses is halved back toward the lean run last; a pass that fails ends the
    search there (but a PlanningFailure, planner.strict, ends the plan)."""
    tilt = scenario.needle.entry_tilt if tilt is None else tilt
    # a known first pass is the passes' own (their prefix keeps its limited steps): kept, it
    # is not run again
    run, limited = (known, []) if known is not None else first_pass(leaning(scenario, tilt))
    best = LeanSearch(tilt, run, limited, [(tilt, run.exit_error_vector_mm)], "")
    miss = best.tries[0][1] - aim
    if length(miss) <= tolerance:
        best.reason = "the first pass met its aim"
        return best
    direction = miss / length(miss)
    slope = _undeformed_lean_slope(scenario, tilt, direction)
    best.reason = _lean_secant(scenario, aim, tolerance, first_pass, best, direction, slope)
    return best


def _undeformed_lean_slope(scenario: Scenario, tilt: float, direction: np.ndarray) -> float:
    """The secant's first slope dg/dlean: the undeformed exit's move along `direction` with
    the lean, one way or the other (a half circle exiting through its entry edge cannot lean
    deeper: it would need more arc); 0 where it leans neither way."""
    for change in (LEAN_STEP, -LEAN_STEP):
        moved = _leaned_exit(scenario, tilt + change)
        if moved is not None:
            return float(direction @ (moved - _leaned_exit(scenario, tilt))) / change
    return 0.0


def _lean_secant(scenario: Scenario, aim: np.ndarray, tolerance: float, first_pass,
                 best: LeanSearch, direction: np.ndarray, slope: float) -> str:
    """lean_for_exit's secant on g(lean) = direction . (e(lean) - aim) from `best`, its one
    try so far, for at most LEAN_RUNS first passes: each run is added to best.tries, and the
    lean whose first pass came nearest the aim is kept in `best`. Returns why it stopped."""
    best_miss = length(best.tries[0][1] - aim)
    points = [(best.tilt, float(direction @ (best.tries[0][1] - aim)))]  # (lean, g)
    for _ in range(LEAN_RUNS):
        if len(points) > 1 and points[-1][0] != points[-2][0]:
            slope = (points[-1][1] - points[-2][1]) / (points[-1][0] - points[-2][0])
        if slope == 0.0:
            return "the exit does not move with the lean"
        trial, stop = _next_lean(scenario, *points[-1], slope)
        if stop is not None:
            return stop
        try:
            run, limited = first_pass(leaning(scenario, trial))
        except PlanningFailure:
            raise
        except NumericalFailure as failure:
            return f"the pass at the lean {trial:.4g} rad failed: {failure}"
        error = run.exit_error_vector_mm
        best.tries.append((trial, error))
        points.append((trial, float(direction @ (error - aim))))
        if length(error - aim) < best_miss:
            best.tilt, best.run, best.limited_steps, best_miss = trial, run, limited, length(error - aim)
        if best_miss <= tolerance:
            return "a first pass met its aim"
    return f"{LEAN_RUNS} leans tried"


def _next_lean(scenario: Scenario, here: float, value: float, slope: float) -> tuple[float, str | None]:
    """The secant's step from the lean `here` (where g = `value`), within planner.max_entry_tilt,
    and why the search stops there instead (None: it goes on). A lean the needle's geometry
    refuses (no exit within its arc, other crossings) is halved toward `here`."""
    limit = scenario.planner.max_entry_tilt
    trial = float(np.clip(here - value / slope, -limit, limit))
    halved = 0
    while halved < LEAN_HALVINGS and _leaned_exit(scenario, trial) is None:
        trial, halved = 0.5 * (here + trial), halved + 1
    if halved and abs(trial - here) < LEAN_STEP:
        return trial, "the needle's geometry allows no lean further that way"
    if trial == here:
        return trial, f"at planner.max_entry_tilt ({limit:g} rad)"
    return trial, None


def _leaned_exit(scenario: Scenario, tilt: float) -> np.ndarray | None:
    """Where the undeformed circle of the needle leaning `tilt` rad leaves the tissue; None
    where the needle cannot lean so (needle.geometry.needle_geometry refuses it)."""
    try:
        geometry = scenario_needle(leaning(scenario, tilt))
    except InputError:
        return None
    return geometry.tip(geometry.exit_rotation)
