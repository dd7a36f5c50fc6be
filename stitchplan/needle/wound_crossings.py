"""The needle tip's boundary crossings through a wound (README, "Tissue shapes"): which
crossing of the undeformed circle a crossing of the tip makes, or the wall it crosses back
through; the failures of a tip that cannot cross (named with the step and the rotation);
and the summary's `crossings` and `bites` once the tip has left (needle/insertion.py runs
the steps).

A crossing made is (index into geometry.crossings, "exit" | "entry", reference point,
needle rotation).
"""

from __future__ import annotations

import logging

import numpy as np

from ..errors import InsertionFailure
from ..events import Event, EventKind
from .equilibrium import NeedleInsertion
from .geometry import BoundaryLoops, NeedleGeometry
from .tip_tracking import locate_reentry

log = logging.getLogger(__name__)

Crossing = tuple[int, str, np.ndarray, float]


def gap_at(insertion: NeedleInsertion, point: np.ndarray) -> str:
    """'wound' where the wall nearest `point` is the outline's (a cut reaching the surface),
    'hole' where it is a hole's: what the tip crossed, in its messages; on a needle whose
    only gaps lie beyond the tissue's far side (no wounds), the gap outside the tissue."""
    if not insertion.domain.nearest_boundary_point(point)[1]:
        return "hole"
    return "wound" if insertion.geometry.wounds else "gap outside the tissue"


def crossed_back(geometry: NeedleGeometry, made: Crossing) -> bool:
    """Whether the tip's boundary crossing went back through the wall of a crossing of the
    other kind (the wall it had just left, or the far wall it had just entered)."""
    crossing, kind, _, _ = made
    return geometry.crossings[crossing][1] != kind


def ahead_after(geometry: NeedleGeometry, made: Crossing) -> int:
    """The first crossing of the undeformed circle still ahead after the tip's boundary
    crossing: the next one when the tip made its crossing, the crossing itself when the tip
    crossed back through its wall (the tip has to cross that wall again)."""
    crossing = made[0]
    return crossing if crossed_back(geometry, made) else crossing + 1


def log_crossing(insertion: NeedleInsertion, step: int, made: list[Crossing]) -> None:
    """Say which wall the tip crossed through a wound, and whether it crossed back (a soft
    wall that bulged round the tip) or crossed that wall once more."""
    geometry = insertion.geometry
    crossing, kind, point, rotation = made[-1]
    wall = f"crossing {crossing + 1} of {len(geometry.crossings)} of the undeformed circle"
    gap = gap_at(insertion, point)
    if crossed_back(geometry, made[-1]):
        if kind == "entry":
            message = (f"step {step}: the tip entered the tissue again at {point_text(point)} at needle rotation "
                       f"{rotation:.3f} rad on the near side of the {gap}: nearest along the boundary to the wall "
                       f"it left ({wall}), not to the far wall (the wall bulged round the tip); it has to leave "
                       "through that wall again")
        else:
            message = (f"step {step}: the tip left the tissue back into the {gap} at {point_text(point)} at needle "
                       f"rotation {rotation:.3f} rad, through the far wall it had entered ({wall}); it has to "
                       "enter that wall again")
        insertion.events.append(Event(EventKind.WALL_CROSSED_BACK, message, step, rotation))
        log.info(message)
    elif any(earlier[:2] == (crossing, kind) for earlier in made[:-1]):  # the same wall once more
        log.info("step %d: the tip %s at %s at needle rotation %.3f rad, through the same wall (%s)",
                 step, f"left the tissue into a {gap} again" if kind == "exit" else "entered the far wall again",
                 point_text(point), rotation, wall)
    elif kind == "entry":
        log.info("step %d: the tip entered the tissue again at needle rotation %.3f rad", step, rotation)
    else:
        log.info("step %d: the tip left the tissue into a %s at needle rotation %.3f rad", step, gap, rotation)


def stayed_on_near_side(insertion: NeedleInsertion, step: int, rotation: float,
                        made: list[Crossing]) -> InsertionFailure:
    """The failure of a run whose tip entered the tissue again through the wall it had left
    and is still on that side of the wound when the needle's arc ends."""
    geometry = insertion.geometry
    crossing, _, point, entered = made[-1]
    gap = gap_at(insertion, point)
    return InsertionFailure(
        f"step {step}: the needle's arc of {geometry.arc:.4g} rad ended (needle rotation {rotation:.3f} rad) with "
        f"its tip still on the near side of the {gap}: the tip entered the tissue again at {point_text(point)} "
        f"at needle rotation {entered:.3f} rad through the wall it had left (crossing {crossing + 1} of the "
        f"undeformed circle; the wall bulged round the tip) and did not leave through it again to cross the {gap}")


