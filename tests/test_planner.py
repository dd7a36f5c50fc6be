"""The deformation-compensating planner (thesis Algorithm 2, eq. 4.1-4.2) as a library:

- on generated scenes (other entry edges, both turn directions, other clamped edges, block
  sizes and materials) the planned exit error is below 0.05 mm and below 5 % of the
  unplanned one, while the unplanned error is large enough for that to mean something;
- within a step the centre satisfies the fixed point O = O(t0) - c + u(X_exit) (Algorithm 2's update) to
  the planner tolerance wherever no eq. 4.2 event was recorded;
- the passes follow the documented shooting update (a secant along the exit edge, started
  at de/dc = -1) and the best pass is returned;
- the trajectory table and its base frame against independent computations.

Scenes are small (at most 50 x 40 mm, 3.5-5 mm spacing, 0.16-0.3 rad steps): a few seconds each.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from stitchplan.config.scenario import Robot, parse_scenario
from stitchplan.events import EventKind
from stitchplan.needle.insertion import run_insertion
from stitchplan.planning.move_limits import REFERENCE_STEP
from stitchplan.planning.pass_offsets import REAIM_FRACTION
from stitchplan.planning.planner import ExitTracker, final_mismatch, run_plan
from stitchplan.planning.trajectory import to_base_frame, trajectory_table

from conftest import TIGHT_NEEDLE_NEWTON

RADIUS = 8.88


def scene(size, entry, turn, clamped, spacing=4.0, step=0.16, material=None, planner=None) -> dict:
    raw = {"tissue": {"size": list(size), "thickness": 10.0, "clamped": list(clamped),
                      "material": material or {"lame_lambda": 0.189151, "lame_mu": 0.147688}},
           "discretization": {"spacing": spacing},
           "needle": {"radius": RADIUS, "entry": list(entry), "turn": turn, "step": step,
                      "friction": 0.0602, "cutting_force": 0.7}}
    if planner is not None:
        raw["planner"] = planner
    return raw


# name: (raw scenario, desired exit expected from the geometry (entry +- 2 R along the entry
# edge), axis of the coordinate that is fixed on that edge)
SCENES = {
    # bottom edge, counter-clockwise (centre at entry - (R, 0)), clamped at the top
    "bottom-ccw-clamped-top-50x30": (scene((50.0, 30.0), (30.0, 0.0), "ccw", ["top"]),
                                     (30.0 - 2 * RADIUS, 0.0), 1),
    # top edge, clockwise (centre at entry - (R, 0)), clamped at the bottom, 3.6 mm spacing
    "top-cw-clamped-bottom-36x36": (scene((36.0, 36.0), (25.0, 36.0), "cw", ["bottom"], spacing=3.6),
                                    (25.0 - 2 * RADIUS, 36.0), 1),
    # right edge, counter-clockwise (centre at entry - (0, R)), clamped at the left, softer
    # neo-Hookean material (mu 0.1 MPa)
    "right-ccw-clamped-left-neo-hookean-40x40": (
        scene((40.0, 40.0), (40.0, 25.0), "ccw", ["left"],
              material={"model": "neo-hookean", "lame_lambda": 0.189151, "lame_mu": 0.1}),
        (40.0, 25.0 - 2 * RADIUS), 0),
}


@pytest.mark.parametrize("name", list(SCENES))
def test_planner_brings_the_tip_out_at_the_desired_exit(name):
    raw, desired, edge_axis = SCENES[name]
    result = run_plan(parse_scenario(raw))
    planned, unplanned = result.planned, result.unplanned
    np.testing.assert_allclose(planned.desired_exit, desired, atol=1e-9)
    # the unplanned needle keeps its entry centre; its exit misses by a meaningful amount
    np.testing.assert_array_equal([s.center for s in unplanned.steps],
                                  np.tile(unplanned.geometry.center, (len(unplanned.steps), 1)))
    assert unplanned.exit_error_mm > 0.05, unplanned.exit_error_mm
    figures = f"{name}: planned {planned.exit_error_mm:.5f} mm, unplanned {unplanned.exit_error_mm:.4f} mm"
    assert planned.exit_error_mm < 0.05, figures
    assert planned.exit_error_mm < 0.05 * unplanned.exit_error_mm, figures
    # the planned tip leaves through the edge of the desired exit, the centre was moved
    assert planned.achieved_exit[edge_axis] == pytest.approx(desired[edge_axis], abs=1e-9)
    assert np.ptp(result.center_trajectory, axis=0).max() > 0.05


@pytest.fixture(scope="module")
def two_passes():
    """The 20 x 20 mm scene planned without the comparison run, forced through two passes
    (exit_tolerance far below reach)."""
    raw = scene((20.0, 20.0), (0.0, 18.0), "cw", ["right"], spacing=5.0, step=0.3,
                planner={"exit_tolerance": 1e-9, "max_passes": 2})
    raw["solver"] = TIGHT_NEEDLE_NEWTON  # a pass alone is compared with the same pass in sequence
    return run_plan(parse_scenario(raw), compare=False)


def test_a_symmetric_target_on_a_needle_crossing_no_wound_aims_at_the_exit_and_says_so():
    """planner.target symmetric means equal bites across a wound; on a needle that crosses
    none the plan aims at the exit, as with the target `exit`, and a note says so."""
    raw = scene((20.0, 20.0), (0.0, 18.0), "cw", ["right"], spacing=5.0, step=0.3)
    symmetric = run_plan(parse_scenario({**raw, "planner": {"target": "symmetric"}}), compare=False)
    at_exit = run_plan(parse_scenario(raw), compare=False)
    np.testing.assert_array_equal(symmetric.center_trajectory, at_exit.center_trajectory)
    notes = [event for event in symmetric.planned.events if event.kind == EventKind.TARGET_NOT_APPLICABLE]
    assert len(notes) == 1 and "crosses no wound or hole: the plan aims at the desired exit" in notes[0].message
    assert not [event for event in at_exit.planned.events if event.kind == EventKind.TARGET_NOT_APPLICABLE]


def test_passes_come_from_the_scenario_planner(two_passes):
    assert two_passes.unplanned is None
    assert [p["pass"] for p in two_passes.passes] == [1, 2]  # max_passes from the scenario


def test_passes_follow_the_shooting_update_and_the_best_is_kept(two_passes):
    first, second = two_passes.passes
    np.testing.assert_array_equal(first["offset_mm"], [0.0, 0.0])  # c_1 = 0
    # c_2 = c_1 + e_1 (de/dc = -1 along the exit edge before any secant information)
    np.testing.assert_allclose(second["offset_mm"], first["exit_error_vector_mm"], rtol=1e-12)
    assert two_passes.planned.exit_error_mm == min(first["exit_error_mm"], second["exit_error_mm"])
    assert second["exit_error_mm"] < first["exit_error_mm"]  # pre-compensating the drift helps
    np.testing.assert_allclose(final_mismatch(two_passes.planned),
                               [p for p in two_passes.passes
                                if p["exit_error_mm"] == two_passes.planned.exit_error_mm][0]["final_mismatch_mm"])


def test_a_pass_depends_on_its_offset_alone(two_passes):
    """The secant over the passes needs e(c): the second pass run on its own, with its offset,
    the first pass's prefix and a model of its own (its prefix steps then solved, not
    replayed), ends where it ended after the first, to the Newton tolerance."""
    second = two_passes.passes[1]
    scenario = two_passes.planned.scenario
    prefix = two_passes.shooting.prefix
    assert second["first_aimed_step"] == prefix.first_aimed > 1
    alone = run_insertion(scenario, control=ExitTracker(scenario.planner, second["offset_mm"], prefix=prefix))
    assert alone.exit_error_mm == pytest.approx(second["exit_error_mm"], abs=1e-7)


def test_later_passes_take_the_first_pass_over_up_to_the_offset(two_passes):
    """PassPrefix: a later pass keeps the first pass's centres before its first aimed step,
    with the first pass's equilibria (no Newton iteration of its own there), and counts the
    first pass's work for those steps; its own iterations are those of the steps it solved."""
    first, second = two_passes.passes
    prefix = two_passes.shooting.prefix
    reference, kept = prefix.reference.steps, two_passes.planned.steps
    taken = prefix.first_aimed - 1
    np.testing.assert_array_equal([s.center for s in kept[:taken]], [s.center for s in reference[:taken]])
    assert [s.newton_iterations for s in kept[:taken]] == [s.newton_iterations for s in reference[:taken]]
    assert [s.planner_iterations for s in kept[:taken]] == [s.planner_iterations for s in reference[:taken]]
    assert [s.equilibrium_solves for s in kept[:taken]] == [s.equilibrium_solves for s in reference[:taken]]
    assert second["newton_iterations"] == sum(s.newton_iterations for s in kept[taken:])
    assert second["newton_iterations"] < first["newton_iterations"]
    assert not np.allclose(kept[taken].center, reference[taken].center, atol=1e-9, rtol=0)  # the offset acts


