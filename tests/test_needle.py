"""Needle geometry (centre and desired exit of the orthogonal entry, as the scenario
format defines it), the user errors of impossible needles, the two tip-tracking kernels on fields
whose answer is known, and the geometry of the shipped needle scenarios."""

from __future__ import annotations

import math

import numpy as np
import pytest

from stitchplan.config.scenario import Needle, ScenarioError, load_scenario, parse_scenario
from stitchplan.errors import TipTrackingJump
from stitchplan.geometry.rectangle import Rectangle
from stitchplan.needle.geometry import needle_geometry
from stitchplan.needle.tip_tracking import inverse_gradient_step, levenberg_marquardt_tip


def inside(points, size, tol=0.0):
    return Rectangle.of_size(size).contains(points, tol)


from conftest import CONFIGS

SIZE = (40.0, 30.0)  # W x H mm of the small test block
RADIUS = 6.0


def make_needle(entry, turn="cw", radius=RADIUS, arc=math.pi, step=0.1) -> Needle:
    return Needle(radius=radius, arc=arc, entry=tuple(entry), turn=turn, step=step, friction=0.05,
                  cutting_force=0.5)


def on_edge(point, size=SIZE, tol=1e-9) -> bool:
    x, y = point
    return inside(np.asarray(point), size, tol) and min(abs(x), abs(x - size[0]), abs(y), abs(y - size[1])) <= tol


# (edge, entry, turn, centre, desired exit): a half circle of radius 6 fits in the 40 x 30
# block from each of these entries, so the exit is the entry mirrored through the centre
# along the edge. Clockwise from the left edge the tip heads into the tissue and curls down.
CASES = [
    ("left", (0.0, 20.0), "cw", (0.0, 14.0), (0.0, 8.0)),
    ("left", (0.0, 10.0), "ccw", (0.0, 16.0), (0.0, 22.0)),
    ("right", (40.0, 10.0), "cw", (40.0, 16.0), (40.0, 22.0)),
    ("right", (40.0, 20.0), "ccw", (40.0, 14.0), (40.0, 8.0)),
    ("bottom", (10.0, 0.0), "cw", (16.0, 0.0), (22.0, 0.0)),
    ("bottom", (30.0, 0.0), "ccw", (24.0, 0.0), (18.0, 0.0)),
    ("top", (30.0, 30.0), "cw", (24.0, 30.0), (18.0, 30.0)),
    ("top", (10.0, 30.0), "ccw", (16.0, 30.0), (22.0, 30.0)),
]


@pytest.mark.parametrize("edge,entry,turn,center,exit_point", CASES, ids=[f"{c[0]}-{c[2]}" for c in CASES])
def test_centre_and_desired_exit_on_every_edge(edge, entry, turn, center, exit_point):
    geometry = needle_geometry(make_needle(entry, turn), Rectangle.of_size(SIZE))
    assert geometry.entry_edge == edge
    np.testing.assert_allclose(geometry.center, center, atol=1e-12)
    np.testing.assert_allclose(geometry.desired_exit, exit_point, atol=1e-12)
    assert geometry.exit_rotation == pytest.approx(math.pi, abs=1e-12)
    # the tip starts at the entry and moves along the inward normal (orthogonal entry) ...
    np.testing.assert_allclose(geometry.tip(0.0), entry, atol=1e-12)
    inward = (geometry.tip(1e-6) - geometry.tip(0.0)) / 1e-6
    normal = {"left": (1, 0), "right": (-1, 0), "bottom": (0, 1), "top": (0, -1)}[edge]
    np.testing.assert_allclose(inward / np.linalg.norm(inward), normal, atol=1e-5)
    # ... turning the requested way: the z component of (velocity x acceleration) is < 0 for cw
    later = (geometry.tip(2e-3) - geometry.tip(1e-3)) / 1e-3
    turning = inward[0] * later[1] - inward[1] * later[0]
    assert np.sign(turning) == (-1.0 if turn == "cw" else 1.0)
    # ... and stays inside the tissue until the desired exit
    path = geometry.tip(np.linspace(0.0, geometry.exit_rotation, 200)[1:-1])
    assert inside(path, SIZE).all()


