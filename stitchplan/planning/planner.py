"""Deformation-compensating needle-centre planning (thesis Algorithm 2, eq. 4.1-4.2).

Each time a needle point is added, the needle centre is moved with the displacement of the
desired exit point, O(t_{n+1}) = O(t_0) + u(X_exit), and the constrained equilibrium is solved
again with the moved needle; within the step this repeats until the centre and the exit
displacement agree to `tolerance`. The fixed-point iteration converges when the exit point
moves less than the centre that drags it (eq. 4.2, ||du(X_exit)|| < ||dO||); when it does
not, planning stops with a message naming the step instead of diverging silently.

The centres are also a path a robot follows: each step's centre is kept within move limits
(move_limits.MoveLimits: the centre's move per step and the change of that move, its second
difference) and the mismatch a limited step leaves is carried to the next steps, whose
aim still holds it. Late in a stitch, where eq. 4.2 fails and no centre move changes the
exit, the limits keep the centre from jumping between steps' best tries; the passes
(run_plan, their offsets in pass_offsets) then correct the exit through the early,
controllable steps.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from ..config import Planner, Scenario
from ..errors import NumericalFailure, PlanningFailure
from ..events import Event, EventKind
from ..needle.equilibrium import NeedleInsertion
from ..needle.geometry import leaning, length, scenario_needle
from ..needle.steering import CenterAim
from ..needle.insertion import run_insertion
from ..needle.prepared_tissue import PreparedTissue
from ..needle.results import InsertionResult
from .entry_lean import LeanSearch, lean_for_exit
from .move_limits import MoveLimits, broken_limits
from .pass_offsets import PassOffsets, PassPrefix
from .replay_models import aims_at_bites
from .trajectory import exported_center, exported_centers

log = logging.getLogger(__name__)


class ExitTracker:
    """Algorithm 2's centre within each step, and the start of each step's iterations (a
    CenterControl for run_insertion).

    Within a step the centre solves O = O(t_0) - c + u(X_exit; O) (Algorithm 2's update, c the pass's
    `offset`). The plain fixed-point iteration contracts by the factor ||du(X_exit)|| /
    ||dO|| of eq. 4.2, often 0.9 or more here, and costs an equilibrium solve per try; the
    centre is instead a third unknown of the step's equilibrium Newton solve
    (needle/steering.py: each iteration moves it by (I - B)^-1 m, B = du(X_exit)/dO from
    the same linearised equilibrium). If the exit point would move as much as the centre or
    more (eq. 4.2 fails), the centre is held where it is and the failure is recorded as an
    event (raised with `strict`). That happens when the needle is deep in the tissue: the
    material enclosed by the arc and the free edge then follows the needle almost rigidly
    and no centre move changes their relative position. With `smooth` every centre lies
    within MoveLimits of the centres before it (`limited_steps`: the steps a limit held back),
    braking toward the step before the undeformed circle's exit or, given `exit_steps` (the
    first pass's steps in the tissue), toward the last of those if earlier. With a `prefix`
    the steps before prefix.first_aimed keep the plan's first pass's centres.
    """

    def __init__(self, settings: Planner, offset: np.ndarray | None = None, smooth: bool = True,
                 prefix: PassPrefix | None = None, exit_steps: int | None = None):
        self.settings = settings
        self.offset = np.zeros(2) if offset is None else np.asarray(offset, dtype=float)
        self.smooth = smooth  # keep the centres within MoveLimits
        self.prefix = prefix
        self.exit_steps = exit_steps
        self.limits: MoveLimits | None = None
        self.centers: list[np.ndarray] = []  # O(t_n) of the steps so far, O(t_0) first
        self.limited_steps: list[int] = []  # steps whose centre a move limit held back
        self._aim: CenterAim | None = None

    def predict(self, center: np.ndarray, step: int) -> np.ndarray:
        """The step starts from the previous step's centre (the Newton solve moves it; an
        extrapolated start saves nothing there, tests/test_planner.py)."""
        if not self.centers:
            self.centers.append(np.asarray(center, dtype=float).copy())  # O(t_0)
        if self._taken_over(step):
            return self.prefix.center(step)
        return self._feasible(center, step)

    def aim(self, insertion: NeedleInsertion, step: int, rotation: float) -> CenterAim | None:
        if self.smooth and self.limits is None:
            self.limits = MoveLimits.for_needle(insertion.geometry, self.settings, self.exit_steps)
        if self._taken_over(step):
            self._aim = None  # the first pass's centre, held
            return None
        geometry, settings = insertion.geometry, self.settings
        self._aim = CenterAim(origin=geometry.center - self.offset, exit_point=geometry.desired_exit,
                              feasible=lambda center: self._feasible(center, step), tolerance=settings.tolerance,
                              max_updates=settings.max_iterations, max_move=geometry.insertion_step,
                              step=step, rotation=rotation)
        return self._aim

    def correct(self, insertion: NeedleInsertion, step: int, rotation: float) -> int:
        """Record the step's centre and what held it back; returns its centre moves."""
        aim = self._aim
        if aim is None:  # a step taken over from the first pass (PassPrefix.take_over counts its work)
            if step in self.prefix.limited_steps:
                self.limited_steps.append(step)
            self.centers.append(insertion.center.copy())
            return 0
        if aim.limited:
            self.limited_steps.append(step)
        if aim.held is not None:
            kind, reason = aim.held
            if self.settings.strict:
                raise PlanningFailure(f"planning failed: {reason}")
            message = f"planning: {reason}; the step keeps its centre"
            insertion.events.append(Event(kind, message, step, rotation))
            log.info(message)  # the user sees it once, as a `note:` from the event
        self.centers.append(insertion.center.copy())
        return aim.updates

    def _taken_over(self, step: int) -> bool:
        return self.prefix is not None and step < self.prefix.first_aimed

    def _feasible(self, center: np.ndarray, step: int) -> np.ndarray:
        if self.limits is None or not self.centers:
            return center
        return self.limits.project(center, self.centers, step)