def test_a_later_pass_takes_the_first_passs_equilibria_over_its_prefix(two_passes):
    """The prefix steps' states are the first pass's to the last bit: taken over, not solved
    again from the first pass's states (which would move them by round-off)."""
    prefix = two_passes.shooting.prefix
    taken = prefix.first_aimed - 1
    kept, reference = two_passes.planned.states[:taken], prefix.reference.states[:taken]
    assert len(kept) == len(reference) == taken
    for mine, first in zip(kept, reference):
        np.testing.assert_array_equal(mine.free, first.free)
        np.testing.assert_array_equal(mine.multipliers, first.multipliers)


def test_a_later_pass_takes_the_first_passs_tip_points_over_its_prefix(monkeypatch):
    """The steps a later pass takes over are replayed about the first pass's centres from its
    states, so their tip points are the first pass's (not tracked again)."""
    import stitchplan.needle.insertion as insertion

    tracked = []  # (pass, step) of every tracking

    def counted(state, step, *args, **kwargs):
        tracked.append(step)
        return track_step(state, step, *args, **kwargs)

    track_step = insertion.track_step
    monkeypatch.setattr(insertion, "track_step", counted)
    raw = scene((20.0, 20.0), (0.0, 18.0), "cw", ["right"], spacing=5.0, step=0.3,
                planner={"exit_tolerance": 1e-9, "max_passes": 2})
    plan = run_plan(parse_scenario(raw), compare=False)
    first_aimed, steps = plan.shooting.prefix.first_aimed, len(plan.planned.steps)
    assert first_aimed > 2
    # the first pass tracks every step and its exit; the second from its first aimed step on
    assert tracked == [*range(1, steps + 2), *range(first_aimed, steps + 2)]
    reference = plan.shooting.prefix.reference.steps
    np.testing.assert_array_equal([s.tip_reference for s in plan.planned.steps[:first_aimed - 1]],
                                  [s.tip_reference for s in reference[:first_aimed - 1]])