def test_desired_exit_where_the_circle_first_leaves_through_another_edge():
    """A 20 mm needle turning cw from (0, 30) of a 100 x 100 block (configs/needle20_entry30.yaml)
    leaves through the bottom edge at x = sqrt(20^2 - 10^2), a third of a turn after entry."""
    geometry = needle_geometry(make_needle((0.0, 30.0), "cw", radius=20.0), Rectangle.of_size((100.0, 100.0)))
    np.testing.assert_allclose(geometry.center, [0.0, 10.0], atol=1e-12)
    np.testing.assert_allclose(geometry.desired_exit, [math.sqrt(300.0), 0.0], atol=1e-9)
    assert geometry.exit_rotation == pytest.approx(2 * math.pi / 3, abs=1e-12)


@pytest.mark.parametrize("entry,fragment", [
    ((5.0, 15.0), "needle.entry: got [5.0, 15.0], expected a point on the boundary"),
    ((-1.0, 15.0), "needle.entry: got [-1.0, 15.0], expected a point on the boundary"),
    ((0.0, 31.0), "needle.entry: got [0.0, 31.0], expected a point on the boundary"),
    ((0.0, 0.0), "needle.entry: got [0.0, 0.0], a corner"),
    ((40.0, 30.0), "needle.entry: got [40.0, 30.0], a corner"),
])
def test_entry_off_the_boundary_or_at_a_corner_is_refused(entry, fragment):
    with pytest.raises(ScenarioError) as error:
        needle_geometry(make_needle(entry), Rectangle.of_size(SIZE))
    assert fragment in str(error.value)


def test_an_entry_off_the_boundary_is_told_the_nearest_boundary_point():
    with pytest.raises(ScenarioError) as error:
        needle_geometry(make_needle((5.0, 15.0)), Rectangle.of_size(SIZE))
    assert str(error.value).endswith("expected a point on the boundary of the 40 x 30 mm tissue; the nearest "
                                     "is [0, 15], 5 mm away")


def test_an_entry_on_a_smooth_vertex_enters_along_the_mean_normal():
    """A vertex of a traced contour or a circular hole, where the boundary turns by a few
    degrees, is no corner: the needle enters along the mean of its two edges' normals (the
    radial direction on a polygon inscribed in a circle)."""
    from stitchplan.geometry.polygon_domain import PolygonDomain

    angles = np.linspace(np.pi, 0.0, 49)  # a top edge bulging as a half circle of radius 40
    arc = np.stack([50.0 + 40.0 * np.cos(angles), 30.0 + 40.0 * np.sin(angles)], axis=1)
    domain = PolygonDomain(np.vstack([[[10.0, 0.0], [90.0, 0.0]], arc[::-1]]))
    vertex = arc[20]  # on the circle, between two edges turning by 3.75 degrees
    assert len(domain.edges_at(vertex)) == 2
    geometry = needle_geometry(make_needle(tuple(vertex), "cw", radius=8.0), domain)
    inward = (np.array([50.0, 30.0]) - vertex) / 40.0
    np.testing.assert_allclose(geometry.center, vertex + 8.0 * np.array([inward[1], -inward[0]]), atol=1e-9)


def test_arc_too_short_to_exit_is_refused():
    """A quarter-circle needle cannot bring the tip back out of a half-circle stitch."""
    with pytest.raises(ScenarioError) as error:
        needle_geometry(make_needle((0.0, 20.0), arc=math.pi / 2), Rectangle.of_size(SIZE))
    message = str(error.value)
    assert message.startswith("needle:") and "leaves after 3.142 rad" in message
    assert "expected an exit within its arc of 1.571 rad" in message


def test_a_half_circle_entering_a_slanted_edge_within_round_off_is_accepted():
    """An entry kept to the bit 4.8e-8 mm off a slanted edge (within the boundary's round-off)
    turns the half circle's exit 1.1e-8 rad past pi: the default arc of pi holds it (it was
    refused as leaving past its arc)."""
    from stitchplan.geometry.polygon_domain import PolygonDomain

    domain = PolygonDomain(np.array([[0.0, 0.0], [96.83, 0.0], [87.71, 48.96], [9.13, 48.96]]))
    assert 0.0 < domain.distance(np.array([[90.807515, 32.331235]]))[0] < domain.tolerance
    geometry = needle_geometry(make_needle((90.807515, 32.331235), "cw", radius=4.57), domain)
    assert 0.0 < geometry.exit_rotation - math.pi < 2e-8


