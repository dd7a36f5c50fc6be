"""Curved-needle insertion into the deformable tissue (thesis section 3.1.5, Algorithm 1).

Each step rotates the rigid needle by `step` about its centre: the tip's new material
point is found by tip tracking (eq. 3.66-3.70, needle/tip_tracking.py), appended to the
needle track Gamma_N, and the tissue brought to equilibrium under the needle's loads and
constraints (eq. 3.58-3.65, needle/equilibrium.py); a planner may then move the centre
(Algorithm 2, planning/planner.py). The run ends when the tip leaves the tissue.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from typing import NamedTuple, Protocol

import numpy as np

from ..config import Scenario
from ..errors import InputError, InsertionFailure
from ..events import EventKind
from ..tissue.shape_functions import SingularMomentAt
from .equilibrium import NeedleInsertion
from .geometry import BoundaryLoops, entry_lean
from .prepared_tissue import PreparedTissue
from .results import InsertionResult, NeedleStep, Snapshot, StepsDone
from .steering import CenterAim
from .tip_tracking import entry_ahead, locate_exit, track_step
from .wound_crossings import (Crossing, ahead_after, crossed_back, crossing_made, crossings_record, left_for_good,
                              left_into_uncrossed_gap, log_crossing, point_text, reentry, stayed_on_near_side,
                              stitch_bites)

log = logging.getLogger(__name__)


class CenterControl(Protocol):
    """Moves the needle centre during an insertion (the planner of Algorithm 2)."""

    def predict(self, center: np.ndarray, step: int) -> np.ndarray:
        """The centre step `step` starts its equilibrium from, once the tip has advanced
        about the previous step's centre."""

    def aim(self, insertion: NeedleInsertion, step: int, rotation: float) -> CenterAim | None:
        """What the step's equilibrium solve asks of the centre (needle/steering.py), or None
        for a centre that stays where `predict` put it."""

    def correct(self, insertion: NeedleInsertion, step: int, rotation: float) -> int:
        """Act on the step's equilibrium (the aim's outcome); returns the centre iterations."""


class InsertionStopped(Exception):
    """Raised by a centre control to end a run before the tip exits (a replay of a planner
    pass that has been dropped, planning/replays.py). run_insertion sets `done`, the steps
    completed, for a later run along the same first centres to take over."""

    done: StepsDone | None = None


class FixedCenter:
    """The unplanned needle: the centre stays where it entered."""

    def predict(self, center: np.ndarray, step: int) -> np.ndarray:
        return center

    def aim(self, insertion: NeedleInsertion, step: int, rotation: float) -> CenterAim | None:
        return None

    def correct(self, insertion: NeedleInsertion, step: int, rotation: float) -> int:
        return 0


class CenterReplay(FixedCenter):
    """Prescribed centres (n, 2), row n for step n (row 0 the entry centre)."""

    def __init__(self, path: np.ndarray):
        self.path = np.asarray(path, dtype=float)

    def predict(self, center: np.ndarray, step: int) -> np.ndarray:
        if step >= len(self.path):
            raise InputError(f"centre path: rows: got {len(self.path)}, expected one per step until the tip exits "
                             f"(it is still in the tissue at step {step})")
        return self.path[step]