def test_a_large_offset_acts_from_the_first_step(two_passes):
    """An offset beyond PassPrefix.largest_offset (a fraction of the second-difference limit)
    would enter late as a jump the move limits hold back: such a pass runs every step."""
    prefix = two_passes.shooting.prefix
    scale = two_passes.planned.geometry.step / REFERENCE_STEP
    assert prefix.largest_offset == pytest.approx(
        REAIM_FRACTION * two_passes.planned.scenario.planner.center_second_difference_limit * scale)
    assert prefix.for_offset(np.array([0.0, prefix.largest_offset])) is prefix
    assert prefix.for_offset(np.array([0.0, 1.01 * prefix.largest_offset])) is None


def test_centre_solves_the_fixed_point_of_eq_4_1_also_where_eq_4_2_fails(two_passes):
    """The centre is a Newton unknown of each step's solve, so every step that no move limit
    held back ends on the fixed point of Algorithm 2's update, also where the exit point follows the
    centre nearly one for one (the thesis's plain update stalls there)."""
    planned = two_passes.planned
    best = [p for p in two_passes.passes if p["exit_error_mm"] == planned.exit_error_mm][0]
    flagged = {e.step for e in planned.events if e.step is not None} | set(best["limited_steps"])
    trajectory = two_passes.center_trajectory
    assert trajectory.shape == (len(planned.steps) + 1, 2)
    np.testing.assert_array_equal(trajectory[0], planned.geometry.center)
    np.testing.assert_allclose(planned.geometry.center, [0.0, 18.0 - RADIUS], atol=1e-12)
    checked, hard = 0, 0
    for record in planned.steps:
        if record.step in flagged:
            continue
        offset = best["offset_mm"] if record.step >= best["first_aimed_step"] else 0.0  # PassPrefix
        mismatch = planned.geometry.center - offset + record.exit_displacement - record.center
        assert np.linalg.norm(mismatch) <= planned.scenario.planner.tolerance, (record.step, mismatch)
        checked += 1
        hard += record.eq42_ratio >= 0.8
    assert checked >= len(planned.steps) // 2 and hard >= 1