def test_a_half_circle_typed_as_3_14159_reaches_its_exit():
    """A half circle's arc written to six digits ends 24 nm (2.7e-6 rad) before the exit on
    the entry edge, well within the 1 um to which typed points are taken: accepted, on a block
    and across a wound (both were refused as leaving past the arc); 5 um short is still refused."""
    from stitchplan.geometry.polygon_domain import PolygonDomain

    block = needle_geometry(make_needle((0.0, 20.0), radius=8.88, arc=3.14159), Rectangle.of_size(SIZE))
    assert block.exit_rotation == pytest.approx(math.pi, abs=1e-12)
    wound = PolygonDomain(np.array([[0.0, 0.0], [60.0, 0.0], [60.0, 30.0], [32.0, 30.0], [32.0, 18.0],
                                    [28.0, 18.0], [28.0, 30.0], [0.0, 30.0]]))
    across = needle_geometry(make_needle((38.88, 30.0), radius=8.88, arc=3.14159), wound)
    assert [kind for _, kind in across.crossings] == ["exit", "entry", "exit"]
    np.testing.assert_allclose(across.desired_exit, [21.12, 30.0], atol=1e-9)
    with pytest.raises(ScenarioError, match="0.00059 rad past its arc"):
        needle_geometry(make_needle((0.0, 20.0), radius=8.88, arc=3.141), Rectangle.of_size(SIZE))


@pytest.mark.parametrize(("domain", "needle", "fragment"), [
    # an entry from within a 4 mm hole: the 16 mm needle's body crosses the tissue beyond it
    ("hole", ((28.0, 25.0), "cw", 8.0, math.pi, 0.0), "1.5 rad back along its arc of 3.142"),
    # a needle of nearly a full turn: its tail is where the tip is about to cut
    ("slab", ((30.0, 40.0), "cw", 10.0, 6.0, 0.0), "4.71 rad back along its arc of 6 rad"),
])
def test_a_needle_whose_body_lies_in_the_tissue_before_it_enters_is_refused(domain, needle, fragment):
    """The driver holds the needle from outside: only its tip may touch the tissue at the
    start. These were accepted and run (exit 0), the needle's tail in uncut tissue."""
    from stitchplan.geometry.polygon_domain import PolygonDomain
    from stitchplan.geometry.polygons import circle_polygon

    shape = {"hole": PolygonDomain.rectangle((60.0, 40.0), (circle_polygon((30.0, 25.0), 2.0),)),
             "slab": Rectangle.of_size((60.0, 40.0))}[domain]
    entry, turn, radius, arc, tilt = needle
    with pytest.raises(ScenarioError) as error:
        needle_geometry(Needle(radius=radius, arc=arc, entry=entry, turn=turn, step=0.1, friction=0.05,
                               cutting_force=0.5, entry_tilt=tilt), shape)
    message = str(error.value)
    assert message.startswith("needle: the ") and fragment in message, message
    assert "expected its body outside the tissue, held from there, with only its tip at the entry" in message
    # upright, the same half circle on the slab keeps its body above the surface
    needle_geometry(Needle(radius=8.0, arc=math.pi, entry=(30.0, 40.0), turn="cw", step=0.1, friction=0.05,
                           cutting_force=0.5), Rectangle.of_size((60.0, 40.0)))


def test_an_arc_that_ends_in_a_wounds_far_wall_is_refused():
    """configs/wound_closure.yaml's needle cut to 2.8 rad: its circle leaves through the near
    wall and enters the far one, and the arc ends inside. It was taken as a stitch whose final
    exit is the near wall, then stopped at that wall (exit 1)."""
    from stitchplan.geometry.polygon_domain import PolygonDomain

    wound = PolygonDomain(np.array([[0.0, 0.0], [60.0, 0.0], [60.0, 30.0], [32.0, 30.0], [32.0, 18.0],
                                    [28.0, 18.0], [28.0, 30.0], [0.0, 30.0]]))
    with pytest.raises(ScenarioError) as error:
        needle_geometry(make_needle((38.88, 30.0), "cw", radius=8.88, arc=2.8), wound)
    assert str(error.value).startswith("needle.arc: got 2.8 rad; the needle entering at [38.88, 30.0] turning cw "
                                       "enters the tissue again after 1.798 rad and does not leave it within its arc")
    assert needle_geometry(make_needle((38.88, 30.0), "cw", radius=8.88), wound).exit_rotation == pytest.approx(
        math.pi, abs=1e-6)