@dataclass
class PlanResult:
    planned: InsertionResult
    unplanned: InsertionResult | None
    passes: list[dict]
    shooting: PassOffsets | None = None  # where the passes ended, to continue from
    verification: object | None = None  # planning.verification.Verification, when verified
    estimate: object | None = None  # planning.verification.ExitEstimate of the planned run
    lean: LeanSearch | None = None  # the needle's lean at entry, when the planner chose it
    stopped: str | None = None  # why the passes stopped short of their aim (None: they met it)

    @property
    def center_trajectory(self) -> np.ndarray:
        """O(t_n) for n = 0 .. N (row 0: the entry centre)."""
        centers = [self.planned.geometry.center] + [s.center for s in self.planned.steps]
        return np.asarray(centers)

    @property
    def exported_centers(self) -> np.ndarray:
        """The centre columns of trajectory.csv, as written: O(t_0) .. O(t_N) and the exit
        step's row, which keeps O(t_N) (trajectory.py)."""
        return exported_centers(self.planned)


SOLVER_COUNTS = ("factorizations", "linear_solves", "solved_columns", "minres_iterations", "minres_fallbacks",
                 "tangent_products")  # a run's solver_counts that add up over runs


def planning_work(result: PlanResult) -> dict:
    """What every planner pass of every round solved, the passes not exported included: the
    total Newton iterations and equilibrium solves, and the solver counts of the exported
    run (its backend, tolerances) with their counts summed over the passes."""
    counts = {key: sum(record["solver"][key] for record in result.passes) for key in SOLVER_COUNTS}
    return {"newton_iterations": int(sum(record["newton_iterations"] for record in result.passes)),
            "equilibrium_solves": int(sum(record["equilibrium_solves"] for record in result.passes)),
            "minres_iterations": int(counts["minres_iterations"]),
            "solver": {**result.planned.solver_counts, **counts}}


