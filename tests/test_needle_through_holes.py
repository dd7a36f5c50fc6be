"""A needle whose path crosses a hole: the tip leaves the tissue into the hole and enters it
again, a stitch across a wound (README, "Tissue shapes"), followed through every crossing.

Near a circular hole's wall (a 96-gon: every vertex a slightly re-entrant corner) the
visibility criterion makes the displacement jump within hundredths of a mm of the wall, so
the tip's material point at a crossing, root-found on a signed distance that jumps across zero
there, may lie inside the tissue instead of on the wall. The bites then used to find no wall
edge at the crossing and the run ended in a traceback after all its steps
(needle/wound_crossings.py, `stitch_bites`).

Where the tip enters the tissue again is found by carrying the boundary forward with u
(needle/tip_tracking.py, `locate_reentry`). It used to invert x = X + u(X) for the tip in the
hole by a fixed-point iteration, u continued from the nearest wall point: where the tip passes
near the hole's middle the nearest wall point sweeps the wall, the iteration found no point
and the run stopped (a 2 mm hole at the default spacing, at the needle's deepest point).
Tested on a prescribed field (no particles: the old iteration fails on it whatever the model)
and on whole runs. Scenes: 60 x 30 mm block, SH 1/2 needle (r = 8.88 mm) entering the top
edge, coarse spacing and a large step (about a second each).
"""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import scipy.sparse as sp
from conftest import CONFIGS
from test_bad_inputs import OUTPUTS, invoke, write_scene

from stitchplan.config.scenario import load_scenario, parse_scenario
from stitchplan.errors import InsertionFailure
from stitchplan.geometry.polygon_domain import PolygonDomain
from stitchplan.geometry.polygons import circle_polygon
from stitchplan.needle.geometry import scenario_needle
from stitchplan.needle.insertion import run_insertion
from stitchplan.needle.wound_crossings import stitch_bites
from stitchplan.planning.replay_models import aims_at_bites
from stitchplan.needle.tip_tracking import MATERIAL_POINT_TOLERANCE, locate_reentry

PHANTOM = {"model": "neo-hookean", "lame_lambda": 0.189151, "lame_mu": 0.147688}
SIZE = [60.0, 30.0]
ENTRY, FINAL_EXIT = np.array([38.88, 30.0]), np.array([21.12, 30.0])  # the needle's centre: (30, 30)
# the needle's deepest point (30, 21.12) is the hole's centre: the scene that crashed
HOLE = {"circle": {"center": [30.0, 21.12], "radius": 2.0}}


def scene(hole: dict, spacing: float = 4.0, step: float = 0.1) -> dict:
    return {
        "name": "needle through a hole",
        "tissue": {"size": SIZE, "thickness": 10.0, "material": dict(PHANTOM), "holes": [hole],
                   "clamped": ["bottom"]},
        "discretization": {"spacing": spacing},
        "needle": {"radius": 8.88, "entry": ENTRY.tolist(), "turn": "cw", "step": step, "friction": 0.0602,
                   "cutting_force": 0.7},
    }


def needle_rotation(geometry, point: np.ndarray) -> float:
    """The needle rotation at which the undeformed circle passes the polar angle of `point`."""
    angle = math.atan2(point[1] - geometry.center[1], point[0] - geometry.center[0])
    return (angle - geometry.start_angle) * geometry.sense % (2.0 * math.pi)


def check_crossings_and_bites(result) -> None:
    """The crossings in needle order (exit into the hole, entry again, final exit), each near
    the undeformed circle's; the bites finite and deformed by about the tissue's displacement."""
    geometry = result.geometry
    assert [kind for _, kind in geometry.crossings] == ["exit", "entry", "exit"]
    assert [c["kind"] for c in result.crossings] == ["exit", "entry", "exit"]
    achieved = [needle_rotation(geometry, c["achieved"]) for c in result.crossings]
    desired = [rotation for rotation, _ in geometry.crossings]
    assert np.all(np.diff(achieved) > geometry.step)  # in needle order, a gap or a bite apart
    assert np.allclose(achieved, desired, atol=0.05)  # within a tenth of a mm of the circle's
    assert all(math.isfinite(c["error_mm"]) and c["error_mm"] < 1.0 for c in result.crossings)
    assert result.crossings[-1]["error_mm"] == pytest.approx(result.exit_error_mm)
    bites = result.bites
    assert bites is not None
    assert all(np.all(np.isfinite(value)) for value in bites.values())
    assert bites["difference_mm"] == pytest.approx(bites["exit_side_mm"] - bites["entry_side_mm"])
    assert bites["entry_side_at_rest_mm"] == pytest.approx(np.linalg.norm(bites["entry_wound_edge"] - ENTRY))
    final_exit = result.crossings[-1]["achieved"]  # the exit side's bite ends at the achieved exit
    assert bites["exit_side_at_rest_mm"] == pytest.approx(np.linalg.norm(bites["exit_wound_edge"] - final_exit))
    # the tissue moves by tenths of a mm: so do the bites
    assert abs(bites["entry_side_mm"] - bites["entry_side_at_rest_mm"]) < 0.5
    assert abs(bites["exit_side_mm"] - bites["exit_side_at_rest_mm"]) < 0.5