def test_exit_within_two_steps_is_refused():
    """An entry 0.5 mm from the bottom corner turning towards it exits almost at once."""
    with pytest.raises(ScenarioError, match="expected at least two steps of 0.4 rad"):
        needle_geometry(make_needle((0.0, 0.5), "cw", step=0.4), Rectangle.of_size(SIZE))


def needle_raw(**changes) -> dict:
    needle = {"radius": 6.0, "entry": [0.0, 20.0], "turn": "cw", "step": 0.1, "friction": 0.05,
              "cutting_force": 0.5}
    needle.update(changes)
    return {"tissue": {"size": list(SIZE), "thickness": 10.0, "clamped": ["right"],
                       "material": {"lame_lambda": 0.19, "lame_mu": 0.15}},
            "needle": needle}


@pytest.mark.parametrize("field,value,fragment", [
    ("radius", -8.88, "needle.radius: got -8.88, expected a positive number (mm)"),
    ("radius", 0.0, "needle.radius: got 0.0, expected a positive number (mm)"),
    ("turn", "left", "needle.turn: got 'left', expected one of cw, ccw"),
    ("step", 0.8, "needle.step: got 0.8, expected a positive angle of at most 0.5 rad per step"),
    ("friction", -0.1, "needle.friction: got -0.1, expected a non-negative number (N/mm)"),
    ("tip_tracking", "newton", "needle.tip_tracking: got 'newton', expected one of auto"),
    ("entry", [0.0], "needle.entry: got [0.0], expected a pair [x, y] of numbers (mm)"),
    ("coupling", "springs", "needle.coupling: got 'springs', expected one of mortar, points"),
    ("cutting_length", 0.0, "needle.cutting_length: got 0.0, expected a positive number (mm)"),
    ("multiplier_ends", "curved", "needle.multiplier_ends: got 'curved', expected one of segments, arc"),
    ("multiplier_length", -1.5, "needle.multiplier_length: got -1.5, expected a positive number (mm)"),
    ("cutting_ramp", "yes", "needle.cutting_ramp: got 'yes', expected true or false"),
])
def test_bad_needle_fields_are_refused_by_the_config(field, value, fragment):
    with pytest.raises(ScenarioError) as error:
        parse_scenario(needle_raw(**{field: value}))
    assert fragment in str(error.value)


# --- tip-tracking kernels ---------------------------------------------------------------


def test_inverse_gradient_step_under_a_homogeneous_stretch():
    """For u = (F - I) X the linearisation is exact: X_{n+1} = F^-1 x_{n+1} (eq. 3.66-3.67)."""
    deformation_gradient = np.array([[1.1, 0.05], [-0.02, 0.95]])
    previous = np.array([2.0, 20.0])
    spatial_previous = deformation_gradient @ previous
    target = spatial_previous + np.array([0.6, -0.1])
    expected = np.linalg.solve(deformation_gradient, target)
    step = expected - previous
    point = inverse_gradient_step(previous, spatial_previous, deformation_gradient, target,
                                  float(np.linalg.norm(step)), step,
                                  displacement=lambda x: (deformation_gradient - np.eye(2)) @ x)
    np.testing.assert_allclose(point, expected, atol=1e-12)


@pytest.mark.parametrize("length_factor,turn_deg,message", [
    (3.0, 0.0, "inverse-gradient step of"),
    (0.3, 0.0, "inverse-gradient step of"),
    (1.0, 80.0, "at 80 deg from the expected"),
])
def test_inverse_gradient_jump_is_detected(length_factor, turn_deg, message):
    """A material step 3x too long, 3x too short or turned by 80 degrees is a jump."""
    expected_direction = np.array([1.0, 0.0])
    angle = math.radians(turn_deg)
    step = length_factor * np.array([math.cos(angle), math.sin(angle)])
    with pytest.raises(TipTrackingJump, match=message):
        inverse_gradient_step(np.zeros(2), np.zeros(2), np.eye(2), step, 1.0, expected_direction)