def final_mismatch(result: InsertionResult) -> np.ndarray:
    """O(t0) + u(X_exit) - O at the last step: what Algorithm 2 drives to zero."""
    last = result.steps[-1]
    return result.geometry.center + last.exit_displacement - last.center


def run_plan(scenario: Scenario, compare: bool = True, on_step=None, aim: np.ndarray | None = None,
             tolerance: float | None = None, shooting: PassOffsets | None = None, smooth: bool = True,
             tissue: PreparedTissue | None = None, bite_aim: float = 0.0, stream=None, retarget=None,
             **options) -> PlanResult:
    """Planned insertion with the scenario's planner settings, and (compare=True, after the
    passes) the unplanned one of the same scene; `options` go to run_insertion. The planned
    run's wall time and timings are every pass's, the model's building included.

    Algorithm 2 controls the exit only while the exit point does not follow the needle
    rigidly (eq. 4.2). Late in a stitch the material enclosed by the arc and the free edge
    follows the needle, and the loads can still shift the exit relative to the centre by a
    drift that no centre move undoes then. The planner therefore shoots over whole passes:
    pass k aims the centre at O(t0) + u(X_exit) - c_k (PassOffsets), so the controllable
    steps before the drift pre-compensate it. The first pass (c_1 = 0) runs every step;
    the later ones keep its centres up to a few steps before its late limited steps
    (PassPrefix: its equilibria taken over, not solved again) and apply c_k from there;
    with the symmetric target (below), whose aim follows both bites, every pass runs every
    step. The passes aim the exit error vector
    at `aim` (default zero; planning.verification aims it by a refined model's offset) and
    stop when they are within `tolerance` of it (default exit_tolerance) or after
    max_passes; the best pass is returned. With planner.target `symmetric` on a stitch
    across a wound the aim is, after each pass, the exit error that would make both bites
    equal (needle.wound_crossings.stitch_bites), so the passes trade exit error for symmetry, or that
    would make their difference `bite_aim` mm (planning.verification aims it by a refined
    model's offset). `shooting` continues from an earlier plan's
    passes; `smooth` keeps the centre path within MoveLimits. The runs share one model
    (`tissue`, made here when not given). Every step a pass solves starts from the step
    before (not from the pass before, run_insertion `start_from`): where the move limits hold the
    centre, the step's centre settles within the planner tolerance at a point that depends
    on where the Newton solve started, and a pass started from the one before would make the
    exit error of a pass depend on that pass, not on its offset alone, which the secant
    over the passes cannot take (the thesis's table 5.1 100 x 100 block then missed the exit
    tolerance after four passes: benchmarks/results/thesis_table.md in the git history).
    `stream` (planning/replays.py) is handed each pass's centres as they become final, so a
    replay of the trajectory can run alongside. `retarget(first pass)` is asked after the
    first pass for (aim, tolerance) to go on with instead, or None to keep them
    (planning.verification's predicted aim).
    """
    settings = scenario.planner
    tissue = tissue or PreparedTissue(scenario)  # built by the first run
    aim = np.zeros(2) if aim is None else np.asarray(aim, dtype=float)
    target = settings.exit_tolerance if tolerance is None else tolerance
    passes = _PlanPasses(scenario, tissue, shooting or PassOffsets(), aim, target, smooth, on_step, stream, options)
    start = time.perf_counter()
    lean = passes.choose_lean() if settings.aim_entry_tilt else None
    if passes.offsets.last is not None:  # continuing with another aim: re-aim from the last pass
        passes.offsets.advance(passes.aim)
    best = passes.shoot(bite_aim, retarget)
    best.wall_seconds, best.timings = time.perf_counter() - start, passes.timings
    _note_rough_path(best, passes.best_limits())
    if settings.target == "symmetric" and not passes.symmetric:
        best.events.append(Event(EventKind.TARGET_NOT_APPLICABLE, (
            "planner.target: symmetric aims at equal bites on a stitch across a wound, and this needle's "
            "undeformed circle crosses no wound or hole: the plan aims at the desired exit"
            + (" (the gap it crosses lies beyond the tissue's far side: no tissue across it to stitch)"
               if scenario_needle(scenario).gaps else ""))))
    # after the passes, so that the planned run's wall time counts building the model it runs on
    # whether or not the comparison runs (and a helper replaying the passes has their centres sooner);
    # the comparison's needle is the scenario's as given, not leaned
    unplanned = run_insertion(scenario, on_step=on_step, tissue=tissue, **options) if compare else None
    return PlanResult(best, unplanned, passes.records, shooting=passes.offsets, lean=lean,
                      stopped=passes.stopped)