def test_centre_unknown_settles_each_step_in_one_solve():
    """With the centre an unknown of the step's Newton solve, a planned step costs one
    equilibrium solve and a few more Newton iterations than the unplanned step, not a solve
    per centre try (one pass on the 40 x 40 mm scene, move limits off)."""
    scenario = parse_scenario(scene((40.0, 40.0), (0.0, 28.0), "cw", ["right"]))
    planned = run_insertion(scenario, control=ExitTracker(scenario.planner, smooth=False))
    unplanned = run_insertion(scenario)
    # one solve per step (the last, where the exit follows the centre, may need the load ramp)
    assert sum(s.equilibrium_solves == 1 for s in planned.steps) >= len(planned.steps) - 1
    assert sum(s.planner_iterations for s in planned.steps) >= len(planned.steps)  # the centre did move
    newton = {name: sum(s.newton_iterations for s in run.steps) for name, run in
              (("planned", planned), ("unplanned", unplanned))}
    # ~2 more a step (40 over 19 steps); a solve per centre try would add ~3 per try (51 tries)
    assert newton["planned"] - newton["unplanned"] <= 3 * len(planned.steps), newton


def test_trajectory_table_columns_and_frames(two_passes):
    planned = two_passes.planned
    n = len(planned.steps)
    columns, table = trajectory_table(planned, Robot())
    assert columns == ["step", "angle_rad", "center_x_mm", "center_y_mm", "tip_x_mm", "tip_y_mm"]
    assert table.shape == (n + 2, 6)
    np.testing.assert_array_equal(table[:, 0], np.arange(n + 2))
    np.testing.assert_allclose(table[:, 1], 0.3 * np.arange(n + 2), atol=1e-12)
    np.testing.assert_allclose(table[1:n + 1, 2:4], [s.center for s in planned.steps], atol=1e-9)  # rounded
    columns, timed = trajectory_table(planned, Robot(angular_speed=4.0))  # timestamps only
    assert columns[-1] == "time_s" and len(columns) == 7
    np.testing.assert_allclose(timed[:, -1], table[:, 1] / 4.0)
    columns, based = trajectory_table(planned, Robot(rotation_deg=-90.0, translation=(1.0, 2.0), given=True))
    assert columns[6:] == ["base_center_x_mm", "base_center_y_mm", "base_tip_x_mm", "base_tip_y_mm"]
    # rotation by -90 deg maps (x, y) to (y, -x)
    np.testing.assert_allclose(based[:, 6], table[:, 3] + 1.0, atol=1e-12)
    np.testing.assert_allclose(based[:, 7], -table[:, 2] + 2.0, atol=1e-12)
    np.testing.assert_allclose(based[:, 8], table[:, 5] + 1.0, atol=1e-12)
    np.testing.assert_allclose(based[:, 9], -table[:, 4] + 2.0, atol=1e-12)