def test_inverse_gradient_jump_when_the_linearisation_misses_the_needle():
    """F at X_n says 'rigid', the real field shifts the point by 0.2 mm: the point found is
    0.2 mm from the target, more than 5 % of the 1 mm step."""
    with pytest.raises(TipTrackingJump, match="lands 0.2 mm from the needle"):
        inverse_gradient_step(np.zeros(2), np.zeros(2), np.eye(2), np.array([1.0, 0.0]), 1.0,
                              np.array([1.0, 0.0]), displacement=lambda x: np.array([0.0, 0.2 * x[0]]))


def test_levenberg_marquardt_in_undeformed_tissue_lands_on_the_circle():
    """With u = 0, eq. 3.68-3.69 has the exact solution: the point of the circle one chord
    (2 R sin(theta / 2)) further along from the previous tip."""
    center, radius, theta = np.array([0.0, 14.0]), 6.0, 0.1
    previous = center + radius * np.array([math.cos(1.2), math.sin(1.2)])
    chord = 2 * radius * math.sin(theta / 2)
    expected = center + radius * np.array([math.cos(1.2 - theta), math.sin(1.2 - theta)])
    start = previous + chord * np.array([math.sin(1.2 - theta / 2), -math.cos(1.2 - theta / 2)])
    point, evaluations = levenberg_marquardt_tip(previous, center, radius, chord, start,
                                                 lambda x: (np.zeros(2), np.zeros((2, 2))))
    np.testing.assert_allclose(point, expected, atol=1e-10)
    assert evaluations >= 1


# --- shipped needle scenarios ------------------------------------------------------------

NEEDLE20 = {  # entry y -> desired exit on the bottom edge (x = sqrt(20^2 - (y - 20)^2))
    30: 17.320508075688775, 25: 19.364916731037084, 20: 20.0, 18: 19.899748742132399}


@pytest.mark.parametrize("function, a, b", [
    (lambda x: x**3 - 2.0 * x - 5.0, 2.0, 3.0),
    (lambda x: math.cos(x) - x, 0.0, 1.0),
    (lambda x: math.atan(50.0 * (x - 0.123456)), 0.0, 1.0),  # steep: bisection takes over
    (lambda x: -(x - 0.7) * (1.0 + x * x), 0.0, 1.0),
    (lambda x: (x - 0.55) ** 5 + 1e-3 * (x - 0.55), 0.0, 1.0),  # flat at the zero
    (lambda x: math.copysign(1.0, x - 0.42), 0.0, 1.0),  # a jump: bisection only
])
def test_brent_root_finds_the_zero_scipy_brentq_finds(function, a, b):
    """brent_root (the exit and re-entry searches) against scipy.optimize.brentq with the same
    tolerances: the same zero within the tolerance, in at most as many evaluations plus one,
    and the zero is a point the function was evaluated at."""
    from scipy.optimize import brentq

    from stitchplan.needle.tip_tracking import brent_root

    seen = []

    def recorded(x):
        seen.append(x)
        return function(x)

    root = brent_root(recorded, a, b, xtol=1e-13, rtol=1e-15)
    reference, info = brentq(function, a, b, xtol=1e-13, rtol=1e-15, full_output=True)
    assert abs(root - reference) <= 1e-13 + 1e-15 * abs(reference)
    assert len(seen) <= info.function_calls + 1
    assert root in seen
    with pytest.raises(ValueError, match="do not bracket"):
        brent_root(function, a, a)  # f(a) is not zero: the same sign at both ends


