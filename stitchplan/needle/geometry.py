"""Rigid circular needle: centre at entry, turning sense and desired exit (thesis section 3.1.5).

Angles: the needle tip sits at C + R (cos phi, sin phi); the needle rotation alpha >= 0
since entry advances phi = phi0 + sense * alpha, with sense -1 for a clockwise turn.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..config import Needle, Scenario
from ..config.blocks import MAX_ENTRY_TILT, default_spacing_of
from ..config.boundary_points import nearest_note, shown_point, shown_point_as_given
from ..errors import InputError
from ..geometry.boundary import boundary_edges, nearest_on_edges, ray_meets_edges, smooth_vertex
from ..geometry.polygon_domain import PolygonDomain
from ..geometry.rectangle import Rectangle, circle_center_at_entry
from ..tissue.particles import RefinementZone, end_spacing


IDENTITY = np.eye(2)


def length(vector: np.ndarray) -> float:
    """|v| of a vector: np.linalg.norm's sqrt(v . v) without its argument handling (Newton,
    the centre aim and the tip tracking take several per iteration)."""
    return math.sqrt(vector.dot(vector))


def unit(angle: float | np.ndarray) -> np.ndarray:
    return np.stack([np.cos(angle), np.sin(angle)], axis=-1)


@dataclass(frozen=True)
class NeedleGeometry:
    """The needle at entry: centre, start angle, turning sense and the desired exit."""

    radius: float
    arc: float
    center: np.ndarray  # (2,) reference centre at entry
    start_angle: float  # phi0, angle of the entry point seen from the centre
    sense: float  # +1 ccw, -1 cw
    step: float  # rad per step
    entry: np.ndarray  # (2,)
    entry_edge: str
    exit_rotation: float  # alpha at which the undeformed circle leaves the tissue for good
    desired_exit: np.ndarray  # (2,)
    # every crossing of the undeformed circle with the boundary after the entry, in needle
    # order, the final exit last: (alpha, "exit" | "entry"); more than one with a wound
    crossings: tuple = ()
    tilt: float = 0.0  # rad leaned from the orthogonal entry (needle.entry_tilt)
    # the orthogonal needle's point of each crossing, the last the desired exit: what a leaning
    # needle aims at (its own circle's crossings are `crossings`); () for the crossings' own points
    desired_points: tuple = ()
    # the gaps (as `gaps`) with tissue beyond the circle across them: a wound or a hole, whose
    # walls a stitch's bites end at; a gap with none is the needle leaving the tissue's far
    # side and coming back (needle_geometry, _wounds)
    wounds: tuple = ()

    @property
    def gaps(self) -> list[tuple[float, float]]:
        """(exit, re-entry) rotations of every gap the undeformed circle crosses (a wound, a
        hole, or the outside beyond the tissue's far side)."""
        return [(a, b) for (a, ka), (b, kb) in zip(self.crossings, self.crossings[1:])
                if ka == "exit" and kb == "entry"]

    @property
    def wound_walls(self) -> set[int]:
        """Indices into `crossings` of the walls of the wounds (the exit into each and the
        re-entry out of it)."""
        rotations = [r for r, _ in self.crossings]
        return {rotations.index(r) for gap in self.wounds for r in gap}

    def crossing_point(self, k: int) -> np.ndarray:
        """The undeformed circle's point at crossing k, (2,)."""
        return self.tip(self.crossings[k][0])

    def desired_point(self, k: int) -> np.ndarray:
        """Where crossing k should be made, (2,): the undeformed circle's point, the orthogonal
        needle's for a leaning one (the last is the desired exit)."""
        return self.desired_points[k] if self.desired_points else self.crossing_point(k)

    def exit_made(self, loops: BoundaryLoops, point: np.ndarray, first: int) -> int | None:
        """Which crossing of the undeformed circle a tip that leaves the tissue at the boundary
        point `point` makes: of the exits from crossing `first` on, the one nearest to it along
        the boundary loop that holds it; None when no exit ahead lies on that loop.

        The deformed tissue may keep the tip from a wound the undeformed circle only clips, or
        let it out before a wall the circle grazes: counting exits would then take the final
        exit for a wound's wall. Where the tip leaves tells which exit it is; the crossings
        passed over are the ones it missed."""
        return self.crossing_made(loops, point, "exit", first)

    def crossing_made(self, loops: BoundaryLoops, point: np.ndarray, kind: str, first: int,
                      back: int | None = None) -> int | None:
        """Which crossing of the undeformed circle the tip crossing the boundary at `point`
        (`kind`: "exit" leaving the tissue, "entry" entering it) is: of the crossings of that
        kind from `first` on, and the crossing `back` the tip made last, the one nearest to it
        along the boundary loop that holds it; None when none of them lies on that loop.

        A soft wall bulges: the tip that left it into a wound may find itself in the tissue
        again on the same side, and leave through the same wall once more. Counting on to the
        crossings ahead would take that re-entry for the far wall and the second exit for the
        final exit; `back`, the wall the tip crossed last, is the tip crossing that wall back
        or once more (exit_made for the rest)."""
        candidates = [k for k in range(first, len(self.crossings)) if self.crossings[k][1] == kind]
        if back is not None and back not in candidates:
            candidates.append(back)
        distances = {k: loops.distance(point, self.crossing_point(k)) for k in candidates}
        nearest = min(distances, key=distances.get, default=None)
        return None if nearest is None or math.isinf(distances[nearest]) else nearest

    def tip(self, rotation: float | np.ndarray, center: np.ndarray | None = None) -> np.ndarray:
        """Tip position of the rigid needle after `rotation` (rad) about `center`."""
        center = self.center if center is None else center
        return center + self.radius * unit(self.start_angle + self.sense * np.asarray(rotation))

    def tips_along(self, centers: np.ndarray) -> np.ndarray:
        """The tip (n, 2) at each step k of a centre path (n, 2): about centre k after k steps.
        Row by row: trajectory.csv's tips and a replay's check of them agree to the bit."""
        return np.array([self.tip(k * self.step, center) for k, center in enumerate(centers)])

    def tangent(self, angle: float | np.ndarray) -> np.ndarray:
        """Direction of needle motion at the point of polar angle `angle` (a_0 of eq. 3.58)."""
        angle = np.asarray(angle)
        direction = np.empty(angle.shape + (2,))
        direction[..., 0], direction[..., 1] = -np.sin(angle), np.cos(angle)
        return self.sense * direction

    @property
    def insertion_step(self) -> float:
        """IS = R theta (eq. 3.69): the arc a step turns; the tip tracking holds the tip a chord
        2 R sin(theta / 2) from the last one instead (tip_tracking.track_tip)."""
        return self.radius * self.step

    @property
    def expected_steps(self) -> int:
        """Needle steps until the undeformed circle leaves the tissue, the exit step included."""
        return int(self.exit_rotation / self.step) + 1


@dataclass(frozen=True)
class BoundaryLoops:
    """The tissue's boundary walked loop by loop (the outline first, then each hole), its
    directed edges with their arc length along their loop: how far apart two boundary points
    are along the boundary (NeedleGeometry.crossing_made)."""

    starts: np.ndarray  # (k, 2) directed boundary edges, loop after loop
    ends: np.ndarray  # (k, 2)
    loop: np.ndarray  # (k,) the loop of each edge, 0 the outline
    offset: np.ndarray  # (k,) arc length along its loop at each edge's start, mm
    perimeter: np.ndarray  # (loops,) mm

    @classmethod
    def of(cls, domain: Rectangle | PolygonDomain) -> BoundaryLoops:
        starts, ends = boundary_edges(domain)
        lengths = np.linalg.norm(ends - starts, axis=1)
        # a loop starts where an edge does not begin at the previous edge's end
        first_of_loop = np.concatenate([[True], np.any(starts[1:] != ends[:-1], axis=1)])
        loop = np.cumsum(first_of_loop) - 1
        before = np.cumsum(lengths) - lengths  # arc length over every loop so far
        return cls(starts, ends, loop, before - before[first_of_loop][loop], np.bincount(loop, weights=lengths))

    def _nearest(self, point: np.ndarray) -> tuple[int, float, np.ndarray]:
        """The edge holding the boundary point nearest `point`, the fraction along it there,
        and that point."""
        k, along, nearest, _ = nearest_on_edges(self.starts, self.ends, point)
        return k, along, nearest

    def position(self, point: np.ndarray) -> tuple[int, float]:
        """The loop of the boundary point nearest `point`, and the arc length along it there."""
        k, along, _ = self._nearest(point)
        return int(self.loop[k]), float(self.offset[k] + along * length(self.ends[k] - self.starts[k]))

    def distance(self, first: np.ndarray, second: np.ndarray) -> float:
        """Distance between two boundary points along the boundary, the shorter way round their
        loop; inf on different loops (a hole's wall and the outline, two holes)."""
        (loop, at_first), (other, at_second) = self.position(first), self.position(second)
        if loop != other:
            return math.inf
        along = abs(at_first - at_second)
        return min(along, float(self.perimeter[loop]) - along)

    def describe(self, point: np.ndarray) -> str:
        """Which loop holds the boundary point: 'the outer boundary' or 'the wall of hole 2'."""
        loop = self.position(point)[0]
        return "the outer boundary" if loop == 0 else f"the wall of hole {loop}"


def needle_geometry(needle: Needle, domain: Rectangle | PolygonDomain) -> NeedleGeometry:
    """Centre on the boundary tangent at the entry (orthogonal entry), desired exit where the
    undeformed circle leaves the tissue for the last time within the needle's arc (the first
    and only time on a convex tissue; README, "Scenario format", "Tissue shapes"). With
    `needle.entry_tilt` the needle leans from there, turned about the entry point (positive:
    against its turn, a deeper bite); its own circle then leaves the tissue elsewhere, while
    the desired exit stays the orthogonal needle's."""
    edges = domain.edges_at(needle.entry)
    entry = np.asarray(needle.entry, dtype=float)
    if not edges:
        raise InputError(f"needle.entry: got {list(needle.entry)}, expected a point on the "
                         f"boundary of the {domain.describe()}; {nearest_note(domain, entry)}")
    # a vertex where the boundary hardly turns (a traced contour's, a circular hole's) has an
    # entry normal: the model treats it as a point inside an edge
    if len(edges) > 1 and not smooth_vertex(domain, entry):
        raise InputError(f"needle.entry: got {list(needle.entry)}, a corner; expected a point "
                         "inside one edge (the entry normal is undefined at a corner)")
    center, edge = circle_center_at_entry(domain, entry, needle.radius, needle.turn)
    sense = -1.0 if needle.turn == "cw" else 1.0
    start_angle, rotation, crossings = _circle_through(needle, domain, entry, center, sense)
    geometry = NeedleGeometry(needle.radius, needle.arc, center, start_angle, sense, needle.step, entry,
                              edge, rotation, entry, crossings)
    geometry = replace(geometry, desired_exit=geometry.tip(rotation))
    if needle.entry_tilt == 0.0:
        return _wounds(_body_outside(geometry, needle, domain), domain)
    lean = f" leaning {needle.entry_tilt:.4g} rad"
    center = entry - needle.radius * unit(start_angle - sense * needle.entry_tilt)  # turned about the entry
    start_angle, rotation, crossings = _circle_through(needle, domain, entry, center, sense, lean)
    leaned = replace(geometry, center=center, start_angle=start_angle, exit_rotation=rotation, crossings=crossings,
                     tilt=needle.entry_tilt,
                     desired_points=tuple(geometry.crossing_point(k) for k in range(len(geometry.crossings))))
    loops = BoundaryLoops.of(domain) if isinstance(domain, PolygonDomain) and domain.holes else None

    def way(circle: NeedleGeometry) -> list:
        """Each crossing's kind and the boundary loop it lies on (the outline or a hole's wall)."""
        return [(kind, 0 if loops is None else loops.position(circle.crossing_point(k))[0])
                for k, (_, kind) in enumerate(circle.crossings)]

    if way(leaned) != way(geometry):
        how = (f"{len(crossings)} times where the orthogonal needle crosses it {len(geometry.crossings)} times"
               if len(crossings) != len(geometry.crossings) else
               "through other walls than the orthogonal needle (a hole's for the outline, or another hole's)")
        raise InputError(
            f"needle.entry_tilt: got {needle.entry_tilt:.4g} rad, which makes the needle cross the boundary {how}; "
            "expected a lean that keeps the needle's way through the tissue (the same gaps and exit)")
    return _wounds(_body_outside(leaned, needle, domain, lean), domain)


def _wounds(geometry: NeedleGeometry, domain: Rectangle | PolygonDomain) -> NeedleGeometry:
    """`geometry` with its `wounds`: the gaps beyond whose middle, outward from the needle's
    centre, the tissue goes on (a wound's far side, a hole's far wall). Across a gap with no
    tissue beyond it (a thin slab's far side, left and entered again) there is no wound to
    stitch: bites measured to its walls would end at the slab's far corners."""
    starts, ends = boundary_edges(domain)
    wounds = []
    for gap in geometry.gaps:
        middle = geometry.tip(0.5 * (gap[0] + gap[1]))
        if ray_meets_edges(starts, ends, middle, middle - geometry.center):
            wounds.append(gap)
    return replace(geometry, wounds=tuple(wounds))


def _field(lean: str) -> str:
    """The field a refused needle geometry names: a lean's own refusal names the lean."""
    return "needle.entry_tilt" if lean else "needle"


# rad between the points of the needle's body checked against the tissue at the start
BODY_SAMPLE = 0.005


def _body_outside(geometry: NeedleGeometry, needle: Needle, domain: Rectangle | PolygonDomain,
                  lean: str = "") -> NeedleGeometry:
    """`geometry`, refused when the needle's body (its arc behind the tip, which the driver
    holds from outside) lies in the tissue when the tip touches the entry: a needle whose tail
    is already in uncut tissue (an arc near a full turn, an entry from within a hole, a lean
    that dips the tail below the surface) is no place a needle can be."""
    rotations = -np.linspace(geometry.arc, 0.0, max(2, math.ceil(geometry.arc / BODY_SAMPLE)), endpoint=False)
    body = geometry.tip(rotations)  # (n, 2)
    inside = domain.contains(body)
    if not inside.any():
        return geometry
    depth = np.zeros(len(body))
    depth[inside] = domain.distance(body[inside])
    if depth.max() > domain.input_tolerance:
        deepest = int(np.argmax(depth))
        raise InputError(
            f"{_field(lean)}: the {needle.radius:g} mm needle entering at {list(needle.entry)} turning "
            f"{needle.turn}{lean} lies in the tissue behind its tip before it enters (at {shown_point(body[deepest])}, "
            f"{-rotations[deepest]:.3g} rad back along its arc of {geometry.arc:.4g} rad); expected its body "
            f"outside the tissue, held from there, with only its tip at the entry (a shorter needle.arc, "
            f"another entry{' or less lean' if lean else ''})")
    return geometry


def _circle_through(needle: Needle, domain: Rectangle | PolygonDomain, entry: np.ndarray, center: np.ndarray,
                    sense: float, lean: str = "") -> tuple[float, float, tuple]:
    """(start angle, rotation at the final exit, crossings) of the needle's circle about
    `center` from `entry`: refused where it leaves no exit within the arc, crosses the
    boundary twice within a step, or exits within two steps."""
    start_angle = math.atan2(*(entry - center)[::-1])
    # an entry kept to the bit within the boundary's round-off (domain.tolerance) turns the exit by
    # up to about that offset over the radius: a half circle on a slanted edge leaves 1e-8 rad past pi;
    # and an arc typed to a few digits (pi as 3.14159) ends within the input tolerance of the exit
    # along the needle, as a typed entry lies within it of the boundary
    slack = 1e-9 + 4.0 * domain.tolerance / needle.radius + domain.input_tolerance / needle.radius
    first = domain.first_exit_rotation(center, needle.radius, start_angle, sense)
    crossings = domain.circle_crossings(center, needle.radius, start_angle, sense, needle.arc + slack)
    exits = [r for r, kind in crossings if kind == "exit"]
    # the last point where the circle leaves the tissue within the arc (the orthogonal needle's:
    # the desired exit); a convex tissue's only exit keeps first_exit_rotation's value
    rotation = exits[-1] if len(exits) > 1 else first
    entering = f"entering at {list(needle.entry)} turning {needle.turn}{lean}"
    field = _field(lean)
    if rotation is None or rotation > needle.arc + slack:
        # the excess too: an entry a hair off a corner leaves a hair past the arc, which 4 digits hide
        reach = ("never leaves the tissue" if rotation is None
                 else f"leaves after {rotation:.4g} rad, {rotation - needle.arc:.2g} rad past its arc")
        raise InputError(f"{field}: the {needle.radius:g} mm needle {entering} {reach}; expected an exit within "
                         f"its arc of {needle.arc:.4g} rad")
    if crossings and crossings[-1][1] == "entry":  # back in the tissue (a wound's far wall) when the arc ends
        entered = crossings[-1][0]
        raise InputError(f"needle.arc: got {needle.arc:.4g} rad; the needle {entering} enters the tissue again after "
                         f"{entered:.4g} rad and does not leave it within its arc; expected an exit within its arc "
                         "(a longer needle.arc, another entry or radius)")
    crossings = (tuple((r, kind) for r, kind in crossings if r <= rotation + 1e-12) if len(exits) > 1
                 else ((rotation, "exit"),))
    if any(b - a < needle.step for (a, ka), (b, kb) in zip(crossings, crossings[1:])):
        raise InputError(
            f"{field}: the needle {entering} crosses the boundary at rotations "
            f"{', '.join(f'{r:.3g}' for r, _ in crossings)} rad, expected crossings at least one step "
            f"({needle.step:g} rad) apart (a gap or a bite shorter than a step: a smaller needle.step, or another "
            "entry or radius)")
    rotation_first = crossings[0][0]
    if rotation_first < 2 * needle.step:
        raise InputError(
            f"{field}: the needle {entering} exits after {rotation_first:.3g} rad, expected at least two steps "
            f"of {needle.step:g} rad inside the tissue")
    return start_angle, rotation, crossings


def orthogonal(scenario: Scenario) -> Scenario:
    """The scenario with its needle entering orthogonally (no needle.entry_tilt)."""
    if scenario.needle is None or scenario.needle.entry_tilt == 0.0:
        return scenario
    return replace(scenario, needle=replace(scenario.needle, entry_tilt=0.0))


def leaning(scenario: Scenario, tilt: float) -> Scenario:
    """The scenario with its needle leaning `tilt` rad from the orthogonal entry."""
    if scenario.needle.entry_tilt == tilt:
        return scenario
    return replace(scenario, needle=replace(scenario.needle, entry_tilt=float(tilt)))


# a centre path's row 0 (needle radii): within ON_CIRCLE of the circle of the needle's radius
# about the entry it leans the needle there (entry_lean), unless it is the needle's own centre
# to as much; an exported trajectory's row 0 lies on that circle to its 1e-9 mm rounding, while
# a centre merely moved off the entry, by d, lies d^2 / 2R off it or more. A trajectory file
# (io/readers.py) may give row 0 within ENTRY_TOLERANCE of the centre at entry (the tip off the
# entry by as much), or within LEAN_TOLERANCE of that circle (written with fewer digits: put
# onto it, on_entry_circle)
ON_CIRCLE = 1e-7
ENTRY_TOLERANCE = 0.01
LEAN_TOLERANCE = 1e-4


def on_entry_circle(geometry: NeedleGeometry, center: np.ndarray, tolerance: float = ON_CIRCLE) -> np.ndarray | None:
    """`center` moved onto the circle of the needle's radius about the entry, when within
    `tolerance` radii of it; else None."""
    arm = np.asarray(center, dtype=float) - geometry.entry
    if abs(length(arm) - geometry.radius) > tolerance * geometry.radius:
        return None
    return geometry.entry + arm * (geometry.radius / length(arm))


def entry_lean(scenario: Scenario, center: np.ndarray) -> Scenario:
    """The scenario whose needle starts about `center` (a centre path's row 0): leaning from
    the orthogonal entry where `center` lies on the circle of the needle's radius about the
    entry (ON_CIRCLE) and is not the scenario's own centre; else the scenario as it is (the
    replay moves the centre to row 0, and the tip with it)."""
    geometry = scenario_needle(scenario)
    center = np.asarray(center, dtype=float)
    if length(center - geometry.center) <= ON_CIRCLE * geometry.radius or on_entry_circle(geometry, center) is None:
        return scenario
    upright = orthogonal(scenario)
    start_angle = math.atan2(*(geometry.entry - center)[::-1])  # as needle_geometry leans it
    tilt = -geometry.sense * math.remainder(start_angle - scenario_needle(upright).start_angle, 2.0 * math.pi)
    if abs(tilt) > MAX_ENTRY_TILT:
        raise InputError(f"centre path: row 0 puts the needle centre at [{center[0]:.6g}, {center[1]:.6g}], leaning "
                         f"the needle {tilt:.4g} rad from the orthogonal entry; expected a lean of at most "
                         f"{MAX_ENTRY_TILT:g} rad")
    return leaning(upright, tilt)


def scenario_needle(scenario: Scenario) -> NeedleGeometry:
    """The needle geometry of a scenario that must have a needle (simulate, plan)."""
    if scenario.needle is None:
        raise InputError("needle: missing, required by simulate, plan and study")
    tissue, entry = scenario.tissue, np.asarray(scenario.needle.entry, dtype=float)
    where = _clamp_at(tissue, entry)
    if where is not None:
        raise InputError(f"needle.entry: got {shown_point_as_given(entry)}, on {where}; expected a point "
                         "on a free edge (a clamp holds the tissue where the needle would enter)")
    geometry = needle_geometry(scenario.needle, scenario.tissue.domain)
    for k, (_, kind) in enumerate(geometry.crossings):
        point = geometry.crossing_point(k)
        where = _clamp_at(tissue, point)
        if where is not None:
            what = "the desired exit" if k == len(geometry.crossings) - 1 else f"its crossing {k + 1} ({kind})"
            raise InputError(
                f"needle: the {scenario.needle.radius:g} mm needle entering at {shown_point_as_given(entry)} "
                f"turning {scenario.needle.turn} {'leaves' if kind == 'exit' else 'enters'} the tissue on "
                f"{where}: {what} {shown_point(point)}; expected the needle's way out on a free edge (a clamp "
                "holds the tissue there: move the entry, turn the other way or change the clamps)")
    return geometry


def _clamp_at(tissue, point: np.ndarray) -> str | None:
    """Which clamp holds the boundary at `point` ("the clamped left edge", "a clamped segment
    of the boundary"), or None."""
    for item, (start, end) in zip(tissue.clamped, tissue.clamped_pieces()):
        along = np.clip((point - start) @ (end - start) / ((end - start) @ (end - start)), 0.0, 1.0)
        if np.linalg.norm(start + along * (end - start) - point) <= 1e-9 * max(tissue.bounding_size):
            return f"the clamped {item} edge" if isinstance(item, str) else "a clamped segment of the boundary"
    return None


# radius (mm) of the refined disks at the needle's entry and exit: 0, points graded like the
# load-segment ends (leaf side growing by 0.5 mm per mm of distance)
NEEDLE_END_RADIUS = 0.0


def needle_end_zones(scenario: Scenario, geometry: NeedleGeometry) -> tuple[RefinementZone, ...]:
    """Refinement zones at the points where the needle's track meets the boundary: the entry
    and every crossing of the undeformed circle (the nominal exit last). The tip with its
    cutting force reaches the free boundary there, a singular point like a load-segment end,
    and the exit error is measured at the exit: the leaf side falls like spacing^2 (one level
    more per halving, tissue.particles.end_spacing) from needle_spacing / 2^needle_end_levels
    at the default spacing; none with discretization.needle_end_levels 0."""
    d = scenario.discretization
    if d.needle_end_levels == 0 or d.needle_spacing is None:
        return ()
    reference = default_spacing_of(scenario.tissue.bounding_size, geometry.radius) * d.needle_spacing / d.spacing
    fine = end_spacing(d.needle_spacing, reference, d.needle_end_levels)
    points = [geometry.entry] + [geometry.crossing_point(k) for k in range(len(geometry.crossings))]
    return tuple(RefinementZone(np.asarray(point, dtype=float), NEEDLE_END_RADIUS, fine)
                 for point in points)


def needle_zone(scenario: Scenario) -> tuple[tuple[float, float], float, tuple[RefinementZone, ...]] | None:
    """(needle centre at entry, needle_zone x radius, zones at the entry and exit) when the
    particles are graded toward the needle, else None: where the tissue model refines. The
    orthogonal needle's, whatever its lean: one model serves every lean the planner tries."""
    if scenario.needle is None or scenario.discretization.needle_spacing is None:
        return None
    scenario = orthogonal(scenario)
    geometry = scenario_needle(scenario)
    return (tuple(geometry.center), scenario.discretization.needle_zone * geometry.radius,
            needle_end_zones(scenario, geometry))