class _PlanPasses:
    """run_plan's passes of Algorithm 2: the scene and model they run on, the aim of the exit
    error they stop within `target` of, the secant over their offsets c_k (Algorithm 2's
    update, PassOffsets), their records (planner_passes) and timings, and the best pass so far."""

    def __init__(self, scenario: Scenario, tissue: PreparedTissue, offsets: PassOffsets, aim: np.ndarray,
                 target: float, smooth: bool, on_step, stream, options: dict):
        self.scenario = scenario  # leaned by choose_lean when the planner chooses the lean
        self.settings = scenario.planner
        self.symmetric = aims_at_bites(scenario)  # each pass aims the exit at equal bites
        self.tissue, self.offsets, self.aim, self.target = tissue, offsets, aim, target
        self.smooth, self.on_step, self.stream, self.options = smooth, on_step, stream, options
        self.timings: dict[str, float] = {}  # every pass's, summed as its wall time is
        self.records: list[dict] = []
        self.best: InsertionResult | None = None
        self.best_miss = np.inf
        # the best pass's offset, prefix and the move limits it kept (None: not smooth)
        self.best_pass: tuple[np.ndarray, PassPrefix | None, MoveLimits | None] | None = None
        self.ready: tuple[InsertionResult, list[int]] | None = None  # the lean search's run at its lean
        self.stopped: str | None = None  # why the passes stopped short of their aim (None: they met it)
        self.follows: np.ndarray | None = None  # the last pass's aim at equal bites (symmetric target)

    def run(self, leaned: Scenario, tracker: ExitTracker, prefix: PassPrefix | None = None) -> InsertionResult:
        """One pass of Algorithm 2 on the shared model (each step's centre solving Algorithm 2's update with
        the tracker's offset), its centres handed to `stream`."""
        run = run_insertion(leaned, control=tracker, on_step=_streamed(self.on_step, self.stream, leaned),
                            tissue=self.tissue, start_from=prefix.start() if prefix else None, **self.options)
        add_timings(self.timings, run.timings)
        return run

    def first_pass(self, leaned: Scenario) -> tuple[InsertionResult, list[int]]:
        """lean_for_exit's first pass (offset zero) and the steps a move limit held back in it."""
        tracker = ExitTracker(self.settings, smooth=self.smooth)
        return self.run(leaned, tracker), tracker.limited_steps

    def choose_lean(self) -> LeanSearch:
        """The needle's lean at entry (planner.aim_entry_tilt, entry_lean.lean_for_exit); the
        passes then run leaning so, the search's run there their first pass."""
        offsets = self.offsets
        known = offsets.prefix.reference if offsets.prefix is not None else None
        lean = lean_for_exit(self.scenario, self.aim, self.target, self.first_pass, known,
                             offsets.tilt)
        log.info("planning: the needle leans %.4g rad (%.3g deg) from the orthogonal entry, its first pass %.4g mm "
                 "from the aim (%d leans tried; %s)", lean.tilt, math.degrees(lean.tilt),
                 length(lean.run.exit_error_vector_mm - self.aim), len(lean.tries), lean.reason)
        if lean.tilt != offsets.tilt:  # passes about another lean: their offsets start afresh
            self.offsets, self.ready = PassOffsets(lean.tilt), (lean.run, lean.limited_steps)
        self.scenario = leaning(self.scenario, lean.tilt)
        return lean

    def shoot(self, bite_aim: float, retarget) -> InsertionResult:
        """Passes, each offset by the secant on the one before, until one exits within
        `target` of the aim or planner.max_passes have run; the best of them."""
        for number in range(1, self.settings.max_passes + 1):
            # a symmetric target's aim follows the bites, the entry side's included: every step
            offsets = self.offsets
            prefix = offsets.prefix.for_offset(offsets.offset) if offsets.prefix and not self.symmetric else None
            # brake toward where the first pass's tip left, when it left before the undeformed circle
            exit_steps = len(offsets.prefix.reference.steps) if offsets.prefix is not None else None
            tracker = ExitTracker(self.settings, offsets.offset, smooth=self.smooth, prefix=prefix,
                                  exit_steps=exit_steps)
            try:
                planned = self._next_pass(tracker, prefix)
            except NumericalFailure as failure:
                if self.best is None or isinstance(failure, PlanningFailure):  # no pass to export, or --strict
                    raise
                self._note_failed(number, failure)
                self.stopped = f"planner pass {number} failed (its note says where)"
                break
            error, miss = self._record(number, planned, tracker, prefix, bite_aim)
            retargeted = retarget(planned) if retarget is not None and number == 1 else None
            if retargeted is not None:
                self.aim, self.target = np.asarray(retargeted[0], dtype=float), retargeted[1]
                miss = float(np.linalg.norm(error - self.aim))
            if miss < self.best_miss:
                self.best, self.best_miss = planned, miss
                self.best_pass = (offsets.offset.copy(), prefix, tracker.limits)
            offsets.record(error, self.follows)
            if miss <= self.target:
                self.stopped = None
                break
            searching = offsets.searching
            offsets.advance(self.aim)
            self.stopped = why_short(self.records[-number:], offsets, self.settings.max_passes)
            if offsets.searching and not searching:
                log.info("planning pass %d: the exit moved along with the offset rather than against it (the move "
                         "limits hold the centre back): the next passes search between the offsets run", number)
            if offsets.searching and offsets.closest_tried() < self.target:
                log.info("planning: the passes settled within %.3g mm of an offset already run; the best of "
                         "them stands", self.target)
                break
        if self.smooth:
            self._brake_for_exit(self.records[-1]["pass"] + 1)
        return self.best

    def best_limits(self) -> MoveLimits:
        """The move limits the best pass kept (the scenario's, braking toward the undeformed
        circle's exit, without `smooth`)."""
        return self.best_pass[2] or MoveLimits.for_needle(self.best.geometry, self.settings)

    def _brake_for_exit(self, number: int) -> None:
        """The best pass run again with its offset, braking toward the step its tip left
        after, when that tip left two steps or more before the step the centre braked toward
        (a first pass, braking toward the undeformed circle's exit, or a later one leaving
        before the first): its centre stopped at the exit row from a speed the move limits
        do not allow. The rerun is the plan's when its path keeps them (the centre braking
        sooner, its exit a little further off); it is not one of the secant's passes."""
        best, limits = self.best, self.best_limits()
        if len(best.steps) > limits.last_step - 2 or not broken_limits(exported_centers(best), limits):
            return
        offset, prefix, _ = self.best_pass
        tracker = ExitTracker(self.settings, offset, smooth=True, prefix=prefix, exit_steps=len(best.steps))
        try:
            braked = self.run(self.scenario, tracker, prefix)
        except NumericalFailure as failure:
            log.info("planning pass %d (the best pass braking toward step %d) failed: %s", number, len(best.steps),
                     failure)
            return
        miss = self._add_record(number, braked, tracker, prefix, offset)
        if broken_limits(exported_centers(braked), tracker.limits):
            return
        log.info("planning pass %d: the best pass braking toward step %d, where its tip left, keeps the move limits "
                 "(%.4g mm from the aim, %.4g mm before)", number, len(best.steps), miss, self.best_miss)
        self.best, self.best_miss = braked, miss
        self.best_pass = (offset, prefix, tracker.limits)

    def _next_pass(self, tracker: ExitTracker, prefix: PassPrefix | None) -> InsertionResult:
        if self.ready is not None:  # the lean search ran this pass already, as a first pass
            (planned, tracker.limited_steps), self.ready = self.ready, None
            tracker.limits = MoveLimits.for_needle(planned.geometry, self.settings) if self.smooth else None
            return planned
        return self.run(self.scenario, tracker, prefix)

    def _note_failed(self, number: int, failure: NumericalFailure) -> None:
        """A later pass moved the centre where the model fails: the best pass so far stands
        (planner_passes lists the passes that ran to the exit)."""
        offset = self.offsets.offset
        message = (f"planner pass {number} (offset ({offset[0]:.4g}, {offset[1]:.4g}) mm) "
                   f"failed: {failure}; the best of the {number - 1} pass{'es' if number > 2 else ''} "
                   "before it is exported")
        self.best.events.append(Event(EventKind.PASS_FAILED, message))
        log.info(message)

    def _record(self, number: int, planned: InsertionResult, tracker: ExitTracker, prefix: PassPrefix | None,
                bite_aim: float) -> tuple[np.ndarray, float]:
        """A pass of the secant: the first kept as the later passes' prefix, (symmetric) the
        aim moved to its bites, and its record (_add_record); returns its exit error vector
        and its distance from the aim."""
        offset = self.offsets.offset
        if prefix is None and not offset.any():  # the plan's first pass: later passes take over its early steps
            self.offsets.prefix = PassPrefix.of(planned, tracker.limited_steps, self.settings)
        self.follows = None
        if self.symmetric and planned.bites is not None:
            self.aim = symmetric_aim(planned, bite_aim)
            self.follows = symmetric_aim(planned)  # the secant's part of the aim (PassOffsets)
        elif self.symmetric:  # this pass's tip passed the wound by: no bites to aim, its exit is judged
            log.info("planning pass %d: the tip crossed no wound (no bites); the pass keeps its exit aim", number)
        return planned.exit_error_vector_mm, self._add_record(number, planned, tracker, prefix, offset)

    def _add_record(self, number: int, planned: InsertionResult, tracker: ExitTracker, prefix: PassPrefix | None,
                    offset: np.ndarray) -> float:
        """The pass's record in planner_passes (its own work, before the prefix's is counted
        in), its final centres handed to `stream`; returns its distance from the aim."""
        own_iterations = sum(step.newton_iterations for step in planned.steps)  # before take_over
        own_solves = sum(step.equilibrium_solves for step in planned.steps)
        if prefix is not None:
            prefix.take_over(planned)
        if self.stream is not None:
            self.stream.end(exported_centers(planned))
        error = planned.exit_error_vector_mm
        miss = float(np.linalg.norm(error - self.aim))
        self.records.append({"pass": number, "offset_mm": offset.copy(), "exit_error_mm": planned.exit_error_mm,
                             "exit_error_vector_mm": error, "aim_mm": self.aim.copy(),
                             "final_mismatch_mm": final_mismatch(planned), "limited_steps": tracker.limited_steps,
                             "first_aimed_step": prefix.first_aimed if prefix else 1,
                             "braking_step": tracker.limits.last_step if tracker.limits else None,  # smooth
                             "newton_iterations": own_iterations, "equilibrium_solves": own_solves,
                             "solver": {key: planned.solver_counts[key] for key in SOLVER_COUNTS},
                             "wall_seconds": planned.wall_seconds})
        log.info("planning pass %d: offset (%.4g, %.4g) mm, exit error %.4g mm (%.4g mm from the aim)", number,
                 *offset, planned.exit_error_mm, miss)
        return miss