@pytest.mark.parametrize("entry_y", sorted(NEEDLE20))
def test_shipped_needle20_scenarios(entry_y):
    """configs/needle20_entry*.yaml (thesis 5.1.1): the material and needle as stated in the
    comments, and the desired exit where the undeformed circle first leaves the block: on the
    bottom edge, as the file's comment says."""
    scenario = load_scenario(CONFIGS / f"needle20_entry{entry_y}.yaml")
    material, needle = scenario.tissue.material, scenario.needle
    assert (material.lame_lambda, material.lame_mu) == (9.263, 1.029)
    assert (needle.radius, needle.step, needle.friction, needle.cutting_force) == (20.0, 0.1, 0.02, 0.03)
    assert needle.turn == "cw" and needle.tip_tracking == "levenberg-marquardt" and needle.arc == pytest.approx(math.pi)
    assert scenario.tissue.size == (100.0, 100.0) and scenario.tissue.clamped == ("right",)
    geometry = needle_geometry(needle, Rectangle.of_size(scenario.tissue.size))
    np.testing.assert_allclose(geometry.desired_exit, [NEEDLE20[entry_y], 0.0], atol=1e-9)
    assert f"({NEEDLE20[entry_y]:.2f}, 0) on the bottom edge" in scenario.source_text


@pytest.mark.parametrize("name,height", [("sh12_100x100_mid", 100.0), ("sh12_100x50", 50.0),
                                         ("sh12_100x40", 40.0), ("sh12_100x30", 30.0)])
def test_shipped_sh12_block_series_follows_one_entry_rule(name, height):
    """configs/sh12_100x{100_mid,50,40,30}.yaml: the SH needle of sh12_100x100.yaml on blocks of
    height 100 ... 30 mm, entering at mid-height + r so the stitch is symmetric about mid-height."""
    reference = load_scenario(CONFIGS / "sh12_100x100.yaml")
    scenario = load_scenario(CONFIGS / f"{name}.yaml")
    assert scenario.tissue.size == (100.0, height)
    assert scenario.tissue.material == reference.tissue.material
    assert scenario.tissue.clamped == ("right",)
    from dataclasses import replace

    assert scenario.needle == replace(reference.needle, entry=scenario.needle.entry)
    geometry = needle_geometry(scenario.needle, Rectangle.of_size(scenario.tissue.size))
    assert scenario.needle.entry == pytest.approx((0.0, height / 2 + 8.88))
    np.testing.assert_allclose(geometry.center, [0.0, height / 2], atol=1e-12)
    np.testing.assert_allclose(geometry.desired_exit, [0.0, height / 2 - 8.88], atol=1e-9)


def test_the_factor_is_renewed_by_the_planner_rule_or_when_newton_loses_ground():
    """needle/newton.py renew_factor: a planner's step renews the factor of K + H when an
    iteration contracts by less than REFACTOR_CONTRACTION; a prescribed centre only when the
    measure exceeds both of the last two iterations'."""
    from stitchplan.needle.newton import REFACTOR_CONTRACTION, renew_factor

    slow = 0.9  # contracted, but by less than the planner's rule asks
    assert REFACTOR_CONTRACTION < 0.9
    assert renew_factor(slow, 1.0, math.inf, planned=True)
    assert not renew_factor(slow, 1.0, math.inf, planned=False)
    assert not renew_factor(1.2, 1.0, 1.5, planned=False)  # grew once, still below two back
    assert renew_factor(1.2, 1.0, 0.8, planned=False)  # above both of the last two
    assert not renew_factor(0.3, 1.0, 2.0, planned=True) and not renew_factor(0.3, 1.0, 2.0, planned=False)


def test_anderson_mixing_remembers_the_plain_step_not_what_the_caller_made_of_it():
    """AndersonMixing (Walker and Ni 2011, type II) differences the plain steps f(x_k): a
    caller that changes the step it got back (the planner keeps the mixed centre within the
    move limits, in place) must not change the f(x_0) the next mixing differences against."""
    from stitchplan.needle.newton import AndersonMixing

    rng = np.random.default_rng(3)
    states, steps = rng.normal(size=(3, 6)), rng.normal(size=(3, 6))
    untouched, clipped = AndersonMixing(5), AndersonMixing(5)
    untouched.step(states[0], steps[0])
    first = clipped.step(states[0], steps[0].copy())
    first[-2:] = 0.0  # as a centre held by the move limits
    for state, step in zip(states[1:], steps[1:]):
        np.testing.assert_array_equal(clipped.step(state, step), untouched.step(state, step))


@pytest.mark.parametrize("clamped, where", [(["left"], "the clamped left edge"),
                                             ([{"segment": [[0.0, 10.0], [0.0, 20.0]]}],
                                              "a clamped segment of the boundary")])