def test_a_needle_across_a_circular_hole_lists_its_crossings_and_bites():
    """The scene that crashed: the tip's material point where it entered the tissue again lay
    inside the tissue, 0.022 mm off the wall, more than the old edge search's tolerance; the
    run returns its result, with the wound edges at the walls the tip crossed. The re-entry
    is now found on the wall itself; the exit into the hole may still lie off it by u's jump."""
    scenario = parse_scenario(scene(HOLE))
    result = run_insertion(scenario)
    domain = scenario.tissue.domain
    off_wall = [float(domain.distance(c["achieved"])) for c in result.crossings[:2]]
    assert off_wall[1] < 1e-9  # a point of the wall's 96-gon (to round-off)
    assert max(off_wall) < 0.1  # next to the wall: the jump, not a lost point
    check_crossings_and_bites(result)
    # each wound edge: the point of the hole's 96-gon nearest its crossing
    for edge, crossing, off in zip(("entry_wound_edge", "exit_wound_edge"), result.crossings, off_wall):
        assert float(domain.distance(result.bites[edge])) < 1e-9
        assert np.linalg.norm(result.bites[edge] - crossing["achieved"]) == pytest.approx(off, abs=1e-9)
    # the hole is centred on the needle's deepest point: the bites match at rest within a
    # chord and the crossings' deviations
    assert result.bites["entry_side_at_rest_mm"] == pytest.approx(result.bites["exit_side_at_rest_mm"], abs=0.2)


def test_simulate_across_a_circular_hole_writes_its_summary(tmp_path):
    """`simulate` ends with exit 0 and a summary listing the three crossings and the bites
    (it used to end with a traceback and exit 1 after the whole run)."""
    write_scene(tmp_path, scene(HOLE))
    run = invoke(tmp_path, "simulate", "scene.yaml", *OUTPUTS["simulate"], "--no-estimate")
    assert run.exit_code == 0, run.output
    assert "Traceback" not in run.output
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert [c["kind"] for c in summary["crossings"]] == ["exit", "entry", "exit"]
    assert all(math.isfinite(c["error_mm"]) for c in summary["crossings"])
    assert all(math.isfinite(summary["bites"][key]) for key in ("entry_side_mm", "exit_side_mm", "difference_mm"))
    assert (tmp_path / "run.h5").exists()


@pytest.mark.parametrize("off", [0.0, 0.01, 0.05])
def test_the_wound_edge_of_a_crossing_off_a_holes_wall_is_the_nearest_wall_point(off):
    """stitch_bites on a still tissue (u = 0): wall crossings on the hole's 96-gon or `off` mm
    inside the tissue find the point of the wall they lie nearest (only crossings on the wall,
    off = 0, passed once; then the wound edge was the end of that edge nearer the entry or the
    final exit, a vertex that moved by a chord between two models of the same stitch)."""
    center, radius = np.array([30.0, 21.12]), 2.0
    hole = circle_polygon(center, radius)
    domain = PolygonDomain.rectangle(SIZE, holes=(hole,))
    insertion = SimpleNamespace(domain=domain, geometry=SimpleNamespace(entry=ENTRY, wound_walls={0, 1}),
                                displacement=lambda points: np.zeros_like(np.atleast_2d(points)))
    walls = []
    for k, t in ((8, 0.3), (44, 0.6)):  # on edges 8 and 44 of the 96-gon, moved off into the tissue
        on_edge = hole[k] + t * (hole[k + 1] - hole[k])
        walls.append(on_edge + off * (on_edge - center) / np.linalg.norm(on_edge - center))
    crossings = [{"achieved": walls[0]}, {"achieved": walls[1]}, {"achieved": FINAL_EXIT}]
    bites = stitch_bites(insertion, crossings)
    # each crossing's foot on its edge (moved off along the radius, not the edge's normal)
    expected = [hole[k] + np.dot(wall - hole[k], hole[k + 1] - hole[k]) / np.sum((hole[k + 1] - hole[k]) ** 2)
                * (hole[k + 1] - hole[k]) for k, wall in zip((8, 44), walls)]
    assert np.allclose(bites["entry_wound_edge"], expected[0]) and np.allclose(bites["exit_wound_edge"], expected[1])
    assert bites["entry_side_mm"] == pytest.approx(np.linalg.norm(expected[0] - ENTRY))
    assert bites["exit_side_mm"] == pytest.approx(np.linalg.norm(expected[1] - FINAL_EXIT))