def left_for_good(insertion: NeedleInsertion, step: int, wall: Crossing) -> InsertionFailure:
    """The failure of a run whose tip left the tissue into a wound and cannot enter it again
    within the needle's arc (a needle turned no further through the air)."""
    crossing, _, point, rotation = wall
    geometry = insertion.geometry
    return InsertionFailure(
        f"step {step}: the needle tip left the tissue into a {gap_at(insertion, point)} at {point_text(point)} at "
        f"needle rotation {rotation:.3f} rad (crossing {crossing + 1} of the undeformed circle) and did not enter "
        f"it again within the needle's arc of {geometry.arc:.4g} rad")


def left_into_uncrossed_gap(insertion: NeedleInsertion, loops: BoundaryLoops, step: int, exit_point: np.ndarray,
                            exit_rotation: float, ahead_entry: tuple[np.ndarray, float]) -> InsertionFailure:
    """The failure of a run whose tip left the tissue where the undeformed circle stays inside
    (the deformed tissue carried a notch's or a hole's wall across the needle's path): the
    needle's circle enters the tissue again ahead, so the tip has not left for good, and a
    crossing the undeformed circle does not make is not followed."""
    geometry = insertion.geometry
    point, rotation = ahead_entry
    return InsertionFailure(
        f"step {step}: the needle tip left the tissue through {loops.describe(exit_point)} at "
        f"{point_text(exit_point)} at needle rotation {exit_rotation:.3f} rad (the undeformed circle's final "
        f"exit: {point_text(geometry.desired_exit)} at {geometry.exit_rotation:.3f} rad), and its circle enters "
        f"the deformed tissue again at {point_text(point)} (deformed position, needle rotation {rotation:.3f} "
        "rad): the tissue's deformation carried the boundary across the needle's path where the undeformed circle "
        "crosses none, and such a crossing is not followed; move the entry or change the radius so that the "
        "undeformed circle crosses that gap or clears it by more than the tissue moves")


def reentry(insertion: NeedleInsertion, step: int, start: float, end: float) -> tuple[np.ndarray, float] | None:
    """locate_reentry, its failure naming the step."""
    try:
        return locate_reentry(insertion, start, end)
    except InsertionFailure as failure:
        raise InsertionFailure(f"step {step}: {failure}") from None


def crossing_made(insertion: NeedleInsertion, loops: BoundaryLoops, step: int, kind: str, point: np.ndarray,
                  rotation: float, ahead: int, back: int | None) -> int:
    """The crossing of the undeformed circle (index into geometry.crossings) that the tip
    crossing the boundary at `point` (`kind`: "exit" or "entry") makes, or `back`, the one it
    made last, when it crosses back through that wall (NeedleGeometry.crossing_made); an event
    for each crossing from `ahead` on that it passed over without making. Raises
    InsertionFailure when the tip crosses a wall the undeformed circle does not cross ahead."""
    geometry = insertion.geometry
    crossing = geometry.crossing_made(loops, point, kind, ahead, back)
    where = f"{point_text(point)} at needle rotation {rotation:.3f} rad"
    verb = "left" if kind == "exit" else "entered"
    if crossing is None:
        raise InsertionFailure(
            f"step {step}: the needle tip {verb} the tissue through {loops.describe(point)} at {where}, where the "
            f"undeformed circle {'leaves' if kind == 'exit' else 'enters'} at none of its crossings "
            f"{ahead + 1}-{len(geometry.crossings)}; expected the tip to {'leave' if kind == 'exit' else 'enter'} "
            "where the undeformed circle does")
    made = "the final exit" if crossing == len(geometry.crossings) - 1 else f"crossing {crossing + 1} ({kind})"
    for missed in range(ahead, crossing):
        missed_kind, desired = geometry.crossings[missed][1], geometry.crossing_point(missed)
        message = (f"crossing {missed + 1} of {len(geometry.crossings)} of the undeformed circle ({missed_kind} at "
                   f"{point_text(desired)} on {loops.describe(desired)}) missed: the needle tip did not cross "
                   f"the boundary there but next {verb} the tissue at {where}, nearest along the boundary to "
                   f"{made}")
        insertion.events.append(Event(EventKind.CROSSING_MISSED, message, step, rotation))
        log.info(message)  # the user sees it once, as a `note:` from the event
    return crossing


def point_text(point: np.ndarray) -> str:
    """'[x, y]' to 4 digits, without -0 or 1e-16 off an edge."""
    x, y = (round(float(value), 9) + 0.0 for value in point)
    return f"[{x:.4g}, {y:.4g}]"