def test_base_frame_is_a_rigid_motion(rng):
    points = rng.uniform(-50.0, 50.0, size=(20, 2))
    np.testing.assert_allclose(to_base_frame(points, Robot(90.0, (3.0, -4.0), given=True)),
                               np.column_stack([-points[:, 1] + 3.0, points[:, 0] - 4.0]), atol=1e-12)
    np.testing.assert_allclose(to_base_frame(points, Robot(360.0, (0.0, 0.0), given=True)), points, atol=1e-12)
    moved = to_base_frame(points, Robot(37.0, (10.0, 20.0), given=True))
    distances = np.linalg.norm(points[:, None] - points[None], axis=2)
    np.testing.assert_allclose(np.linalg.norm(moved[:, None] - moved[None], axis=2), distances, atol=1e-10)
    # 37 deg: the angle between the first point pair's chord turns by exactly 37 deg
    chord, moved_chord = points[1] - points[0], moved[1] - moved[0]
    turned = math.atan2(moved_chord[1], moved_chord[0]) - math.atan2(chord[1], chord[0])
    assert math.remainder(turned - math.radians(37.0), 2 * math.pi) == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("verify", [False, True])
def test_a_plan_that_misses_its_target_says_so(verify):
    """Centre moves held to 0.005 mm per step cannot compensate: the best pass misses the
    0.005 mm target (0.1 mm on the planning model; re-aimed, 0.009 mm on the refined); the
    plan is still made (its trajectory the best found) and one target-missed event names the
    miss, on the planning model or (verified) on the refined one, where 1.5 x the tolerance
    is accepted."""
    from stitchplan.events import EventKind
    from stitchplan.planning.verification import plan_verified

    raw = scene((20.0, 20.0), (0.0, 18.0), "cw", ["right"], spacing=5.0, step=0.3,
                planner={"center_step_limit": 0.005, "max_passes": 2})
    result = plan_verified(parse_scenario(raw), compare=False, verify=verify)
    misses = [e for e in result.planned.events if e.kind == EventKind.TARGET_MISSED]
    assert len(misses) == 1
    if verify:
        miss, where = result.verification.result.exit_error_mm, "on the refined model (spacing 2.5 mm)"
    else:
        miss, where = result.planned.exit_error_mm, "on the planning model"
    accepted = 0.0075 if verify else 0.005
    assert miss > accepted
    assert misses[0].message.startswith(f"plan: the tip exits {miss:.4g} mm from the desired exit {where}, "
                                        f"above the {accepted:.4g} mm accepted, after {len(result.passes)} planner "
                                        "passes")
    assert "the move limits held the centre back" in misses[0].message  # what the passes met, said


def test_passes_held_back_at_every_step_search_between_their_offsets_and_stop_once_settled():
    """Centre moves held to 0.005 mm per step: a larger offset moves the exit away from the aim
    (the second pass misses by more than the first), so the later passes search between the
    offsets run instead of going on along the secant, and stop before max_passes once the
    next offset is within the exit tolerance of one run; the best pass is the nearest."""
    raw = scene((20.0, 20.0), (0.0, 18.0), "cw", ["right"], spacing=5.0, step=0.3,
                planner={"center_step_limit": 0.005, "max_passes": 8})
    result = run_plan(parse_scenario(raw), compare=False)
    offsets = [float(np.linalg.norm(record["offset_mm"])) for record in result.passes]
    misses = [record["exit_error_mm"] for record in result.passes]
    assert result.shooting.searching and misses[1] > misses[0]
    assert max(offsets[2:]) <= offsets[1] + 1e-12  # between the passes run, not past them
    assert len(result.passes) < 8 and result.shooting.closest_tried() < 0.005
    assert result.planned.exit_error_mm == min(misses)
