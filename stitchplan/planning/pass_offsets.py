"""The planner's passes over the whole insertion (planner.run_plan): the offsets c_k that
aim each pass's centres, found by a secant search along the exit edge (PassOffsets), and the
early steps a later pass takes over from the first (PassPrefix)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..config import Planner
from ..events import EventKind
from ..needle.geometry import length
from ..needle.results import InsertionResult
from .move_limits import REFERENCE_STEP

REAIM_LEAD = 4  # a later pass's offset acts from this many steps before the first pass's late limited steps
# ... when it is at most this fraction of the second-difference limit: a larger one acts from step 1
REAIM_FRACTION = 0.25


@dataclass(frozen=True)
class PassPrefix:
    """The steps a later pass takes over from the plan's first pass (PassOffsets): steps 1 ..
    first_aimed - 1 keep the first pass's centres, tip points and equilibria (run_insertion
    `start_from`: taken over, not solved again), so only the steps from `first_aimed` on are
    solved with the pass's offset."""

    reference: InsertionResult  # the first pass (offset zero)
    first_aimed: int  # the first step whose centre the pass's offset moves
    limited_steps: tuple[int, ...]  # the first pass's steps a move limit held back
    largest_offset: float  # mm: a larger offset acts from step 1 (`for_offset`)

    @classmethod
    def of(cls, reference: InsertionResult, limited_steps: list[int], settings: Planner) -> PassPrefix:
        """The offset acts REAIM_LEAD steps before the run of limited steps the first pass
        ended with (its last step when it did not end held): the drift the offset
        compensates comes after those steps, and the steps from there on still move the exit.
        It enters there as a jump of the aimed centre, which the second-difference limit
        passes only when small: up to REAIM_FRACTION of that limit (0.035 mm per 0.08 rad
        by default). The thesis's table 5.1 100 x 100 block, whose first pass misses by
        0.21 mm, took 3 passes to 0.00025 mm with the offset from step 1 and was still
        0.021 mm off after 4 with it from step 15."""
        late = len(reference.steps)
        if late in limited_steps:
            while late - 1 in limited_steps:
                late -= 1
        scale = reference.geometry.step / REFERENCE_STEP
        return cls(reference, max(late - REAIM_LEAD, 1), tuple(limited_steps),
                   REAIM_FRACTION * settings.center_second_difference_limit * scale)

    def for_offset(self, offset: np.ndarray) -> PassPrefix | None:
        """This prefix for a pass with `offset`, or None: the pass runs every step."""
        return self if self.first_aimed > 1 and length(offset) <= self.largest_offset else None

    def center(self, step: int) -> np.ndarray:
        """The first pass's centre at `step` (0: the entry centre)."""
        return self.reference.center_after(step).copy()

    def start(self) -> InsertionResult:
        """run_insertion's `start_from` for the prefix: the first pass, its states cut there."""
        return replace(self.reference, states=self.reference.states[:self.first_aimed - 1])

    def take_over(self, result: InsertionResult) -> None:
        """Count the first pass's work for each prefix step in `result`'s record (its Newton
        iterations and wall time added to the later pass's, its equilibrium solves, centre moves
        and eq. 4.2 ratio instead of the later pass's), and add its planner events there: the
        steps as planned. The result's solver_counts stay those of its own run."""
        for record, planned in zip(result.steps[:self.first_aimed - 1], self.reference.steps):
            record.newton_iterations += planned.newton_iterations
            record.equilibrium_solves = planned.equilibrium_solves
            record.wall_seconds += planned.wall_seconds
            record.planner_iterations, record.eq42_ratio = planned.planner_iterations, planned.eq42_ratio
        held = [event for event in self.reference.events
                if event.kind == EventKind.PLANNER_NOT_CONVERGED and event.step is not None
                and event.step < self.first_aimed]
        result.events[:0] = held