def crossings_record(insertion: NeedleInsertion, made: list[Crossing]) -> list[dict]:
    """The summary's `crossings` (README, "Tissue shapes"): every crossing of the
    undeformed circle after the entry in needle order, its point (desired, at rest and moved
    with the tissue) against the tip's material point there (achieved, deformed); achieved,
    achieved_def and error_mm None for a crossing the tip missed (`made`: the tip's boundary
    crossings in order, by index). A wall the tip crossed more than once (back into the tissue
    through a bulging wall and out again) keeps the last time, the one before it went on."""
    geometry = insertion.geometry
    desired = np.array([geometry.desired_point(k) for k in range(len(geometry.crossings))])
    # the last crossing of each wall made in its own direction (not a crossing back through it)
    achieved = {crossing: point for crossing, kind, point, _ in made if kind == geometry.crossings[crossing][1]}
    reached = np.array([achieved[k] for k in sorted(achieved)]).reshape(-1, 2)
    u = insertion.displacement(np.vstack([desired, reached]))
    u_reached = dict(zip(sorted(achieved), u[len(desired):]))
    records = []
    for k, (_, kind) in enumerate(geometry.crossings):
        desired_def = desired[k] + u[k]
        record = {"kind": kind, "desired": desired[k], "desired_def": desired_def,
                  "achieved": None, "achieved_def": None, "error_mm": None}
        if k in achieved:
            achieved_def = achieved[k] + u_reached[k]
            record.update(achieved=achieved[k], achieved_def=achieved_def,
                          error_mm=float(np.linalg.norm(achieved_def - desired_def)))
        records.append(record)
    return records


def wound_walls_crossed(geometry: NeedleGeometry, crossings: list[dict]) -> list[np.ndarray]:
    """The achieved points, in needle order, of the wounds' walls the tip crossed
    (`crossings`: crossings_record's)."""
    walls = geometry.wound_walls
    return [crossing["achieved"] for k, crossing in enumerate(crossings[:-1])
            if k in walls and crossing["achieved"] is not None]


def stitch_bites(insertion: NeedleInsertion, crossings: list[dict]) -> dict | None:
    """The stitch's bites across a wound: on the entry side the deformed distance from the
    needle's entry to the wound edge (a cut's: the end of the wall the tip left through nearest
    the entry, its lip on the surface; a hole's, which reaches no surface: the point of its wall
    the tip left through), on the exit side from the final exit to the edge of the wall it came
    back in through; and their difference (the symmetry surgeons look for). None where the tip
    crossed no wound's walls.

    A wall crossing's achieved point is the tip's material point, which need not lie on the
    wall: the visibility criterion makes u jump within hundredths of a mm of a wall it tests
    for pairs along it (a wound's, a hole's with corners; not a round hole's, whose pairs it
    weighs by the way round: shape_functions.Visibility), so the signed distance the crossing is
    root-found on can jump across zero there, and the point found lies up to that jump inside
    the tissue (0.008 mm at the SH 1/2 needle's default spacing across a 2 mm hole while round
    holes were tested for every pair). The wall crossed is the boundary edge nearest the
    point (both edges at a vertex), however near; a hole's wall point is the nearest to it (not an end of its
    edge: a circle's 96-gon would put the bite's end at whichever vertex lies nearer)."""
    domain, geometry = insertion.domain, insertion.geometry
    tol = 1e-6 * max(domain.size)

    def edge_near(point: np.ndarray, toward: np.ndarray) -> np.ndarray:
        wall_point, cut = domain.nearest_boundary_point(point)
        if not cut:  # a hole's wall
            return wall_point
        off = float(np.linalg.norm(wall_point - point))
        if off > tol:
            log.info("wound crossing %s lies %.3g mm off the boundary (u jumps near the wall); "
                     "its wall is the nearest boundary edge", np.round(point, 6).tolist(), off)
        names = domain.edges_at(point, off + tol)
        ends = np.array([end for name in names for end in domain.edge(name)])  # (2 x edges, 2)
        return ends[np.argmin(np.linalg.norm(ends - toward, axis=1))]

    # the walls of the wounds the tip crossed (a wound it missed has none; a gap that is the
    # outside beyond the tissue's far side is no wound)
    walls = wound_walls_crossed(geometry, crossings)
    if not walls:  # no bites
        return None
    first_wall, last_wall = walls[0], walls[-1]
    entry, final_exit = geometry.entry, crossings[-1]["achieved"]
    points = np.vstack([entry, edge_near(first_wall, entry), final_exit, edge_near(last_wall, final_exit)])
    moved = points + insertion.displacement(points)
    entry_side = float(np.linalg.norm(moved[1] - moved[0]))
    exit_side = float(np.linalg.norm(moved[3] - moved[2]))
    at_rest = (float(np.linalg.norm(points[1] - points[0])), float(np.linalg.norm(points[3] - points[2])))
    return {"entry_side_mm": entry_side, "exit_side_mm": exit_side, "difference_mm": exit_side - entry_side,
            "entry_wound_edge": points[1], "exit_wound_edge": points[3],
            "entry_wound_edge_def": moved[1], "exit_wound_edge_def": moved[3],
            "entry_side_at_rest_mm": at_rest[0], "exit_side_at_rest_mm": at_rest[1]}