def run_insertion(
    scenario: Scenario,
    control: CenterControl | None = None,
    center_path: np.ndarray | None = None,
    linear_solver: str | None = None,
    tip_tracking: str | None = None,
    condition_numbers: bool = False,
    on_step: Callable[[NeedleStep], None] | None = None,
    tissue: PreparedTissue | None = None,
    start_from: InsertionResult | StepsDone | None = None,
    take_over_only: bool = False,
    on_ramp: Callable[[int, float, float], None] | None = None,
) -> InsertionResult:
    """Insert the needle step by step until its tip leaves the tissue.

    `control` moves the centre during the run (the planner); `center_path` (n, 2) replays
    prescribed centres instead, row n for step n (row 0 is the entry centre; on the circle of
    the needle's radius about the entry it leans the needle there: geometry.entry_lean). With
    `condition_numbers` each step records the (dense) condition numbers of its saddle system.
    `tissue`: the scenario's PreparedTissue when another run on the same model made it.
    `start_from`: an earlier run on the same model along a nearby centre path (the
    verification's first replay, for its second): each step's Newton solve starts from this
    run's previous state plus that run's change over the step (NeedleInsertion.equilibrate
    `guess`). Not for planner passes (planning.planner.run_plan says why), except over the
    steps a later pass takes over from the first (planning.pass_offsets.PassPrefix). While this
    run has taken the earlier run's centres (and the needle crosses no wound), its tip points
    are the earlier run's (they would be tracked from the same state about the same centre),
    and so are its equilibria where its centre control holds the centre where the earlier
    run's was: the state and needle coupling after such a step are taken over
    (NeedleInsertion.take_over), not solved again from the earlier state. With
    `take_over_only` the earlier run gives only those steps and no Newton starts: a run made
    from no earlier run along centres that agree with `start_from`'s (itself made from none)
    up to some step, which then ends as if made alone, to the last bit; `start_from` may then
    be the steps a stopped run had done (InsertionStopped). `on_ramp` is called with (step,
    load carried, next increment) as a step's ramp cuts or carries its load
    (NeedleInsertion.equilibrate).
    """
    if scenario.discretization.accuracy is not None:
        raise InputError("discretization.accuracy: got an accuracy target, expected a discretization "
                         "chosen before the run (stitchplan.study.auto.resolve_accuracy)")
    wall_start = time.perf_counter()
    insertion, control = _needle_at_entry(scenario, control, center_path, linear_solver, tip_tracking, tissue)
    insertion.on_ramp = on_ramp
    run = _Run(insertion, control, condition_numbers, on_step, start_from, take_over_only, wall_start)
    geometry = insertion.geometry
    limit = math.ceil(2.0 * math.pi / geometry.step) + 2
    for step in range(1, limit + 1):  # Algorithm 1: rotate the needle by one step
        rotation = step * geometry.step
        started = time.perf_counter()  # the step's wall time counts tracking its tip
        try:
            tip = run.step_in_gap(step, rotation, started) if run.in_gap else run.track_in_tissue(step, rotation)
            if tip is None:  # the tip still in a wound's gap: the step is solved and recorded
                continue
            if insertion.domain.outside_distance(tip.point) > 0.0:
                if (result := run.tip_outside(step, rotation, tip, started)) is not None:
                    return result  # through the final exit
            else:
                run.solve(step, rotation, tip.point, tip.method, started, tip.fraction, tip.taken)
        except SingularMomentAt as error:  # shape functions asked for where too few particles see (the
            # exit search's samples on a hole's wall, ...): the step named, as its other failures
            raise InsertionFailure(f"step {step} (needle rotation {rotation:.3f} rad): {error}") from None
    raise InsertionFailure(f"the needle tip did not leave the tissue within {limit} steps "
                           f"(needle rotation {limit * geometry.step:.3f} rad)")


def _needle_at_entry(scenario: Scenario, control: CenterControl | None, center_path: np.ndarray | None,
                     linear_solver: str | None, tip_tracking: str | None,
                     tissue: PreparedTissue | None) -> tuple[NeedleInsertion, CenterControl]:
    """The needle insertion with the needle at its entry, and the run's centre control (a
    replay of `center_path` when given, the fixed centre when none): a replayed path's row 0
    leans the needle as the path was planned (geometry.entry_lean)."""
    if center_path is not None:
        control = CenterReplay(center_path)
    replayed_entry = control.predict(None, 0) if isinstance(control, CenterReplay) else None  # row 0
    if replayed_entry is not None:  # a path planned with the needle leaning at entry leans it
        scenario = entry_lean(scenario, replayed_entry)
    insertion = NeedleInsertion(scenario, linear_solver=linear_solver, tip_tracking=tip_tracking, tissue=tissue)
    if replayed_entry is not None:
        insertion.move_center(replayed_entry)
    return insertion, control or FixedCenter()


class _TrackedTip(NamedTuple):
    """The tip's material point after a step and how it was tracked; `fraction` the part of a
    step the track segment ending there spans (less after entering from a wound's gap),
    `taken` the earlier run's state after the step when this run follows that run's tip."""

    point: np.ndarray
    method: str
    fraction: float = 1.0
    taken: Snapshot | None = None