@pytest.mark.parametrize("hole, spacing, step", [
    ({"circle": {"center": [25.0, 22.5], "radius": 2.0}}, 2.5, 0.1),
    ({"circle": {"center": [30.0, 22.0], "radius": 2.0}}, 3.5, 0.12),
    ({"polygon": [[28.0, 19.5], [32.0, 19.5], [32.0, 22.5], [28.0, 22.5]]}, 4.0, 0.1),
], ids=["circle-left-of-the-deepest-point", "circle-below", "square"])
def test_holes_on_the_path_that_ran_before_still_run(hole, spacing, step):
    """Holes on the needle's path that ran before the fix: same crossings, finite bites."""
    check_crossings_and_bites(run_insertion(parse_scenario(scene(hole, spacing, step))))


# --- where the tip enters the tissue again ----------------------------------------------------

# Coarse scenes: the hole, the spacing and the step, and the converged crossings (deformed,
# mm: exit into the hole, entry into its far wall, final exit) from runs at spacing 0.5 mm (~7300
# particles). Two particle placements on the hole's wall (with and without a particle at every
# vertex of its 96-gon) agree on those to 0.015 mm.
COARSE_SCENES = {
    "needle-near-the-hole-middle": ({"circle": {"center": [27.032, 21.313], "radius": 3.0}}, 2.0, 0.1,
                                    [[29.83, 21.11], [24.23, 23.28], [21.129, 30.408]]),
    "circle-left-of-the-deepest-point": ({"circle": {"center": [25.0, 22.5], "radius": 2.0}}, 3.0, 0.1,
                                         [[26.645, 21.761], [23.305, 24.176], [21.127, 30.362]]),
    "circle-below": ({"circle": {"center": [30.0, 22.0], "radius": 2.0}}, 4.0, 0.15,
                     [[31.794, 21.300], [27.728, 21.415], [21.124, 30.270]]),
}


@pytest.mark.parametrize("name", COARSE_SCENES)
def test_a_coarse_needle_across_a_hole_crosses_where_the_converged_one_does(name):
    """Every crossing of a coarse run lies within a tenth of the spacing of the converged one,
    the displacement's resolution at the wall (MATERIAL_POINT_TOLERANCE, what a re-entry may
    miss the tip by): the errors met were 0.37-0.78 of it (largest 0.23 mm, the re-entry at
    spacing 3) on both particle placements. The first scene's needle passes 0.1 mm from the
    hole's middle: the re-entry's fixed-point iteration stopped it at step 17 ("no material
    point maps to the tip at (28.86, 21.2) mm") on both; the other two stopped it on the
    placement with a particle at every vertex of the wall."""
    hole, spacing, step, converged = COARSE_SCENES[name]
    result = run_insertion(parse_scenario(scene(hole, spacing, step)))
    check_crossings_and_bites(result)
    achieved = np.array([crossing["achieved_def"] for crossing in result.crossings])
    assert np.linalg.norm(achieved - converged, axis=1).max() < MATERIAL_POINT_TOLERANCE * spacing
    re_entry = result.crossings[1]["achieved"]
    assert float(result.scenario.tissue.domain.distance(re_entry)) < 1e-9  # on the far wall


TURN = np.array([[0.0, -1.0], [1.0, 0.0]])  # 90 degrees anticlockwise