class PassOffsets:
    """The offsets c_k of the planning passes, a secant search along the exit edge.

    The exit error e = achieved_exit_def - desired_exit_def lies along the deformed edge at
    the exit (both points are on it), so the passes solve one equation: t . (e(c) - aim) = 0
    with c = s t, t the direction of the first pass's miss. Moving the aim of the centre by
    c moves the exit by about -c along the edge (de/dc ~ -1, the start of the secant); the
    slope is then the secant of t . e over the last two passes (whatever each aimed at: a
    later round or a predicted aim changes the aim, not e(c)), kept within [-3, -1/3] so that
    a pass held back by the move limits cannot send the next one far off.

    With the symmetric target the aim follows each pass's bites (planner.symmetric_aim: the
    exit moved by the bites' difference), and t . e has the difference's slope only where the
    bites end at points fixed in the tissue (a cut's lips). Through a hole they end where the
    needle crosses its wall, which moves with the offset: there the difference moved 1.4 mm
    per mm of offset where t . e moved 0.4, so each pass overshot the aim further than the
    one before. Once two passes lie on either side of the aim (`overshot`), the secant is
    taken of t . (e - p) instead, p the aim at equal bites each pass's own bites set (the
    bites' difference along t, whatever bite difference a round aims at), which brings the
    next pass between them.

    Where the move limits hold the centre back from the start, a larger offset can move the
    exit away from the aim as well as toward it: once a secant's slope comes out zero or
    positive, the offsets stop extrapolating and search between the passes already run for
    the exit nearest the aim (`searching`, _offset_between): the root between two passes on
    either side of the aim, else the vertex of the parabola through the nearest pass and its
    neighbours (a golden-section point when the vertex falls outside them), so the passes close
    in on the nearest exit the limits allow instead of running off; run_plan's passes stop
    once the next offset is within the exit tolerance of one already run (`closest_tried`).

    The offset of every pass after the first acts from the same step on (`prefix`, set from
    the first pass): the steps before it are the first pass's, taken over rather than solved
    again, so a pass costs only its late steps and e(c) stays one function of c.
    """

    def __init__(self, tilt: float | None = None):
        self.offset = np.zeros(2)
        self.tilt = tilt  # rad the needle leans at entry in these passes (planner.aim_entry_tilt)
        self.prefix: PassPrefix | None = None
        self.direction: np.ndarray | None = None
        self.slope = -1.0
        self.last: tuple[float, np.ndarray] | None = None  # (s, e) of the last pass run
        self.follows: np.ndarray | None = None  # p of the last pass run (symmetric target)
        self.tried: dict[float, float] = {}  # s: t . e of every pass advanced from
        self._previous: tuple[float, float, float | None] | None = None  # (s, t . e, t . (e - p)) of the pass before
        self.overshot = False  # (symmetric target) two passes fell on either side of the aim
        self.searching = False  # a secant slope came out >= 0: offsets between the passes run

    @property
    def position(self) -> float:
        return 0.0 if self.direction is None else float(self.direction @ self.offset)

    def record(self, error: np.ndarray, follows: np.ndarray | None = None) -> None:
        """The exit error vector of the pass run with the current offset and (symmetric
        target) `follows`, the aim at equal bites its bites set."""
        self.last = (self.position, np.asarray(error, dtype=float))
        self.follows = None if follows is None else np.asarray(follows, dtype=float)

    def advance(self, aim: np.ndarray) -> None:
        """The offset of the next pass, aiming the exit error at `aim`."""
        position, error = self.last
        miss = error - aim
        if self.direction is None:
            norm = float(np.linalg.norm(miss))
            if norm == 0.0:
                return
            self.direction = miss / norm
        along, exit_along = float(self.direction @ miss), float(self.direction @ error)
        bites_along = None if self.follows is None else float(self.direction @ (error - self.follows))
        previous = self._previous
        if previous is not None and previous[2] is not None and bites_along is not None:
            # the pass before's miss of this aim: previous t . (e - p) - this one's + this miss
            self.overshot = self.overshot or along * (previous[2] - bites_along + along) < 0.0
        if previous is not None and position != previous[0]:
            if self.overshot and previous[2] is not None and bites_along is not None:
                slope = (bites_along - previous[2]) / (position - previous[0])
            else:
                slope = (exit_along - previous[1]) / (position - previous[0])
            self.searching = self.searching or slope >= 0.0
            self.slope = float(np.clip(slope, -3.0, -1.0 / 3.0))
        self._previous, self.tried[position] = (position, exit_along, bites_along), exit_along
        if self.searching:
            self.offset = _offset_between(self.tried, exit_along - along) * self.direction
        else:
            self.offset = (position - along / self.slope) * self.direction

    def closest_tried(self) -> float:
        """mm between the next pass's offset and the nearest one already run (along the search)."""
        return min(abs(self.position - position) for position in self.tried)


GOLDEN_SECTION = (3.0 - math.sqrt(5.0)) / 2.0  # the smaller golden-section fraction of an interval


def _offset_between(tried: dict[float, float], aim_along: float) -> float:
    """The next offset s of PassOffsets' search, within the passes `tried` (s: t . e), about
    the pass nearest the aim: with a neighbour (in s) on the aim's other side, the root
    between them of the parabola through it and its two neighbours (of their secant when it
    has no two neighbours or the parabola no root there); else the vertex of the parabola
    through |t . e - aim| at the three, or a golden-section point of the wider side when that
    parabola has no minimum between them; the midpoint toward its neighbour when the nearest
    pass is the first or last in s."""
    positions, exits = np.array(sorted(tried.items())).T
    misses = exits - aim_along
    best = int(np.argmin(np.abs(misses)))
    sides = [k for k in (best - 1, best + 1) if 0 <= k < len(positions)]
    three = positions[best - 1:best + 2] if len(sides) == 2 else None
    for k in sides:
        if misses[k] * misses[best] < 0.0:
            low, high = sorted((positions[best], positions[k]))
            if three is not None:
                roots = np.roots(_parabola(three, misses[best - 1:best + 2]))
                inside = [root.real for root in roots if root.imag == 0.0 and low < root.real < high]
                if inside:
                    return float(inside[0])
            return float(positions[best] - misses[best] * (positions[k] - positions[best]) / (misses[k] - misses[best]))
    if three is None:
        return float(0.5 * (positions[best] + positions[sides[0]]))
    curvature, slope, _ = _parabola(three, np.abs(misses[best - 1:best + 2]))
    vertex = -slope / (2.0 * curvature) if curvature > 0.0 else np.nan
    if three[0] < vertex < three[2]:
        return float(vertex)
    wider_end = three[0] if three[1] - three[0] > three[2] - three[1] else three[2]
    return float(three[1] + GOLDEN_SECTION * (wider_end - three[1]))


def _parabola(points: np.ndarray, values: np.ndarray) -> tuple[float, float, float]:
    """(A, B, C) of A s^2 + B s + C through three (point, value) pairs (divided differences)."""
    (a, b, c), (fa, fb, fc) = points, values
    first = (fb - fa) / (b - a)
    curvature = ((fc - fb) / (c - b) - first) / (c - a)
    return curvature, first - curvature * (a + b), fa - first * a + curvature * a * b