class _Run:
    """One run_insertion's state between needle steps (Algorithm 1): the needle insertion,
    the tip's boundary crossings so far, the earlier run it follows, and the steps' records
    (NeedleStep, the equilibrium after each, the displacement coefficients d after each)."""

    def __init__(self, insertion: NeedleInsertion, control: CenterControl, condition_numbers: bool,
                 on_step: Callable[[NeedleStep], None] | None, start_from: InsertionResult | StepsDone | None,
                 take_over_only: bool, wall_start: float):
        self.insertion, self.geometry, self.control = insertion, insertion.geometry, control
        self.condition_numbers, self.on_step, self.wall_start = condition_numbers, on_step, wall_start
        self.entry_center = insertion.center.copy()
        insertion.add_point(self.geometry.entry.copy())  # Gamma_N starts at the entry
        # d after each step, the entry's first (InsertionResult.displacements)
        self.coefficients = [np.zeros_like(insertion.model.particles)]
        self.steps: list[NeedleStep] = []
        self.states: list[Snapshot] = []  # the equilibrium after each step
        self.start_from = start_from
        self.earlier = start_from.states if start_from is not None and start_from.model is insertion.model else []
        self.guesses = [] if take_over_only else self.earlier  # where the steps not taken over start their Newton solve
        # every centre so far the earlier run's (a needle across no wound, whose steps' records
        # hold their tracked tip points)
        self.followed = bool(self.earlier) and not self.geometry.gaps
        self.loops = BoundaryLoops.of(insertion.domain)
        # the tip's boundary crossings in order, (index into geometry.crossings, "exit" | "entry",
        # reference point, rotation): each matched to the undeformed circle's crossing it makes,
        # or to the wall it crosses back through (a crossing of the other kind: a soft wall that
        # bulged round the tip); the ones passed over missed
        self.made: list[Crossing] = []
        self.ahead = 0  # the first crossing of the undeformed circle the tip has yet to make (or miss)
        self.in_gap = False  # the tip crossing a wound: no new needle point until it re-enters

    def track_in_tissue(self, step: int, rotation: float) -> _TrackedTip:
        """The tip's new material point (eq. 3.66-3.70), tracked about the previous step's
        centre, or the earlier run's while this run has taken that run's centres."""
        geometry, made = self.geometry, self.made
        if rotation > geometry.arc and made and crossed_back(geometry, made[-1]):
            raise stayed_on_near_side(self.insertion, step, rotation, made)
        self.followed = (self.followed and step <= len(self.earlier)
                         and np.array_equal(self.start_from.center_after(step - 1), self.insertion.center))
        taken = self.earlier[step - 1] if self.followed else None
        if taken is not None:
            return _TrackedTip(*_tracked_before(self.start_from, step, self.insertion), taken=taken)
        return _TrackedTip(*track_step(self.insertion, step, rotation))  # about the previous step's centre

    def step_in_gap(self, step: int, rotation: float, started: float) -> _TrackedTip | None:
        """A step of the tip crossing a wound's gap: where the tip enters the tissue again
        within the step (added to the track) and its point tracked on from there; None while
        it stays in the gap, the step then solved with no new needle point."""
        insertion, geometry, wall = self.insertion, self.geometry, self.made[-1]
        previous = rotation - geometry.step
        # the needle turns no further than its arc through a wound: the tip enters again within it
        entered = reentry(insertion, step, max(previous, wall[3]), min(rotation, geometry.arc))
        if entered is None:
            if rotation >= geometry.arc:
                raise left_for_good(insertion, step, wall)
            self.solve(step, rotation, None, "gap", started)
            return None
        entry_point, entry_rotation = entered
        self._cross(step, "entry", entry_point, entry_rotation, back=wall[0])
        _add_point(insertion, step, rotation, entry_point, gap=True)
        self.in_gap = False
        log_crossing(insertion, step, self.made)
        point, method = track_step(insertion, step, rotation, rotation - entry_rotation)
        return _TrackedTip(point, method, (rotation - entry_rotation) / geometry.step)

    def tip_outside(self, step: int, rotation: float, tip: _TrackedTip, started: float) -> InsertionResult | None:
        """The tip tracked outside the tissue: where it left within the step and which
        crossing of the undeformed circle that makes. Through a wound's wall the track reaches
        the wall and the tip goes on in the gap (None); through the final exit, the run's
        result."""
        insertion, geometry = self.insertion, self.geometry
        previous = rotation - geometry.step
        start = max(previous, self.made[-1][3]) if self.made else previous  # after an entry within the step
        exit_point, exit_rotation = locate_exit(insertion, start, tip.method,
                                                (rotation - start) if start != previous else None)
        crossing = self._cross(step, "exit", exit_point, exit_rotation,
                               back=self.made[-1][0] if self.made else None)
        if crossing < len(geometry.crossings) - 1:
            log_crossing(insertion, step, self.made)
            if rotation >= geometry.arc:  # too late in the arc to enter again
                raise left_for_good(insertion, step, self.made[-1])
            _add_point(insertion, step, rotation, exit_point, fraction=(exit_rotation - start) / geometry.step)
            self.in_gap = True
            self.solve(step, rotation, None, tip.method, started)
            return None
        if (ahead_entry := entry_ahead(insertion, exit_rotation, geometry.arc)) is not None:
            raise left_into_uncrossed_gap(insertion, self.loops, step, exit_point, exit_rotation, ahead_entry)
        return _result(insertion, self.entry_center, self.steps, self.states, self.coefficients, exit_point,
                       exit_rotation, time.perf_counter() - self.wall_start, self.made)

    def _cross(self, step: int, kind: str, point: np.ndarray, rotation: float, back: int | None) -> int:
        """Keep the tip's boundary crossing at `point` (`kind`: "exit" or "entry"), matched by
        _crossing_made (`back`: the crossing made last, whose wall the tip may cross back
        through), and the crossing ahead after it; returns the index it matched."""
        crossing = crossing_made(self.insertion, self.loops, step, kind, point, rotation, self.ahead, back)
        self.made.append((crossing, kind, point, rotation))
        self.ahead = ahead_after(self.geometry, self.made[-1])
        return crossing

    def solve(self, step: int, rotation: float, point: np.ndarray | None, method: str, started: float,
              fraction: float = 1.0, taken: Snapshot | None = None) -> None:
        """_needle_step, its Newton solve started from the earlier run's change over the step
        (_at), and its record and state kept; a control that stops the run (InsertionStopped)
        gets the steps done before it."""
        insertion = self.insertion
        guess = _at(self.guesses, step, insertion)
        try:
            record = _needle_step(insertion, self.control, step, rotation, point, method, self.condition_numbers,
                                  started, fraction, guess, taken=taken)
        except InsertionStopped as stopped:
            stopped.done = StepsDone(insertion.model, self.geometry, self.entry_center, self.steps, insertion.events,
                                     self.states)
            raise
        self.steps.append(record)
        self.states.append(insertion.snapshot(coupling=True))
        self.coefficients.append(insertion.coefficients())  # a new array after each solve, never changed in place
        if self.on_step is not None:
            self.on_step(record)