class TurnedHole:
    """A prescribed displacement about a hole: u(X) = a J (X - c) + b, the tissue turned by a
    small angle a about the hole's centre c and moved by b (affine: the 96-gon's edges stay
    straight, so its crossings with the needle are exact), plus `jump` (wall angles from, to
    and the jump (2,)): u jumps by it on the wall between those polar angles about c. Stands in
    for the tissue model (`free_rows_at`, a weak-referable model) and its coefficients."""

    def __init__(self, turn: float, shift, jump: tuple | None = None):
        self.center = np.array(HOLE["circle"]["center"])
        self.gradient, self.shift, self.jump = turn * TURN, np.asarray(shift, dtype=float), jump

    def columns(self, points: np.ndarray) -> np.ndarray:
        """(n, 3 or 4): X - c, 1 and, with a jump, 1 on the jump's sector."""
        points = np.atleast_2d(points)
        columns = [points - self.center, np.ones((len(points), 1))]
        if self.jump is not None:
            angle = np.arctan2(*(points - self.center).T[::-1])
            columns.append(((angle > self.jump[0]) & (angle < self.jump[1]))[:, None].astype(float))
        return np.hstack(columns)

    def coefficients(self) -> np.ndarray:
        jump = [] if self.jump is None else [np.asarray(self.jump[2])[None]]
        return np.vstack([self.gradient.T, self.shift[None]] + jump)

    def free_rows_at(self, points: np.ndarray) -> sp.csr_matrix:
        return sp.csr_matrix(self.columns(points))


def insertion_in(field: TurnedHole, spacing: float = 1.0) -> SimpleNamespace:
    """What locate_reentry asks of a NeedleInsertion, on the needle scene with the 2 mm hole at
    its deepest point and the prescribed displacement (continued outside the tissue by its
    value at the nearest tissue point, as NeedleInsertion.displacement)."""
    scenario = parse_scenario(scene(HOLE))
    geometry, domain = scenario_needle(scenario), scenario.tissue.domain

    def displacement(points, gradient=False):
        u = field.columns(domain.clip(np.atleast_2d(points))) @ field.coefficients()
        return (u, np.broadcast_to(field.gradient, (len(u), 2, 2))) if gradient else u

    return SimpleNamespace(domain=domain, geometry=geometry, center=geometry.center.copy(), model=field,
                           free=field.coefficients(), displacement=displacement, timings={"tip_tracking": 0.0},
                           coupling=SimpleNamespace(local_spacing=lambda p: np.full(len(np.atleast_2d(p)), spacing)),
                           tissue=SimpleNamespace(boundary_samples=None))  # its PreparedTissue's cache


def far_wall_crossing(insertion: SimpleNamespace, field: TurnedHole) -> tuple[float, np.ndarray]:
    """Where the needle's circle crosses the far wall of the moved hole (the moved 96-gon's
    edges against the circle, quadratic roots): the rotation there and the wall point at rest."""
    geometry, hole = insertion.geometry, insertion.domain.holes[0]
    moved = hole + (hole - field.center) @ field.gradient.T + field.shift
    crossings = []
    for a, b in zip(moved, np.roll(moved, -1, axis=0)):
        e, f = b - a, a - geometry.center
        qa, qb, qc = e @ e, f @ e, f @ f - geometry.radius**2
        if qb * qb - qa * qc < 0.0:
            continue
        for s in np.array([-1.0, 1.0]) * math.sqrt(qb * qb - qa * qc) / qa - qb / qa:
            if 0.0 <= s <= 1.0:
                x = a + s * e
                at_rest = field.center + np.linalg.solve(np.eye(2) + field.gradient, x - field.shift - field.center)
                crossings.append((needle_rotation(geometry, x), at_rest))
    return max(crossings, key=lambda crossing: crossing[0])  # the later one: the far wall


