"""The needle leaning at entry (needle.entry_tilt) and the planner choosing the lean
(planner.aim_entry_tilt):

- the geometry: a leaning needle is the orthogonal one turned about the entry point, the sign
  as documented (positive: a deeper bite), the desired exit the orthogonal needle's; leans
  the geometry or the config cannot take are refused with the field named;
- a centre path whose row 0 lies on the circle about the entry leans the replayed needle
  (a plan's trajectory replays as planned, from the scenario as given), while a row 0 moved
  off that circle keeps moving the needle as before; one model serves every lean;
- the planner: where the move limits cannot carry the compensation (a soft corner scene like
  thesis figure 5.10's), the orthogonal plan misses by more than a millimetre and the leaning
  one reaches the exit with the limits held; `simulate --center-path` replays its file to the
  planned exit error.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from stitchplan.cli import app
from stitchplan.config.scenario import ScenarioError, parse_scenario
from stitchplan.needle.geometry import entry_lean, leaning, orthogonal, scenario_needle
from stitchplan.needle.insertion import run_insertion
from stitchplan.needle.prepared_tissue import PreparedTissue
from stitchplan.planning.move_limits import center_moves
from stitchplan.planning.planner import run_plan
from stitchplan.planning.trajectory import exported_centers

RADIUS = 8.88


def corner_scene(mu=0.05, limit=0.1, lean=True, tilt=0.0) -> dict:
    """A 40 x 40 mm neo-Hookean block clamped on the right; the needle enters the top edge
    one radius from the left corner and exits through the free left edge (figure 5.10's
    layout), 0.16 rad steps, the move limits `limit` (second difference half of it)."""
    return {"tissue": {"size": [40.0, 40.0], "thickness": 10.0, "clamped": ["right"],
                       "material": {"model": "neo-hookean", "lame_lambda": 0.189151, "lame_mu": mu}},
            "discretization": {"spacing": 4.0},
            "needle": {"radius": RADIUS, "entry": [RADIUS, 40.0], "turn": "cw", "step": 0.16,
                       "friction": 0.0602, "cutting_force": 0.7, "entry_tilt": tilt},
            "planner": {"center_step_limit": limit, "center_second_difference_limit": limit / 2,
                        "aim_entry_tilt": lean}}


# --- geometry -------------------------------------------------------------------------------


@pytest.mark.parametrize("tilt", [-0.3, 0.2, 0.5])
def test_a_leaning_needle_is_the_orthogonal_one_turned_about_its_entry(tilt):
    upright = scenario_needle(parse_scenario(corner_scene(tilt=0.0)))
    leaned = scenario_needle(parse_scenario(corner_scene(tilt=tilt, lean=False)))
    entry = np.array([RADIUS, 40.0])
    assert leaned.tilt == tilt and upright.tilt == 0.0
    np.testing.assert_allclose(leaned.tip(0.0), entry, atol=1e-12)  # the tip still at the entry
    np.testing.assert_allclose(np.linalg.norm(leaned.center - entry), RADIUS, rtol=1e-14)
    # turned by the lean against the needle's (clockwise) turn: counter-clockwise
    a, b = upright.center - entry, leaned.center - entry
    assert math.atan2(a[0] * b[1] - a[1] * b[0], a @ b) == pytest.approx(tilt, abs=1e-12)
    np.testing.assert_array_equal(leaned.desired_exit, upright.desired_exit)  # (0, 40 - R)
    np.testing.assert_allclose(upright.desired_exit, [0.0, 40.0 - RADIUS], atol=1e-9)
    exit_point = leaned.tip(leaned.exit_rotation)  # its own circle leaves the tissue there
    assert abs(exit_point[0]) < 1e-9 or abs(exit_point[1]) < 1e-9
    # positive: a deeper bite (the needle reaches further below the entry edge)
    depth = lambda geometry: geometry.center[1] - geometry.radius  # noqa: E731
    assert (depth(leaned) < depth(upright)) == (tilt > 0)


def test_leans_the_needle_cannot_take_are_refused_naming_the_field():
    with pytest.raises(ScenarioError) as error:
        parse_scenario(corner_scene(tilt=1.2))
    assert "needle.entry_tilt: got 1.2, expected an angle between -1 and 1 rad" in str(error.value)
    # a half circle exiting through its entry edge has no arc left for a deeper bite
    flat = corner_scene(tilt=0.1)
    flat["needle"]["entry"] = [30.0, 40.0]
    with pytest.raises(ScenarioError) as error:
        scenario_needle(parse_scenario(flat))
    assert str(error.value).startswith("needle.entry_tilt: the 8.88 mm needle entering at [30.0, 40.0] turning cw "
                                       "leaning 0.1 rad leaves after")
    with pytest.raises(ScenarioError) as error:
        parse_scenario({**corner_scene(), "planner": {"aim_entry_tilt": True, "target": "symmetric"}})
    assert "planner.aim_entry_tilt: got true, expected false with target symmetric" in str(error.value)


def test_the_leans_first_slope_is_the_undeformed_exits_one_sided_difference():
    """The secant's first slope: the undeformed exit's move along a direction per radian of
    lean, a forward difference where the needle can lean deeper, a backward one where it
    cannot (a half circle exiting through its entry edge), each signed as the lean moves."""
    from stitchplan.planning.entry_lean import (
        LEAN_STEP,
        _leaned_exit,
        _undeformed_lean_slope,
    )

    corner = parse_scenario(corner_scene(lean=False))
    flat = corner_scene(lean=False)
    flat["needle"]["entry"] = [30.0, 40.0]
    flat = parse_scenario(flat)
    assert _leaned_exit(flat, LEAN_STEP) is None and _leaned_exit(corner, LEAN_STEP) is not None
    for scenario, change in ((corner, LEAN_STEP), (flat, -LEAN_STEP)):
        moved = _leaned_exit(scenario, change) - _leaned_exit(scenario, 0.0)
        direction = moved / np.linalg.norm(moved)  # along the edge the exit lies on
        expected = direction @ moved / change
        assert expected != 0.0  # 7.1 mm/rad at the corner; the half circle's chord 2R cos(lean) moves at second order
        assert _undeformed_lean_slope(scenario, 0.0, direction) == pytest.approx(expected, rel=1e-12)


# --- replays --------------------------------------------------------------------------------


def test_a_centre_path_starting_on_the_circle_about_the_entry_leans_the_needle():
    scenario = parse_scenario(corner_scene(lean=False))
    leaned = leaning(scenario, 0.25)
    center = scenario_needle(leaned).center
    assert entry_lean(scenario, center).needle.entry_tilt == pytest.approx(0.25, abs=1e-12)
    assert entry_lean(leaned, center) is leaned
    assert orthogonal(leaned) == scenario
    # a centre moved off the entry (by 0.1 mm across the needle's arm: 6e-5 radii off the
    # circle) moves the needle, as before
    moved = scenario_needle(scenario).center + [0.1, 0.0]
    assert entry_lean(scenario, moved) is scenario
    # one model for every lean
    tissue = PreparedTissue(scenario)
    assert tissue.fits(leaned)
    # the fixed leaning needle and its centre replayed from the scenario as given: the same run
    fixed = run_insertion(leaned, tissue=tissue)
    path = np.repeat(center[None, :], len(fixed.steps) + 2, axis=0)
    replayed = run_insertion(scenario, center_path=path, tissue=tissue)
    assert replayed.geometry.tilt == pytest.approx(0.25, abs=1e-12)
    assert replayed.exit_error_mm == pytest.approx(fixed.exit_error_mm, abs=1e-9)
    assert replayed.exit_error_mm != pytest.approx(run_insertion(scenario, tissue=tissue).exit_error_mm, abs=1e-3)


# --- the planner ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def plans():
    """The corner scene planned upright and leaning, with the move limits 0.1 mm per 0.08 rad."""
    return {lean: run_plan(parse_scenario(corner_scene(lean=lean))) for lean in (False, True)}


def test_where_the_move_limits_cannot_carry_the_plan_the_lean_does(plans):
    upright, leaned = plans[False], plans[True]
    scale = 0.16 / 0.08  # the limits scale with the step
    for plan in (upright, leaned):
        moves, second = center_moves(exported_centers(plan.planned))
        assert moves.max() <= 0.1 * scale + 1e-6 and second.max() <= 0.05 * scale + 1e-6
    assert upright.planned.exit_error_mm > 1.0  # held back by the limits
    assert leaned.planned.exit_error_mm < 0.01
    tilt = leaned.planned.geometry.tilt
    assert 0.0 < tilt <= leaned.planned.scenario.planner.max_entry_tilt
    assert leaned.lean.tilt == tilt and len(leaned.lean.tries) >= 2
    assert leaned.lean.tries[0][0] == 0.0  # the search starts upright
    # the comparison is the needle as the scenario gives it: upright
    assert leaned.unplanned.geometry.tilt == 0.0
    assert leaned.unplanned.exit_error_mm == upright.unplanned.exit_error_mm
    # the trajectory starts with the tip at the entry and the centre a radius from it
    row0 = exported_centers(leaned.planned)[0]
    assert np.linalg.norm(row0 - [RADIUS, 40.0]) == pytest.approx(RADIUS, rel=1e-9)


def test_the_plans_trajectory_file_replays_to_its_exit_error(plans, tmp_path):
    """`plan --export` then `simulate --center-path` on the same scenario file: the replay
    leans the needle as planned and lands where the plan did."""
    scene = tmp_path / "corner.yaml"
    scene.write_text(json.dumps(corner_scene()))
    runner = CliRunner()
    planned = runner.invoke(app, ["plan", str(scene), "--export", str(tmp_path / "t.csv"), "--no-verify",
                                  "--summary", str(tmp_path / "plan.json")])
    assert planned.exit_code == 0, planned.output
    replayed = runner.invoke(app, ["simulate", str(scene), "--center-path", str(tmp_path / "t.csv"),
                                   "--no-estimate", "--summary", str(tmp_path / "replay.json")])
    assert replayed.exit_code == 0, replayed.output
    plan, replay = (json.loads((tmp_path / name).read_text()) for name in ("plan.json", "replay.json"))
    assert plan["needle_entry_tilt_rad"] == pytest.approx(plans[True].planned.geometry.tilt, abs=1e-12)
    assert plan["planner_entry_lean"]["entry_tilt_rad"] == plan["needle_entry_tilt_rad"]
    assert replay["needle_entry_tilt_rad"] == pytest.approx(plan["needle_entry_tilt_rad"], abs=1e-9)
    # the plan's centres settle within its solver's tolerances, the replay's are prescribed
    # (test_plan_cli's replay of an upright plan: 1e-3 mm)
    assert replay["exit_error_mm"] == pytest.approx(plan["exit_error_mm"], abs=1e-4)
    # the final exit's crossing record is judged against the same desired exit, the upright needle's
    for summary in (plan, replay):
        assert summary["crossings"][-1]["desired"] == summary["desired_exit"]
        assert summary["crossings"][-1]["error_mm"] == pytest.approx(summary["exit_error_mm"], rel=1e-12)


def test_a_row_0_written_with_six_digits_still_leans_the_needle(plans, tmp_path):
    """A trajectory file whose row 0 was rounded (six significant digits: ~1e-6 radii off the
    circle about the entry) replays the same lean to the rounding."""
    from stitchplan.io.readers import read_center_path

    scenario = parse_scenario(corner_scene())
    centers = exported_centers(plans[True].planned)
    rows = ["step,center_x_mm,center_y_mm"] + [f"{k},{x:.6g},{y:.6g}" for k, (x, y) in enumerate(centers)]
    path = tmp_path / "rounded.csv"
    path.write_text("\n".join(rows) + "\n")
    geometry = scenario_needle(scenario)
    read = read_center_path(path, geometry, lambda first: scenario_needle(entry_lean(scenario, first)))
    assert np.linalg.norm(read[0] - [RADIUS, 40.0]) == pytest.approx(RADIUS, rel=1e-12)
    assert entry_lean(scenario, read[0]).needle.entry_tilt == pytest.approx(plans[True].planned.geometry.tilt,
                                                                            abs=1e-5)


def test_a_row_0_leaning_too_far_is_refused_naming_the_file(tmp_path):
    scene = tmp_path / "corner.yaml"
    scene.write_text(json.dumps(corner_scene(lean=False)))
    entry = np.array([RADIUS, 40.0])
    arm = scenario_needle(parse_scenario(corner_scene())).center - entry
    turned = entry + np.array([[math.cos(1.3), -math.sin(1.3)], [math.sin(1.3), math.cos(1.3)]]) @ arm
    rows = ["step,center_x_mm,center_y_mm", f"0,{float(turned[0])!r},{float(turned[1])!r}"]
    rows += [f"{k},{float(turned[0])!r},{float(turned[1])!r}" for k in range(1, 12)]
    (tmp_path / "t.csv").write_text("\n".join(rows) + "\n")
    result = CliRunner().invoke(app, ["simulate", str(scene), "--center-path", str(tmp_path / "t.csv"),
                                      "--no-estimate"])
    assert result.exit_code == 2
    assert f"--center-path: {tmp_path / 't.csv'}: row 0 puts the needle centre at" in result.output
    assert "leaning the needle 1.3 rad from the orthogonal entry; expected a lean of at most 1 rad" in result.output


@pytest.mark.parametrize("block, field, value, fragment", [
    ("needle", "entry_tilt", "steep", "needle.entry_tilt: got 'steep', expected an angle between -1 and 1 rad"),
    ("needle", "entry_tilt", -1.5, "needle.entry_tilt: got -1.5, expected an angle between -1 and 1 rad"),
    ("planner", "max_entry_tilt", 0.0, "planner.max_entry_tilt: got 0.0, expected a positive angle of at most 1 rad"),
    ("planner", "max_entry_tilt", 1.2, "planner.max_entry_tilt: got 1.2, expected a positive angle of at most 1 rad"),
    ("planner", "aim_entry_tilt", "yes", "planner.aim_entry_tilt: got 'yes', expected true or false"),
    # the search starts from the needle's own lean: beyond max_entry_tilt (0.35) it was the plan's
    ("needle", "entry_tilt", -0.5, "needle.entry_tilt: got -0.5, expected a lean of at most "
                                   "planner.max_entry_tilt (0.35 rad) either way with planner.aim_entry_tilt"),
])
def test_bad_lean_fields_are_refused_naming_the_field(block, field, value, fragment):
    raw = corner_scene()
    raw[block][field] = value
    with pytest.raises(ScenarioError) as error:
        parse_scenario(raw)
    assert fragment in str(error.value)


def test_a_lean_that_leaves_through_another_wall_is_refused():
    """The upright 8.18 mm needle's arc of 2.27 rad ends past its exit into a round hole (its
    desired exit on the hole's wall); leaned by -0.594 rad its circle leaves through the top
    surface instead, as many crossings of the same kinds: that lean was accepted, its exit
    judged against the hole's wall. A lean keeps the walls too."""
    from stitchplan.config.scenario import Needle
    from stitchplan.geometry.polygon_domain import PolygonDomain
    from stitchplan.geometry.polygons import circle_polygon
    from stitchplan.needle.geometry import needle_geometry

    domain = PolygonDomain.rectangle((60.0, 30.0), (circle_polygon((10.355, 23.719), 1.678),))
    needle = dict(radius=8.181, arc=2.269, entry=(24.736, 30.0), turn="cw", step=0.08, friction=0.05,
                  cutting_force=0.5)
    upright = needle_geometry(Needle(**needle), domain)
    assert domain.distance(upright.desired_exit[None])[0] < 1e-6 and upright.desired_exit[1] < 29.0  # the hole's wall
    with pytest.raises(ScenarioError) as error:
        needle_geometry(Needle(**needle, entry_tilt=-0.594), domain)
    assert str(error.value).startswith("needle.entry_tilt: got -0.594 rad, which makes the needle cross the boundary "
                                       "through other walls than the orthogonal needle")


def test_a_later_rounds_search_lists_the_pass_it_starts_from_once():
    """A verification round's search starts from the pass the earlier round chose, kept and
    not run again: the merged record lists it once (it read as two tries of one lean)."""
    from stitchplan.planning.entry_lean import LeanSearch

    chosen = (0.055, np.array([-4.9e-6, -1.4e-4]))
    earlier = LeanSearch(0.055, None, [], [(0.0, np.array([0.0099, 0.2533])), chosen], "a first pass met its aim")
    later = LeanSearch(0.1, None, [], [(0.055, chosen[1].copy()), (0.1, np.array([-0.0075, -0.2117]))], "at max")
    assert [tilt for tilt, _ in later.after(earlier).tries] == [0.0, 0.055, 0.1]
    fresh = LeanSearch(0.1, None, [], [(0.07, np.array([1e-3, 2e-3]))], "")  # a search that ran its own first pass
    assert [tilt for tilt, _ in fresh.after(earlier).tries] == [0.0, 0.055, 0.07]