def why_short(records: list[dict], offsets: PassOffsets, max_passes: int) -> str:
    """What passes none of which came within the target of its aim did (their planner_passes
    `records`, `offsets` after them), for the target-missed note of a plan that misses its
    target: held back by the move limits (the offsets searching between those run), still
    closing in when max_passes ran out, or not converging (a pass missing by more than the
    one before it)."""
    misses = [float(np.linalg.norm(r["exit_error_vector_mm"] - r["aim_mm"])) for r in records]
    listed = f"they missed their aim by {', '.join(f'{miss:.3g}' for miss in misses)} mm"
    if offsets.searching:
        return ("the move limits held the centre back: a larger offset moved the exit away from the aim and the "
                f"passes searched between the offsets run ({listed}; planner.center_step_limit, "
                "center_second_difference_limit, or the steps where eq. 4.2 fails: see planner_passes)")
    if all(later < earlier for earlier, later in pairwise(misses)):
        return f"planner.max_passes ({max_passes}) ran out with the passes still closing in ({listed})"
    sides = [np.sign(offsets.direction @ (r["exit_error_vector_mm"] - r["aim_mm"])) for r in records]
    swung = len(sides) > 2 and all(a * b < 0 for a, b in pairwise(sides))
    return (f"the passes did not converge: {listed}{', overshooting it from side to side' if swung else ''} "
            "(see planner_passes)")