def test_the_tip_entering_a_hole_s_far_wall_is_found_on_the_wall_where_no_point_maps_to_it():
    """The tissue about the hole turned by 0.1 rad and moved 0.3 mm along the needle: the
    needle passes through the moved hole's middle, where no material point maps to the tip (the
    old fixed-point iteration cycled about the middle and stopped the run, missing the tip by
    r a sqrt 2 = 0.28 mm). Still in the gap there and every needle step on; the step the tip
    enters the far wall gives the wall point whose moved position the needle's circle passes,
    and the rotation there, to round-off (Brent's method along the wall, 1e-13); a tip already
    in the wall enters at its material point."""
    field = TurnedHole(0.1, [-0.3, 0.0])
    insertion = insertion_in(field)
    geometry = insertion.geometry
    rotation, point = far_wall_crossing(insertion, field)
    through_middle = needle_rotation(geometry, field.center + field.shift)
    assert geometry.crossings[0][0] < through_middle < rotation < geometry.crossings[2][0]
    start = through_middle - geometry.step
    while start + geometry.step < rotation:
        assert locate_reentry(insertion, start, start + geometry.step) is None
        start += geometry.step
    entered, at = locate_reentry(insertion, start, start + geometry.step)
    assert np.linalg.norm(entered - point) < 1e-9 and at == pytest.approx(rotation, abs=1e-9)
    # a tip already in the wall at the window's start (the wall moved over it) enters there, at
    # its material point
    start = rotation + 0.01
    entered, at = locate_reentry(insertion, start, start + geometry.step)
    assert at == start and insertion.domain.outside_distance(entered) < 0.0
    tip = geometry.tip(start, insertion.center)
    assert np.linalg.norm(entered + insertion.displacement(entered)[0] - tip) < 1e-9


def test_a_far_wall_whose_displacement_jumps_across_the_needle_stops_the_run_naming_it():
    """u jumps by 0.5 mm on the far wall a little before the point the needle would enter, out
    of the needle's circle: the moved wall steps across the circle without meeting it, 0.2 mm
    off on the near side, more than a tenth of the spacing. No wall point is taken there; the
    failure names the rotations and the wall point and asks for a finer spacing."""
    smooth = TurnedHole(0.1, [-0.3, 0.0])
    insertion = insertion_in(smooth)
    rotation, point = far_wall_crossing(insertion, smooth)
    wall_angle = math.atan2(*(point - smooth.center)[::-1])
    moved = point + insertion.displacement(point)[0]
    outward = (moved - insertion.center) / np.linalg.norm(moved - insertion.center)
    insertion = insertion_in(TurnedHole(0.1, [-0.3, 0.0], (wall_angle - 0.1, wall_angle + 0.1, 0.5 * outward)))
    step = insertion.geometry.step
    with pytest.raises(InsertionFailure, match=r"re-entry of the tip between needle rotations .* the deformed wall "
                                               r"jumps across the needle by 0\.2 mm at the wall point .* refine the "
                                               r"spacing"):
        locate_reentry(insertion, rotation - 0.5 * step, rotation + 0.5 * step)


def test_a_track_point_tracked_into_a_hole_fails_its_step_by_name():
    """A track point that no particle's kernel covers (a tip tracked past a wall the deformed
    tissue had moved, into a hole at rest) fails its step naming the step, the point, how far
    outside the tissue it lies and why; it used to end in the shape functions' 'covered by 0
    particles ... refine the spacing', no step named. (A soft slab whose round hole's wall
    bulged round the tip reached this; with the hole tested only for pairs that can reach
    across it, points just inside it are covered and that slab fails later, naming the wall
    the tip came back through.)"""
    from stitchplan.needle.insertion import _add_point
    from stitchplan.tissue.shape_functions import SingularMomentAt

    domain = PolygonDomain.rectangle((100.0, 40.0), (circle_polygon([50.0, 30.0], 2.5),))
    inside = np.array([50.53, 32.43])  # 0.0115 mm inside the hole's wall

    def add_point(point, **options):
        raise SingularMomentAt("moment matrix M(X) is singular at (50.53, 32.43) mm: covered by 0 particles",
                               inside)

    insertion = SimpleNamespace(domain=domain, add_point=add_point)
    with pytest.raises(InsertionFailure, match=r"^step 11 \(needle rotation 1\.540 rad\): the needle's track "
                                               r"reaches \[50\.53, 32\.43\], 0\.01\d\d mm outside the tissue at "
                                               r"rest \(in a hole or a gap\), where no particle's kernel reaches"):
        _add_point(insertion, 11, 1.54, inside)


# --- equal bites through a hole ---------------------------------------------------------------

def symmetric_scene(max_passes: int) -> dict:
    """The hole centred on the needle's deepest point, the block pulled at its right edge (as
    configs/hole_near_stitch.yaml is): planner.target symmetric."""
    raw = scene(HOLE)
    raw["loads"] = [{"segment": [[60.0, 0.0], [60.0, 30.0]], "force": [2.0, 0.0]}]
    raw["planner"] = {"target": "symmetric", "max_passes": max_passes}
    return raw


def passes_missed(result) -> list[float]:
    return [float(np.linalg.norm(p["exit_error_vector_mm"] - p["aim_mm"])) for p in result.passes]