def test_a_needle_entering_a_clamped_edge_is_refused(clamped, where):
    from stitchplan.needle.geometry import scenario_needle

    scenario = parse_scenario({
        "tissue": {"size": [40.0, 30.0], "thickness": 10.0, "clamped": clamped,
                   "material": {"lame_lambda": 0.189151, "lame_mu": 0.147688}},
        "needle": {"radius": 8.0, "entry": [0.0, 15.0], "turn": "cw", "step": 0.2}})
    with pytest.raises(ScenarioError, match=rf"^needle.entry: got \[0.0, 15.0\], on {where}; expected a point on a "
                                         r"free edge"):
        scenario_needle(scenario)


@pytest.mark.parametrize("clamped, where", [(["bottom"], "the clamped bottom edge"),
                                             ([{"segment": [[0.0, 0.0], [20.0, 0.0]]}],
                                              "a clamped segment of the boundary")])
def test_a_needle_leaving_through_a_clamped_edge_is_refused(clamped, where):
    """Entering 5 mm above the bottom turning cw, the 8 mm needle's way out is the bottom edge
    at x = 7.42: held there by a clamp, it cannot come out (and the exit error would only say
    that the clamp does not move)."""
    from stitchplan.needle.geometry import scenario_needle

    raw = {"tissue": {"size": [40.0, 30.0], "thickness": 10.0, "clamped": clamped,
                      "material": {"lame_lambda": 0.189151, "lame_mu": 0.147688}},
           "needle": {"radius": 8.0, "entry": [0.0, 5.0], "turn": "cw", "step": 0.2}}
    with pytest.raises(ScenarioError, match=rf"^needle: the 8 mm needle entering at \[0.0, 5.0\] turning cw leaves "
                                         rf"the tissue on {where}: the desired exit \[7.416198, 0\]; expected"):
        scenario_needle(parse_scenario(raw))
    raw["tissue"]["clamped"] = ["right"]
    assert scenario_needle(parse_scenario(raw)).desired_exit[1] == pytest.approx(0.0, abs=1e-12)


def test_the_tip_conditions_jacobian_is_their_derivative_for_a_sheared_field():
    """Eq. 3.68's two conditions (on the deformed needle circle, one insertion length from the
    previous tip) and their Jacobian under a non-symmetric displacement gradient (a shear, as
    friction gives along the track): the Jacobian is the conditions' central difference, so
    the tip's Newton iteration converges quadratically."""
    from stitchplan.needle.tip_tracking import _tip_conditions

    gradient = np.array([[0.05, 0.4], [-0.1, 0.02]])  # u = A X: du_i / dX_j = A_ij
    center, radius, step, previous = np.array([0.0, -20.0]), 20.0, 1.0, np.array([1.0, 0.0])

    def conditions(x):
        return _tip_conditions(x, gradient @ x, gradient, previous, center, radius, step)

    x = np.array([1.7, 0.4])
    _, jacobian = conditions(x)
    h = 1e-6
    numeric = np.column_stack([(conditions(x + h * e)[0] - conditions(x - h * e)[0]) / (2 * h) for e in np.eye(2)])
    np.testing.assert_allclose(jacobian, numeric, atol=1e-8)


def test_anderson_mixing_solves_a_linear_fixed_point_problem_like_gmres():
    """AndersonMixing on x <- x + f(x), f(x) = b - A x (a modified Newton step with the
    identity for the old factor): with depth >= n its iterates reach A^-1 b within n + 2
    steps, as GMRES would, where the plain iteration (contracting by ~0.75) is still far off."""
    from stitchplan.needle.newton import AndersonMixing

    rng = np.random.default_rng(0)
    n = 5
    matrix = np.eye(n) + 0.3 * rng.normal(size=(n, n))
    b = rng.normal(size=n)
    solution = np.linalg.solve(matrix, b)
    mixing, x, plain = AndersonMixing(depth=n + 1), np.zeros(n), np.zeros(n)
    for _ in range(n + 2):
        x = x + mixing.step(x, b - matrix @ x)
        plain = plain + (b - matrix @ plain)
    assert np.linalg.norm(x - solution) <= 1e-10 * np.linalg.norm(solution)
    assert np.linalg.norm(plain - solution) > 1e-2 * np.linalg.norm(solution)