def add_timings(total: dict[str, float], more: dict[str, float]) -> None:
    """Add a run's timings_seconds split (discretization, assembly, solve, tip tracking) to `total`."""
    for key, seconds in more.items():
        total[key] = total.get(key, 0.0) + seconds


def _note_rough_path(result: InsertionResult, limits: MoveLimits) -> None:
    """An event on a pass whose exported centre path breaks the move limits (a robot told to
    follow it would be told too late): the planner keeps them step by step, braking toward the
    step before the undeformed circle's exit (in the passes after the first, toward the first
    pass's last step in the tissue if earlier), so a tip that leaves two steps or more earlier
    stops the centre at the exit row from a speed the braking had not yet taken off, where the
    best pass run again braking toward its exit (_PlanPasses._brake_for_exit) failed or broke
    them too."""
    broken = broken_limits(exported_centers(result), limits)
    if not broken:
        return
    steps = len(result.steps)
    why = (f": the tip left the tissue after step {steps}, before step {limits.last_step}, the step the centre "
           "brakes toward" if steps < limits.last_step else "")
    message = (f"plan: the exported centre path breaks the planner's move limits with {' and '.join(broken)}"
               f"{why}; slow the robot there or loosen planner.center_step_limit / "
               "center_second_difference_limit knowingly")
    result.events.append(Event(EventKind.PATH_LIMITS_EXCEEDED, message))
    log.info(message)


def _streamed(on_step, stream, scenario: Scenario):
    """on_step, and (with `stream`) the pass's start and each step's centre handed to it."""
    if stream is None:
        return on_step
    stream.begin(exported_center(scenario_needle(scenario).center))

    def step_done(record) -> None:
        stream.row(record.step, exported_center(record.center))
        if on_step is not None:
            on_step(record)

    return step_done


def symmetric_aim(result: InsertionResult, bite_aim: float = 0.0) -> np.ndarray:
    """The exit error vector that would make the bites' difference `bite_aim` (0: equal
    bites): the exit moved along the surface by the difference's excess, toward the wound
    edge when the exit side is the longer one."""
    away = result.achieved_exit_def - result.bites["exit_wound_edge_def"]
    excess = result.bites["difference_mm"] - bite_aim
    return result.exit_error_vector_mm - excess * away / np.linalg.norm(away)