def test_a_symmetric_plan_through_a_hole_closes_in_on_equal_bites():
    """Through a hole the bites end at the wall points the needle crosses, which move with it:
    the bites' difference moves faster than the exit error's secant says, and the passes used
    to overshoot equal bites further each time (misses of their aim 0.302, 0.0248, 0.0452,
    0.0725 mm; the best 0.0248 mm apart). Once a pass falls on the other side of equal bites
    the secant takes the bites' difference, and the next pass closes in."""
    from stitchplan.planning.planner import run_plan

    result = run_plan(parse_scenario(symmetric_scene(4)), compare=False)
    misses = passes_missed(result)
    assert misses[-1] < min(misses[:-1])
    assert abs(result.planned.bites["difference_mm"]) <= result.planned.scenario.planner.exit_tolerance


def test_a_symmetric_plan_short_of_equal_bites_says_what_its_passes_did():
    """Two passes, still closing in on equal bites: the target-missed note says that
    planner.max_passes ran out, with each pass's miss, and no longer blames move limits the
    passes never reached ('the centre could not be moved far enough')."""
    from stitchplan.events import EventKind
    from stitchplan.planning.verification import plan_verified

    result = plan_verified(parse_scenario(symmetric_scene(2)), compare=False, verify=False)
    notes = [event.message for event in result.planned.events if event.kind == EventKind.TARGET_MISSED]
    first, second = passes_missed(result)
    assert second < first
    assert len(notes) == 1 and notes[0].endswith(
        f"planner.max_passes (2) ran out with the passes still closing in (they missed their aim by {first:.3g}, "
        f"{second:.3g} mm)")
    assert "could not be moved" not in notes[0]


def test_a_needle_through_the_far_side_of_a_thin_slab_runs_as_on_the_same_outline():
    """A 6 mm slab given by `size`, the needle leaving through its bottom and coming back in
    (the undeformed circle reaches 2.88 mm below it): the crossings' walls are asked of the
    rectangle as of a polygon, which it could not answer (AttributeError after the whole run).
    The rectangle now gives the crossings of the same slab drawn as an outline. The gap is the
    outside beyond the slab's far side, no wound: neither has bites (they were measured to the
    slab's bottom corners, 16 mm apart), and a symmetric target aims at the exit."""
    def thin(tissue_shape: dict) -> dict:
        return {"tissue": {**tissue_shape, "thickness": 10.0, "material": dict(PHANTOM), "clamped": ["left", "right"]},
                "discretization": {"spacing": 2.0},
                "needle": {"radius": 8.88, "entry": [30.0, 6.0], "turn": "cw", "step": 0.1, "friction": 0.0602,
                           "cutting_force": 0.1, "cutting_ramp": True}}

    by_size = run_insertion(parse_scenario(thin({"size": [60.0, 6.0]})))
    by_outline = run_insertion(parse_scenario(thin({"outline": [[0, 0], [60, 0], [60, 6], [0, 6]]})))
    assert [c["kind"] for c in by_size.crossings] == ["exit", "entry", "exit"]
    for ours, theirs in zip(by_size.crossings, by_outline.crossings):
        assert np.allclose(ours["achieved_def"], theirs["achieved_def"], rtol=0.0, atol=1e-9)
    assert by_size.bites is None and by_outline.bites is None
    symmetric = parse_scenario({**thin({"size": [60.0, 6.0]}), "planner": {"target": "symmetric"}})
    assert len(scenario_needle(symmetric).gaps) == 1 and scenario_needle(symmetric).wounds == ()
    assert not aims_at_bites(symmetric)
    from stitchplan.events import EventKind
    from stitchplan.planning.planner import run_plan

    notes = [event.message for event in run_plan(symmetric, compare=False).planned.events
             if event.kind == EventKind.TARGET_NOT_APPLICABLE]
    assert len(notes) == 1 and notes[0].endswith("(the gap it crosses lies beyond the tissue's far side: no tissue "
                                                 "across it to stitch)")


def test_a_wound_and_a_hole_are_wounds_to_the_needle():
    """Tissue lies beyond the needle across a wound's gap and a hole: both are stitched across."""
    for scenario in (load_scenario(CONFIGS / "wound_closure_symmetric.yaml"), parse_scenario(scene(HOLE))):
        geometry = scenario_needle(scenario)
        assert len(geometry.gaps) == 1 and geometry.wounds == tuple(geometry.gaps)