def _tracked_before(earlier: InsertionResult | StepsDone, step: int,
                    insertion: NeedleInsertion) -> tuple[np.ndarray, str]:
    """The earlier run's tip point of `step` and how it was tracked, with its tracking events."""
    record = earlier.steps[step - 1]
    insertion.events.extend(event for event in earlier.events
                            if event.kind == EventKind.TIP_TRACKING_FALLBACK and event.step == step)
    return record.tip_reference.copy(), record.tracking


def _at(states: list[Snapshot], step: int, insertion: NeedleInsertion) -> Snapshot | None:
    """Where `step`'s Newton solve starts, from an earlier run that got that far: this run's
    state before the step plus the earlier run's change over the step (its multipliers as
    they were)."""
    if step > len(states):
        return None
    before = states[step - 2].free if step > 1 else 0.0
    after = states[step - 1]
    return Snapshot(insertion.free + (after.free - before), after.multipliers, after.center, after.violation)


def _add_point(insertion: NeedleInsertion, step: int, rotation: float, point: np.ndarray, **options) -> None:
    """insertion.add_point, a point of the new track segment that no particle's kernel covers
    (a tip tracked past a wall, into a hole) failing the step by name."""
    try:
        insertion.add_point(point, **options)
    except SingularMomentAt as error:
        outside = insertion.domain.outside_distance(error.point)
        why = (f"{outside:.3g} mm outside the tissue at rest (in a hole or a gap), where no particle's kernel "
               "reaches: the tip was tracked past a wall the deformed tissue had moved; a finer spacing at that "
               "wall may carry it" if outside > insertion.domain.tolerance else str(error))
        raise InsertionFailure(f"step {step} (needle rotation {rotation:.3f} rad): the needle's track reaches "
                               f"{point_text(error.point)}, {why}") from None


def _needle_step(insertion: NeedleInsertion, control: CenterControl, step: int, rotation: float,
                 point: np.ndarray | None, method: str, condition_numbers: bool, started: float,
                 fraction: float = 1.0, guess: Snapshot | None = None, taken: Snapshot | None = None) -> NeedleStep:
    """Add the tracked tip point (none while the tip crosses a wound's gap), equilibrate
    about the step's centre (with the control's aim: the centre an unknown of the same
    Newton solve); the step's record (its wall time from `started`, before the tip was
    tracked). `taken`: an earlier run's state after this step, reached from this run's
    state before it with the same tip point; taken over (NeedleInsertion.take_over) when
    the control holds the centre where that run's was."""
    newton_before, solves_before = insertion.newton_iterations, insertion.equilibrium_solves
    insertion.move_center(control.predict(insertion.center, step))
    aim = control.aim(insertion, step, rotation)
    minres_iterations = 0
    if taken is not None and aim is None and np.array_equal(insertion.center, taken.center):
        insertion.take_over(taken)
    else:
        if point is not None:
            _add_point(insertion, step, rotation, point, fraction=fraction)
        _, minres_iterations, _ = insertion.equilibrate(rotation, step, aim, guess)
    if point is None:
        point = insertion.points[-1]
    planner_iterations = control.correct(insertion, step, rotation)
    geometry = insertion.geometry
    friction, cutting = insertion.coupling.applied_forces()
    record = NeedleStep(
        step=step, rotation=rotation, center=insertion.center.copy(),
        needle_tip=geometry.tip(rotation, insertion.center), tip_reference=point.copy(),
        tip_spatial=point + insertion.tip_displacement(), needle_points=len(insertion.points),
        friction_force=friction, cutting_force=cutting, newton_iterations=insertion.newton_iterations - newton_before,
        equilibrium_solves=insertion.equilibrium_solves - solves_before,
        minres_iterations=minres_iterations, constraint_violation=insertion.last_violation, tracking=method,
        exit_displacement=insertion.point_displacement(geometry.desired_exit),
        planner_iterations=planner_iterations,
    )
    record.wall_seconds = time.perf_counter() - started  # tracking and solves, before diagnostics
    if aim is not None:
        record.eq42_ratio = aim.eq42_ratio
    if condition_numbers:
        record.condition_saddle, record.condition_preconditioned = insertion.condition_numbers()
    log.info("step %d (needle rotation %.3f rad): Newton iterations %d, constraint violation %.2e mm%s",
             step, rotation, record.newton_iterations, record.constraint_violation,
             "" if isinstance(control, FixedCenter) else f", centre iterations {planner_iterations}")
    return record


def _result(insertion: NeedleInsertion, entry_center: np.ndarray, steps: list[NeedleStep],
            states: list[Snapshot],
            coefficients: list[np.ndarray],
            exit_point: np.ndarray, exit_rotation: float, wall_seconds: float,
            made: list[Crossing]) -> InsertionResult:
    """The run's record once the tip has left the tissue at `exit_point` (the final exit, the
    last of the tip's boundary crossings `made`)."""
    desired_exit = insertion.geometry.desired_exit
    crossings = crossings_record(insertion, made)
    u_exit = insertion.displacement(np.vstack([exit_point, desired_exit]))  # achieved, desired
    result = InsertionResult(
        scenario=insertion.scenario, model=insertion.model, geometry=insertion.geometry,
        entry_center=entry_center, steps=steps, coefficients=np.asarray(coefficients),
        needle_points=insertion.points.copy(),
        desired_exit=desired_exit, desired_exit_def=desired_exit + u_exit[1],
        achieved_exit=exit_point, achieved_exit_def=exit_point + u_exit[0], exit_rotation=exit_rotation,
        wall_seconds=wall_seconds, timings=insertion.timings, events=insertion.events,
        solver_counts={"factorizations": insertion.saddle.factorizations,
                       "linear_solves": insertion.saddle.solves,
                       "solved_columns": insertion.saddle.solved_columns,
                       "linear_solver": insertion.linear_method,
                       "linear_solver_backend": insertion.saddle.backend,
                       "linear_solver_backends": list(insertion.saddle.backends),
                       "minres_iterations": insertion.saddle.minres_iterations,
                       "minres_fallbacks": insertion.saddle.fallbacks,
                       "tangent_products": insertion.assembler.tangent_products,
                       # the needle steps' Newton stopped at these (needle/newton.py newton_tolerances)
                       "needle_residual_tolerance": insertion.newton_tolerances[0],
                       "needle_constraint_tolerance": insertion.newton_tolerances[1]},
        crossings=crossings,
        bites=stitch_bites(insertion, crossings),
        states=states,
    )
    log.info("the tip left the tissue at needle rotation %.3f rad: exit error %.4g mm",
             exit_rotation, result.exit_error_mm)
    return result
