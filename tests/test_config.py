"""Scenario parsing: every user error names the field, the value received and what was
expected; defaults and overrides of the discretization."""

from __future__ import annotations

import copy
import math
import re

import numpy as np
import pytest

from stitchplan.config.scenario import (
    Needle,
    ScenarioError,
    default_spacing,
    load_scenario,
    parse_scenario,
    with_discretization,
)


def set_in(raw: dict, path: tuple, value) -> dict:
    block = raw
    for key in path[:-1]:
        block = block[key]
    block[path[-1]] = value
    return raw


def drop(raw: dict, path: tuple) -> dict:
    block = raw
    for key in path[:-1]:
        block = block[key]
    del block[path[-1]]
    return raw


# (id, mutation of the shipped scenario, fragments the message must contain: the field,
#  the value received, what was expected)
BAD_SCENARIOS = [
    ("missing thickness", lambda r: drop(r, ("tissue", "thickness")),
     ["tissue.thickness", "missing", "required"]),
    ("missing lame_mu", lambda r: drop(r, ("tissue", "material", "lame_mu")),
     ["tissue.material.lame_mu", "missing", "required"]),
    ("missing tissue", lambda r: drop(r, ("tissue",)), ["tissue: missing", "required", "size, thickness"]),
    ("unknown top-level key", lambda r: set_in(r, ("load_step",), 5),
     ["scenario", "unknown key 'load_step'", "load_steps"]),
    ("unknown tissue key", lambda r: set_in(r, ("tissue", "colour"), "red"),
     ["tissue", "unknown key 'colour'", "size, thickness, material, clamped"]),
    ("negative lame_mu", lambda r: set_in(r, ("tissue", "material", "lame_mu"), -0.1),
     ["tissue.material.lame_mu", "-0.1", "positive number (MPa)"]),
    ("zero lame_mu", lambda r: set_in(r, ("tissue", "material", "lame_mu"), 0.0),  # the bound itself
     ["tissue.material.lame_mu", "got 0.0", "positive number (MPa)"]),
    ("zero thickness", lambda r: set_in(r, ("tissue", "thickness"), 0.0),
     ["tissue.thickness", "got 0.0", "positive number (mm)"]),
    ("negative lame_lambda", lambda r: set_in(r, ("tissue", "material", "lame_lambda"), -1.0),
     ["tissue.material.lame_lambda", "-1.0", "non-negative number (MPa)"]),
    ("negative thickness", lambda r: set_in(r, ("tissue", "thickness"), -10.0),
     ["tissue.thickness", "-10.0", "positive number (mm)"]),
    ("unknown material model", lambda r: set_in(r, ("tissue", "material", "model"), "mooney-rivlin"),
     ["tissue.material.model", "'mooney-rivlin'", "saint-venant-kirchhoff, neo-hookean"]),
    ("bad clamped edge", lambda r: set_in(r, ("tissue", "clamped"), ["rigth"]),
     ["tissue.clamped[0]", "'rigth'", "left, right, bottom, top"]),
    ("clamped not a list", lambda r: set_in(r, ("tissue", "clamped"), "right"),
     ["tissue.clamped", "'right'", "a list of edges"]),
    ("segment inside the tissue", lambda r: set_in(r, ("loads", 0, "segment"), [[10.0, 40.0], [10.0, 60.0]]),
     ["loads[0].segment", "[[10.0, 40.0], [10.0, 60.0]]", "straight piece of one edge"]),
    ("segment across two edges", lambda r: set_in(r, ("loads", 0, "segment"), [[0.0, 40.0], [10.0, 0.0]]),
     ["loads[0].segment", "[[0.0, 40.0], [10.0, 0.0]]", "one edge"]),
    ("force and displacement", lambda r: set_in(r, ("loads", 0, "displacement"), [1.0, 0.0]),
     ["loads[0]", "exactly one of 'force' (N) or 'displacement' (mm)", "['displacement', 'force']"]),
    ("neither force nor displacement", lambda r: drop(r, ("loads", 0, "force")),
     ["loads[0]", "exactly one of", "neither"]),
    ("null force", lambda r: set_in(r, ("loads", 0, "force"), None), ["loads[0]", "exactly one of", "neither"]),
    ("a key that is not a string", lambda r: set_in(r, (1,), 2), ["scenario: unknown key 1", "load_steps"]),
    ("a key true, as written", lambda r: set_in(r, (True,), 2), ["scenario: unknown key true,", "load_steps"]),
    ("a key null, as written", lambda r: set_in(r, ("tissue", None), 2), ["tissue: unknown key null,", "thickness"]),
    ("a NUL in the name", lambda r: set_in(r, ("name",), "a\x00b"),
     ["name: got 'a\\x00b', expected a one-line string without control characters (U+0000 at character 2)"]),
    ("a line break in the name", lambda r: set_in(r, ("name",), "two\nlines"), ["name", "(U+000A at character 4)"]),
    ("a force of 1e300 N", lambda r: set_in(r, ("loads", 0, "force"), [-1e300, 0.5]),
     ["loads[0].force[0]: got -1e+300, expected a number between -1e+06 and 1e+06 (N"]),
    ("a robot base 10 km away", lambda r: set_in(r, ("robot",), {"base_transform": {"translation": [0, -1e9]}}),
     ["robot.base_transform.translation[1]: got -1000000000.0, expected a number between -10000 and 10000 (mm"]),
    ("a robot base turned 1000 deg", lambda r: set_in(r, ("robot",), {"base_transform": {"rotation_deg": 1000}}),
     ["robot.base_transform.rotation_deg: got 1000, expected a number between -360 and 360 (deg)"]),
    ("a needle turning at 1e-300 rad/s", lambda r: set_in(r, ("robot",), {"angular_speed": 1e-300}),
     ["robot.angular_speed: got 1e-300, expected a positive number of at least 1e-06 (rad/s"]),
    # from 1 up every needle step stopped before its first iteration: an exit error of 5e-16 mm
    ("a needle residual tolerance of 1", lambda r: set_in(r, ("solver",), {"needle_residual_tolerance": 1.0}),
     ["solver.needle_residual_tolerance: got 1.0, expected a positive number of at most 0.01 (a relative "
      "tolerance: a larger one leaves the tissue out of balance, from 1 up at rest)"]),
    ("a study reference spacing below 0", lambda r: set_in(r, ("study",), {"reference": {"grading": 4, "spacing": -1}}),
     ["study.reference.spacing: got -1, expected a positive number (mm) or a non-empty list of them"]),
    ("a study reference spacing list with one below 0",
     lambda r: set_in(r, ("study",), {"reference": {"spacing": [2, -1]}}),
     ["study.reference.spacing[1]: got -1, expected a positive number (mm)"]),
    ("probe outside", lambda r: set_in(r, ("probes",), [[0.0, 50.0], [120.0, 50.0]]),
     ["probes[1]", "[120.0, 50.0]", "inside [0, 100] x [0, 100] mm"]),
    ("probe below", lambda r: set_in(r, ("probes",), [[50.0, -0.5]]),
     ["probes[0]", "[50.0, -0.5]", "inside"]),
    ("zero spacing", lambda r: set_in(r, ("discretization",), {"spacing": 0}),
     ["discretization.spacing", "0", "positive number (mm)"]),
    ("dilation too small", lambda r: set_in(r, ("discretization",), {"dilation": 1.0}),
     ["discretization.dilation", "1.0", "> 1"]),
    ("zero load steps", lambda r: set_in(r, ("load_steps",), 0), ["load_steps", "0", "integer between 1"]),
    ("non-numeric size", lambda r: set_in(r, ("tissue", "size"), [100.0, "wide"]),
     ["tissue.size[1]", "'wide'", "positive number (mm)"]),
]


@pytest.mark.parametrize("mutate, fragments", [pytest.param(m, f, id=i) for i, m, f in BAD_SCENARIOS])
def test_errors_name_field_value_and_expectation(slab_raw, mutate, fragments):
    with pytest.raises(ScenarioError) as error:
        parse_scenario(mutate(slab_raw))
    message = str(error.value)
    assert "\n" not in message
    for fragment in fragments:
        assert fragment in message


def test_shipped_scenario_parses(slab_path):
    scenario = load_scenario(slab_path)
    assert scenario.tissue.size == (100.0, 100.0)
    assert scenario.tissue.clamped == ("right",)
    assert scenario.loads[0].force == (-3.0, 1.0) and scenario.loads[0].displacement is None
    assert len(scenario.probes) == 6 and scenario.load_steps == 10
    assert scenario.source_text == slab_path.read_text()


@pytest.mark.parametrize("text, fragments", [
    ("tissue: [1, 2\n  size: {\n", ["not valid YAML", "line 2"]),
    ("- 1\n- 2\n", ["scenario", "[1, 2]", "a mapping"]),
    ("", ["scenario", "an empty file", "a mapping"]),
    # a tab after a value: YAML 1.2 takes it as a space, PyYAML's reader refuses it
    ("name: slab\t# comment\n", ["line 1: a tab character", "replace the tab by spaces"]),
])
def test_bad_yaml_is_reported_with_the_file(tmp_path, text, fragments):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ScenarioError) as error:
        load_scenario(path)
    message = str(error.value)
    for fragment in fragments:
        assert fragment in message
    if "YAML" in fragments[0]:
        assert str(path) in message


def test_missing_file_is_reported(tmp_path):
    path = tmp_path / "absent.yaml"
    with pytest.raises(ScenarioError, match="absent.yaml: cannot be read"):
        load_scenario(path)


def test_default_spacing_is_a_twentieth_of_the_smaller_side(slab_raw):
    slab_raw["tissue"]["size"] = [100.0, 60.0]
    slab_raw["probes"] = []
    scenario = parse_scenario(slab_raw)
    assert "discretization" not in slab_raw
    assert scenario.discretization.spacing == pytest.approx(3.0)
    assert default_spacing(scenario.tissue, None) == pytest.approx(3.0)
    assert scenario.discretization.dilation == 2.0  # the other defaults stay


def test_default_spacing_resolves_the_needle(slab_raw):
    """With a needle the default spacing is tied to the radius and graded finer around the
    needle (the fractions are documented in config.default_spacing); with a needle larger than
    the slab the spacing is the static one, and at least eight spacings cross the smaller side."""
    from stitchplan.config.scenario import DEFAULT_NEEDLE_REFINEMENT, Material, Tissue

    tissue = Tissue((100.0, 100.0), 10.0, Material(), ("right",))

    def needle(radius: float) -> Needle:
        return Needle(radius=radius, arc=3.14159, entry=(0.0, 30.0), turn="cw", step=0.08,
                      friction=0.06, cutting_force=0.7)

    static = default_spacing(tissue, None)
    sh_needle = default_spacing(tissue, needle(8.88))  # ETHICON SH
    assert sh_needle < static
    assert 8.88 / sh_needle >= 2.0  # at least two coarse spacings across the radius
    assert default_spacing(tissue, needle(4.44)) == pytest.approx(sh_needle / 2)
    assert default_spacing(tissue, needle(400.0)) == pytest.approx(static)
    narrow = Tissue((100.0, 30.0), 10.0, Material(), ("right",))
    assert default_spacing(narrow, needle(400.0)) == pytest.approx(30.0 / 8)

    slab_raw["needle"] = {"radius": 8.88, "entry": [0.0, 30.0], "turn": "cw", "step": 0.08,
                          "friction": 0.06, "cutting_force": 0.7}
    d = parse_scenario(slab_raw).discretization
    assert d.spacing == pytest.approx(sh_needle)
    assert d.needle_spacing == pytest.approx(sh_needle / DEFAULT_NEEDLE_REFINEMENT)
    assert 8.88 / d.needle_spacing >= 4.0  # at least four spacings across the radius at the needle
    # --spacing refines the graded arrangement as a whole
    halved = with_discretization(parse_scenario(slab_raw), spacing=sh_needle / 2).discretization
    assert (halved.spacing, halved.needle_spacing) == pytest.approx((sh_needle / 2, d.needle_spacing / 2))
    # a spacing given in the file means a uniform grid unless the file asks for grading
    slab_raw["discretization"] = {"spacing": 3.0}
    assert parse_scenario(slab_raw).discretization.needle_spacing is None
    slab_raw["discretization"] = {"spacing": 3.0, "needle_refinement": 3}
    assert parse_scenario(slab_raw).discretization.needle_spacing == pytest.approx(1.0)


def test_given_spacing_wins_and_overrides_are_validated(slab_raw):
    slab_raw["discretization"] = {"spacing": 2.0}
    scenario = parse_scenario(slab_raw)
    assert scenario.discretization.spacing == 2.0
    overridden = with_discretization(scenario, spacing=4.0, dilation=None)
    assert overridden.discretization.spacing == 4.0 and overridden.discretization.dilation == 2.0
    with pytest.raises(ScenarioError, match=r"spacing: got -4\.0, expected a positive number"):
        with_discretization(scenario, spacing=-4.0)


# --- every problem of a file at once -------------------------------------------------------


def test_every_problem_of_a_file_is_reported_together(slab_raw):
    """One InputError: a line per problem, in the order of the file's blocks, each naming the
    field, the value as given and what was expected; str() is the lines joined."""
    slab_raw["tissue"]["thickness"] = -1
    slab_raw["tissue"]["material"]["model"] = "mooney-rivlin"
    slab_raw["tissue"]["clamped"] = ["right", "right"]
    slab_raw["loads"][0]["segment"] = [[10.0, 40.0], [10.0, 60.0]]
    slab_raw["loads"].append({"segment": [[0.0, 0.0], [0.0, 10.0]]})
    slab_raw["probes"][2] = [25.0, 150.0]
    slab_raw["load_steps"] = 2.5
    slab_raw["discretization"] = {"spacing": 2.0, "needle_spacing": 3.0, "dilation": 0.9}
    slab_raw["colour"] = "red"
    with pytest.raises(ScenarioError) as error:
        parse_scenario(slab_raw)
    lines = error.value.lines
    assert str(error.value) == "\n".join(lines)
    assert lines == [
        "tissue.thickness: got -1, expected a positive number (mm)",
        "tissue.material.model: got 'mooney-rivlin', expected one of saint-venant-kirchhoff, neo-hookean",
        "tissue.clamped: got ['right', 'right'], expected each edge at most once",
        ("discretization.dilation: got 0.9, expected a number > 1 (kernel support / spacing; "
         "at least ~1.5 for a linear basis, at most ~3: wider kernels make the stiffness nearly singular)"),
        ("loads[0].segment: got [[10.0, 40.0], [10.0, 60.0]], expected a non-empty straight piece of "
         "one edge of the 100 x 100 mm tissue; its end [10, 40] is off the boundary, the nearest is [0, 40], "
         "10 mm away; its end [10, 60] is off the boundary, the nearest is [0, 60], 10 mm away"),
        "loads[1]: got neither, expected exactly one of 'force' (N) or 'displacement' (mm)",
        "load_steps: got 2.5, expected an integer between 1 and 10000",
        "probes[2]: got [25.0, 150.0], expected a point inside [0, 100] x [0, 100] mm; the nearest is [25, 100], "
        "50 mm away",
        ("scenario: unknown key 'colour', expected one of: name, tissue, discretization, needle, loads, "
         "load_steps, probes, solver, planner, robot, study"),
    ]


def test_a_block_check_runs_once_its_fields_are_valid(slab_raw):
    """needle_spacing <= spacing is a check of the whole block: reported once the block's own
    fields are valid, with the field it concerns."""
    slab_raw["discretization"] = {"spacing": 2.0, "needle_spacing": 3}
    with pytest.raises(ScenarioError, match=r"^discretization.needle_spacing: got 3(\.0)?, expected a "
                                            r"spacing \(mm\) no larger than spacing = 2 mm$"):
        parse_scenario(slab_raw)


def test_the_file_path_starts_every_line(write_scenario, slab_raw):
    slab_raw["tissue"]["thickness"] = -1
    slab_raw["tissue"]["size"] = [100.0, "wide"]
    path = write_scenario(slab_raw, "scene.yaml")
    with pytest.raises(ScenarioError) as error:
        load_scenario(path)
    assert error.value.lines == [f"{path}: tissue.size[1]: got 'wide', expected a positive number (mm)",
                                 f"{path}: tissue.thickness: got -1, expected a positive number (mm)"]


def test_a_load_segment_shorter_than_the_input_tolerance_is_one_point(slab_raw):
    """Two ends 4e-15 mm apart (one vertex computed twice) were a segment: the run gave a probe
    no displacement; now one point, refused."""
    slab_raw["loads"] = [{"segment": [[100.0, 50.0], [100.0, 50.000000000000004]], "force": [1.0, 0.0]}]
    with pytest.raises(ScenarioError) as error:
        parse_scenario(slab_raw)
    assert "loads[0].segment: got [[100.0, 50.0], [100.0, 50.00000000000001]], expected a non-empty straight " \
           "piece of one edge of the 100 x 100 mm tissue (its ends are one point: 7.1e-15 mm apart" in str(error.value)


def test_a_closed_ring_outline_is_told_to_leave_out_its_last_vertex(slab_raw):
    slab_raw["tissue"].pop("size")
    slab_raw["tissue"]["outline"] = [[0, 0], [100, 0], [100, 100], [0, 100], [0, 0]]
    with pytest.raises(ScenarioError) as error:
        parse_scenario(slab_raw)
    assert error.value.lines[0].endswith("expected a polygon without repeated consecutive vertices (the last vertex "
                                         "repeats the first: the polygon closes by itself, leave the last one out)")


def test_a_holes_or_regions_unknown_keys_are_said_once_with_where_they_belong(slab_raw):
    """A hole given as {center, radius} and a region's moduli given beside it, not in its
    material: each unknown key once (they came twice, from the scenario's check and the
    shape's own, one with a hint that sent a hole's radius to the needle)."""
    slab_raw["tissue"]["holes"] = [{"center": [30.0, 15.0], "radius": 3.0}]
    slab_raw["tissue"]["regions"] = [{"polygon": [[10, 10], [20, 10], [20, 20], [10, 20]], "lame_mu": 1.2}]
    with pytest.raises(ScenarioError) as error:
        parse_scenario(slab_raw)
    circle = "expected one of: polygon, circle (a circle is given as circle: {center: [x, y], radius: r})"
    assert error.value.lines == [
        f"tissue.holes[0]: unknown key 'center', {circle}",
        f"tissue.holes[0]: unknown key 'radius', {circle}",
        "tissue.regions[0].material: missing, required: a mapping with keys among: model, lame_lambda, lame_mu",
        "tissue.regions[0]: unknown key 'lame_mu', expected one of: material, polygon, circle "
        "('lame_mu' belongs in material)"], error.value.lines


@pytest.mark.parametrize("shape", [{"size": [0.06, 0.03]},
                                   {"outline": [[0.0, 0.0], [0.06, 0.0], [0.06, 0.03], [0.0, 0.03]]}])
def test_a_tissue_written_in_metres_is_refused(slab_raw, shape):
    """A 6 x 3 cm block written in m ran on a 60 um speck, stretched to 16 times its size."""
    slab_raw["tissue"].pop("size")
    slab_raw["tissue"].update(shape)
    slab_raw["probes"], slab_raw["loads"] = [], [{"segment": [[0.06, 0.0], [0.06, 0.03]], "force": [1.0, 0.0]}]
    with pytest.raises(ScenarioError) as error:
        parse_scenario(slab_raw)
    (name,) = shape
    assert error.value.lines[0].startswith(f"tissue.{name}: got ")
    assert error.value.lines[0].endswith("expected a tissue at least 0.5 mm across (mm; a smaller one is a tissue "
                                         "written in m)")


@pytest.mark.parametrize("probe, placed", [
    ([100.0000001, 25.0], (100.0, 25.0)), ([100.00000001, 25.0], (100.0, 25.0)), ([-1e-7, 25.0], (0.0, 25.0)),
    ([50.0, 100.0000001], (50.0, 100.0)), ([100.0009, 25.0], (100.0, 25.0)), ([99.99999999, 25.0], (99.99999999, 25.0)),
])
def test_probes_just_outside_are_placed_on_the_boundary(slab_raw, probe, placed):
    """A probe within the input tolerance (1 um) outside the tissue is moved onto its boundary,
    also where it lies within round-off's tolerance of it (1e-7 mm out: kept as given, it was
    outside the tissue the model checks, and `deform` stopped with a traceback)."""
    slab_raw["probes"] = [probe]
    assert parse_scenario(slab_raw).probes == (placed,)


@pytest.mark.parametrize("value, shown", [
    (float("nan"), "nan"), (float("inf"), "inf"), (True, "true"), ("10", "'10'"), (None, "null"),
    ([10.0], "[10.0]"),
])
def test_numbers_are_finite_numbers(slab_raw, value, shown):
    slab_raw["tissue"]["thickness"] = value
    with pytest.raises(ScenarioError) as error:
        parse_scenario(slab_raw)
    assert str(error.value) == f"tissue.thickness: got {shown}, expected a positive number (mm)"


@pytest.mark.parametrize("text, shown", [(".nan", "nan"), ("-.inf", "-inf"), ("yes", "'yes'"), ("'3'", "'3'")])
def test_yaml_spellings_of_non_numbers_are_refused(write_scenario, slab_raw, text, shown):
    path = write_scenario(slab_raw)
    path.write_text(path.read_text().replace("thickness: 10.0", f"thickness: {text}"))
    with pytest.raises(ScenarioError, match=rf"tissue.thickness: got {shown}, expected a positive"):
        load_scenario(path)


@pytest.mark.parametrize("value", [2.0, True, "2", 0, 11])
def test_integers_are_integers(slab_raw, value):
    slab_raw["discretization"] = {"quadrature_order": value}
    with pytest.raises(ScenarioError, match="discretization.quadrature_order: got .*, expected an integer "
                                            "between 1 and 10"):
        parse_scenario(slab_raw)


def test_unknown_key_suggests_the_close_one(slab_raw):
    slab_raw["tissue"]["thicknes"] = slab_raw["tissue"].pop("thickness")
    with pytest.raises(ScenarioError) as error:
        parse_scenario(slab_raw)
    # one mistake, one line: the misspelt key says that the key it is close to is missing
    assert error.value.lines == [
        ("tissue: unknown key 'thicknes', expected one of: size, thickness, material, clamped, "
         "outline, holes, regions (did you mean 'thickness'? tissue.thickness is missing)"),
    ]


def test_a_key_of_another_block_is_sent_there_not_to_a_near_spelling(slab_raw):
    """`dilation` under needle is close to no needle key but 'friction' by spelling; it
    belongs in discretization, and the line says so (at the top level too)."""
    slab_raw["tissue"]["dilation"] = 3.0
    slab_raw["max_step_cuts"] = 4
    with pytest.raises(ScenarioError) as error:
        parse_scenario(slab_raw)
    assert sorted(error.value.lines) == [
        ("scenario: unknown key 'max_step_cuts', expected one of: name, tissue, discretization, needle, loads, "
         "load_steps, probes, solver, planner, robot, study ('max_step_cuts' belongs in solver)"),
        ("tissue: unknown key 'dilation', expected one of: size, thickness, material, clamped, outline, holes, "
         "regions ('dilation' belongs in discretization)"),
    ]


def test_long_values_are_shortened(slab_raw):
    slab_raw["tissue"]["clamped"] = "right " * 100
    with pytest.raises(ScenarioError) as error:
        parse_scenario(slab_raw)
    line = str(error.value)
    # cut between words, the string's quote closed
    assert line.startswith("tissue.clamped: got 'right right") and " right ...', expected a list of edges" in line
    assert len(line) < 160


def test_a_null_block_keeps_the_defaults(slab_raw):
    slab_raw.update(solver=None, planner=None, robot=None, study=None, needle=None, discretization=None)
    scenario = parse_scenario(slab_raw)
    assert scenario.needle is None and scenario.study is None
    assert scenario.discretization.spacing == pytest.approx(5.0)  # min(W, H) / 20


def test_robot_block_reads_the_base_transform(slab_raw):
    from stitchplan.config import Robot

    slab_raw["robot"] = {"base_transform": {"rotation_deg": 90, "translation": [400, 120]}, "angular_speed": 0.5}
    assert parse_scenario(slab_raw).robot == Robot(90.0, (400.0, 120.0), 0.5, given=True)
    slab_raw["robot"] = {"angular_speed": 0.5}
    assert parse_scenario(slab_raw).robot == Robot(angular_speed=0.5)
    slab_raw["robot"] = {"rotation_deg": 90}
    with pytest.raises(ScenarioError, match="robot: unknown key 'rotation_deg', expected one of: "
                                            "base_transform, angular_speed"):
        parse_scenario(slab_raw)


def test_robot_block_takes_the_bounds_of_the_options(slab_raw):
    """The file's robot block accepts what --base-transform and --angular-speed accept, up to
    their bounds (the Robot held inside is not bounded: planning.trajectory is the backstop)."""
    from stitchplan.config import Robot
    from stitchplan.config.plan_blocks import MAX_BASE_OFFSET_MM, MAX_BASE_ROTATION_DEG, MIN_ANGULAR_SPEED

    slab_raw["robot"] = {"base_transform": {"rotation_deg": -MAX_BASE_ROTATION_DEG,
                                            "translation": [MAX_BASE_OFFSET_MM, -MAX_BASE_OFFSET_MM]},
                         "angular_speed": MIN_ANGULAR_SPEED}
    assert parse_scenario(slab_raw).robot == Robot(-360.0, (1e4, -1e4), 1e-6, given=True)
    assert Robot(angular_speed=5e-324, translation=(1e308, 0.0)).angular_speed == 5e-324


def test_a_name_may_hold_any_printable_text(slab_raw):
    slab_raw["name"] = "\u202e \u00e9vil \u2014 na\u00efve \U0001f9f5"  # format characters (Cf) are not Cc
    assert parse_scenario(slab_raw).name == slab_raw["name"]


# --- typed objects: construction validates, replace and asdict work ------------------------------


def test_blocks_are_typed_frozen_hashable_and_replace_revalidates(slab_raw):
    import dataclasses
    import pickle

    from pydantic import ValidationError

    scenario = parse_scenario(slab_raw)
    assert isinstance(scenario.tissue.size, tuple) and all(type(v) is float for v in scenario.tissue.size)
    assert all(type(v) is float for p in scenario.probes for v in p)
    assert type(scenario.load_steps) is int and isinstance(scenario.loads, tuple)
    assert scenario.tissue.domain.size == (100.0, 100.0)
    assert hash(scenario) == hash(parse_scenario(slab_raw))
    assert pickle.loads(pickle.dumps(scenario)) == scenario
    assert dataclasses.asdict(scenario.tissue)["material"]["lame_mu"] == pytest.approx(0.147688)
    with pytest.raises(dataclasses.FrozenInstanceError):
        scenario.tissue.thickness = 1.0
    thinner = dataclasses.replace(scenario, tissue=dataclasses.replace(scenario.tissue, thickness=5.0))
    assert thinner.tissue.thickness == 5.0 and thinner.loads == scenario.loads
    with pytest.raises(ValidationError):
        dataclasses.replace(scenario.tissue, thickness=-5.0)
    with pytest.raises(ValidationError):  # the loads no longer on an edge of the smaller tissue
        dataclasses.replace(scenario, tissue=dataclasses.replace(scenario.tissue, size=(50.0, 50.0)))


def test_a_load_constructed_in_python_needs_exactly_one_kind():
    from pydantic import ValidationError

    from stitchplan.config import Load

    assert Load(((0.0, 0.0), (0.0, 1.0)), force=(1, 2)).force == (1.0, 2.0)
    for kinds in ({}, {"force": (1.0, 0.0), "displacement": (0.0, 1.0)}):
        with pytest.raises(ValidationError, match="exactly one of 'force'"):
            Load(((0.0, 0.0), (0.0, 1.0)), **kinds)


def test_replaced_is_a_validated_copy_and_as_input_round_trips():
    from stitchplan.config import Discretization, parse_discretization

    graded = parse_discretization({"spacing": 4.0, "needle_refinement": 2})
    assert graded.needle_spacing == 2.0
    assert parse_discretization(graded.as_input()) == graded
    assert graded.replaced(spacing=2.0).needle_spacing == 1.0  # derived: follows the spacing
    assert graded.replaced(needle_spacing=None, needle_refinement=None).needle_spacing is None
    assert Discretization(spacing=3.0).replaced(dilation=1.5) == Discretization(spacing=3.0, dilation=1.5)
    with pytest.raises(ScenarioError) as error:
        graded.replaced(path="study 'a'", dilation=0.5, basis_order=3)
    assert error.value.lines == [
        ("study 'a'.dilation: got 0.5, expected a number > 1 (kernel support / spacing; "
         "at least ~1.5 for a linear basis, at most ~3: wider kernels make the stiffness nearly singular)"),
        "study 'a'.basis_order: got 3, expected an integer between 1 and 2"]


# --- YAML reading ---------------------------------------------------------------------------


@pytest.mark.parametrize("text, fragment", [
    ("tissue: {size: [1, 2]}\nname: a\ntissue: {}\n",
     "line 3: duplicate key 'tissue' (first given at line 1), expected each key once"),
    ("tissue: {size: [1, 2], size: [3, 4]}\n", "line 1: duplicate key 'size' (first given at line 1)"),
    ("a: &a [*a]\n", "line 1: a recursive YAML alias, expected plain data"),
    ("b: &b [1]\nc: [" + ", ".join(["*b"] * 101) + "]\n", "line 2: more than 100 YAML aliases"),
    ("tissue: !!python/object:os.system {}\n", "not valid YAML at line 1"),
])
def test_yaml_files_are_plain_data(tmp_path, text, fragment):
    path = tmp_path / "scene.yaml"
    path.write_text(text)
    with pytest.raises(ScenarioError) as error:
        load_scenario(path)
    # the first line says it (a duplicate key's is followed by the problems of the data with the
    # key's last value: a tissue without thickness or material here)
    lines = error.value.lines
    assert all(line.startswith(f"{path}: ") for line in lines) and fragment in lines[0]
    assert len(lines) == 1 or "duplicate key" in lines[0]


def test_an_alias_bomb_is_one_short_line(tmp_path):
    """Nine levels of ten aliases would expand to 10^10 values: refused before they are built."""
    import time

    lines = ["a0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    lines += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]" for i in range(1, 10)]
    path = tmp_path / "bomb.yaml"
    path.write_text("\n".join(lines) + "\n")
    start = time.perf_counter()
    with pytest.raises(ScenarioError) as error:
        load_scenario(path)
    assert time.perf_counter() - start < 1.0
    assert str(error.value) == f"{path}: line 5: YAML aliases expand to more than 100000 values, expected plain data"


def test_a_few_aliases_are_fine_and_merge_keys_are_refused(tmp_path, slab_raw):
    """An alias stands for a whole value; YAML 1.1's merge key `<<` is refused (YAML 1.2 has
    none, and the keys it merges give way silently to the mapping's own: tests/test_yaml_files.py)."""
    path = tmp_path / "scene.yaml"
    text = ("tissue:\n  size: &square [100.0, 100.0]\n  thickness: 10.0\n"
            "  material: &phantom {lame_lambda: 0.19, lame_mu: 0.15}\n  clamped: [right]\n"
            "probes: [[0.0, 50.0]]\n"
            "loads:\n  - &pull {segment: [[0.0, 40.0], [0.0, 60.0]], force: &force [1.0, 0.0]}\n"
            "  - {segment: [[0.0, 60.0], [0.0, 70.0]], force: *force}\n")
    path.write_text(text)
    scenario = load_scenario(path)
    assert [load.force for load in scenario.loads] == [(1.0, 0.0), (1.0, 0.0)]
    assert scenario.loads[1].segment == ((0.0, 60.0), (0.0, 70.0))
    path.write_text(text.replace("{segment: [[0.0, 60.0]", "{<<: *pull, segment: [[0.0, 60.0]"))
    with pytest.raises(ScenarioError) as error:
        load_scenario(path)
    assert error.value.lines == [f"{path}: line 9: merge key '<<' in loads[1] (YAML 1.1; files are read as YAML 1.2, "
                                 "which has no merge keys), expected the keys written out in this mapping (an alias "
                                 "such as `material: *phantom` may still stand for a whole value)"]


def test_a_file_that_is_not_utf8_is_named(tmp_path):
    path = tmp_path / "latin1.yaml"
    path.write_bytes("name: café\n".encode("latin-1"))
    with pytest.raises(ScenarioError) as error:
        load_scenario(path)
    assert str(error.value) == f"{path}: not UTF-8 text (byte 0xe9 at offset 9), expected a YAML text file"


def test_a_utf8_byte_order_mark_is_fine(tmp_path, slab_path):
    path = tmp_path / "bom.yaml"
    path.write_bytes(b"\xef\xbb\xbf" + slab_path.read_bytes())
    assert load_scenario(path).tissue.size == (100.0, 100.0)


# --- the config layer stands on errors and geometry only ------------------------------------------


def test_config_imports_no_layer_above_it():
    """Importing stitchplan.config (each of its modules first, so a cycle would show) loads no
    stitchplan module outside errors, geometry and config."""
    import subprocess
    import sys

    modules = ["fields", "messages", "yaml_files", "boundary_points", "tissue_shape", "blocks", "load_checks",
               "study", "scenario", "schema", "calibration", "uncertainty"]
    for module in modules:
        code = (f"import sys, stitchplan.config.{module}\n"
                "print(sorted(m for m in sys.modules if m.startswith('stitchplan')))")
        loaded = eval(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                     check=True).stdout)
        outside = [m for m in loaded if m not in ("stitchplan", "stitchplan.errors", "stitchplan.geometry")
                   and not m.startswith(("stitchplan.config", "stitchplan.geometry."))]
        assert outside == [], (module, outside)


# --- points typed on the boundary ------------------------------------------------------------------

# a block whose top edge slants from (40, 20) to (0, 30) (the line x + 4 y = 120): no point of it
# but its ends has short decimal coordinates, so every point typed on it is a little off it
SLANT_TISSUE = {"outline": [[0, 0], [40, 0], [40, 20], [0, 30]], "thickness": 10.0,
                "material": {"lame_lambda": 0.189151, "lame_mu": 0.147688},
                "clamped": [{"segment": [[0, 0], [40, 0]]}]}
SLANT_NEEDLE = {"radius": 5.0, "entry": [13.3333, 26.6667], "turn": "cw", "step": 0.1}
SLANT_NORMAL = np.array([1.0, 4.0]) / math.sqrt(17.0)
NEAREST = re.compile(r"the nearest is \[([-0-9.]+), ([-0-9.]+)\], ([0-9.e+-]+) mm away")


def slant(**blocks) -> dict:
    return copy.deepcopy({"tissue": SLANT_TISSUE, **blocks})


def off_slant(point) -> float:
    """Signed distance (mm) of a point from the slanted edge's line, > 0 outside the block."""
    return float(np.dot(point, SLANT_NORMAL) - 120.0 / math.sqrt(17.0))


@pytest.mark.parametrize("entry", [[13.3333, 26.6667], [13.333333, 26.666667], [13.3337, 26.6663],
                                   [20.0004, 25.0]])
def test_an_entry_typed_on_a_slanted_edge_is_moved_onto_it(entry):
    """[13.3333, 26.6667] is 2.43e-5 mm off the edge, [13.333333, 26.666667] 2.4e-7 mm: both were
    refused, told of a nearest point that printed as the point given. Within a micrometre the
    entry is the boundary point nearest it, and the run uses that point."""
    scenario = parse_scenario(slant(needle={**SLANT_NEEDLE, "entry": entry}))
    used = np.asarray(scenario.needle.entry)
    assert 0 < abs(off_slant(entry)) <= 1e-3
    assert abs(off_slant(used)) <= scenario.tissue.domain.tolerance
    np.testing.assert_allclose(used, np.asarray(entry) - off_slant(entry) * SLANT_NORMAL, rtol=0, atol=1e-12)


def test_a_point_typed_on_a_circular_holes_wall_is_on_it():
    """A hole's wall point at 30 deg typed to the micrometre, [35.196, 18.0], is 1.5e-4 mm off
    the hole's 96-gon: it is the 96-gon's vertex there."""
    from stitchplan.geometry.polygons import circle_polygon

    raw = {"tissue": {"size": [60.0, 40.0], "thickness": 10.0, "material": {"lame_lambda": 0.19, "lame_mu": 0.15},
                      "holes": [{"circle": {"center": [30.0, 15.0], "radius": 6.0}}], "clamped": ["left"]},
           "needle": {"radius": 8.0, "entry": [35.196, 18.0], "turn": "cw", "step": 0.1},
           "loads": [{"segment": [[35.196, 18.0], [35.093, 18.167]], "force": [0.0, 1.0]}]}  # to mid-edge
    scenario = parse_scenario(raw)
    vertices = circle_polygon([30.0, 15.0], 6.0)
    assert scenario.needle.entry == tuple(vertices[8]) and scenario.loads[0].segment[0] == tuple(vertices[8])
    end = np.asarray(scenario.loads[0].segment[1])
    assert scenario.tissue.domain.segment_edge(vertices[8], end) is not None
    assert 0 < np.linalg.norm(end - [35.093, 18.167]) <= 1e-3


@pytest.mark.parametrize("field", ["needle.entry", "loads[0].segment", "tissue.clamped[1].segment", "probes[0]"])
def test_the_nearest_point_told_for_a_point_off_the_boundary_is_accepted_pasted_back(field):
    """[13.3, 26.7] lies 0.0243 mm outside the slanted edge: refused, naming the nearest
    boundary point to the nanometre; that point, pasted into the file, is accepted."""
    far, other = [13.3, 26.7], [26.6667, 23.3333]
    raw = slant(needle=dict(SLANT_NEEDLE), probes=[[20.0, 10.0]])

    def place(point):
        if field == "needle.entry":
            raw["needle"]["entry"] = point
        elif field == "loads[0].segment":
            raw["loads"] = [{"segment": [point, other], "force": [0.0, -1.0]}]
        elif field == "tissue.clamped[1].segment":
            raw["tissue"]["clamped"][1:] = [{"segment": [point, other]}]
        else:
            raw["probes"] = [point]

    place(far)
    with pytest.raises(ScenarioError) as error:
        parse_scenario(raw)
    [line] = error.value.lines
    assert line.startswith(f"{field}: got [")
    x, y, distance = (float(value) for value in NEAREST.search(line).groups())
    assert distance == pytest.approx(off_slant(far), rel=1e-2) and abs(off_slant([x, y])) < 1e-6
    place([x, y])
    scenario = parse_scenario(raw)
    assert scenario.tissue.domain.distance(np.array([x, y])) < 1e-6


def test_a_point_typed_next_to_a_corner_is_the_corner(slab_raw):
    """Snapping cannot slide an entry along an edge to within a hair of a corner: a point within
    the tolerance of a vertex is the vertex, so the entry is refused as a corner and a segment
    typed there ends at the corner."""
    slab_raw["needle"] = {"radius": 8.88, "entry": [0.0004, 99.9997], "turn": "cw", "step": 0.08}
    with pytest.raises(ScenarioError) as error:
        parse_scenario(slab_raw)
    assert error.value.lines == ["needle.entry: got [0.0004, 99.9997], 0.0005 mm from the corner [0, 100], expected "
                                 "a point inside one edge (the entry normal is undefined at a corner; a point within "
                                 "0.001 mm of a vertex is the vertex)"]
    slab_raw["needle"]["entry"] = [0.0, 30.0]
    slab_raw["loads"][0]["segment"] = [[0.0003, 99.9998], [0.0, 60.0]]
    assert parse_scenario(slab_raw).loads[0].segment == ((0.0, 100.0), (0.0, 60.0))


def test_a_load_typed_on_a_clamped_slanted_edge_meets_the_clamp():
    """Both typed by hand on the slanted edge: moved onto it, the load is on the clamp and
    refused as such (the clamp's segment unmoved, they would not be seen to overlap)."""
    raw = slant(loads=[{"segment": [[33.3333, 21.6667], [26.6667, 23.3333]], "force": [0.0, -1.0]}])
    raw["tissue"]["clamped"].append({"segment": [[40.0, 20.0], [6.6667, 28.3333]]})
    with pytest.raises(ScenarioError) as error:
        parse_scenario(raw)
    assert error.value.lines == ["loads[0].segment: got [[33.333294, 21.666676], [26.666706, 23.333324]], expected "
                                 "a segment off the clamped edges (the clamped[1] segment edge is clamped: it neither "
                                 "moves nor takes a load; remove it from tissue.clamped or move the load)"]


def test_moved_points_are_logged_and_exact_ones_kept_to_the_bit(slab_raw, caplog):
    """A move within the rounding of the digits given is logged at INFO, a larger one at
    WARNING; a point on the boundary as given is kept as it is and not logged."""
    import logging

    caplog.set_level(logging.INFO, logger="stitchplan")
    scenario = parse_scenario(slab_raw)
    assert scenario.loads[0].segment == ((0.0, 40.0), (0.0, 60.0)) and not caplog.records
    raw = slant(needle={**SLANT_NEEDLE, "entry": [13.3337, 26.6663]},
                loads=[{"segment": [[33.3333, 21.6667], [26.6667, 23.3333]], "force": [0.0, -1.0]}])
    parse_scenario(raw)
    records = [(r.levelname, r.getMessage()) for r in caplog.records]
    assert records[0] == ("WARNING", "needle.entry: [13.3337, 26.6663] lies 0.000267 mm off the boundary of the "
                          "polygon tissue (4 vertices); the run uses [13.333765, 26.666559] on it (more than the "
                          "rounding of the digits given)")
    assert [(level, message.split(":")[0]) for level, message in records[1:]] == [
        ("INFO", "loads[0].segment[0]"), ("INFO", "loads[0].segment[1]")]


# --- magnitudes that are unit mistakes --------------------------------------------------------------

THICKNESS = "a number between 0.001 and 10000 (mm; a thinner or thicker slab is a unit mistake)"
CUTTING = "a number between 0 and 1e+06 (N; a larger force at the needle's tip is a unit mistake)"
FRICTION = "a number between 0 and 1e+06 (N/mm; a larger force on each millimetre of needle is a unit mistake)"


@pytest.mark.parametrize("path, value, line", [
    (("tissue", "thickness"), 1e300, f"tissue.thickness: got 1e+300, expected {THICKNESS}"),
    (("tissue", "thickness"), 1e-300, f"tissue.thickness: got 1e-300, expected {THICKNESS}"),
    (("tissue", "thickness"), 20000, f"tissue.thickness: got 20000, expected {THICKNESS}"),
    (("needle", "cutting_force"), 1e7, f"needle.cutting_force: got 10000000.0, expected {CUTTING}"),
    (("needle", "friction"), 1e7, f"needle.friction: got 10000000.0, expected {FRICTION}"),
])
def test_thickness_and_needle_forces_beyond_any_tissue_are_unit_mistakes(slab_raw, path, value, line):
    """As a load's force beyond 1e6 N: before, 1e300 mm or 1e-300 mm thickness and a 1e7 N
    cutting force ran into a failed first step that named no field."""
    slab_raw["needle"] = {"radius": 8.88, "entry": [0.0, 30.0], "turn": "cw", "step": 0.08}
    set_in(slab_raw, path, value)
    slab_raw["tissue"]["material"]["lame_mu"] = -1.0  # reported with the other problems of the file
    with pytest.raises(ScenarioError) as error:
        parse_scenario(slab_raw)
    assert error.value.lines[:1] == ["tissue.material.lame_mu: got -1.0, expected a positive number (MPa)"]
    assert line in error.value.lines and len(error.value.lines) == 2


def test_the_magnitude_bounds_admit_their_ends_and_python_callers(slab_raw):
    """The bounds are of the files; the numerics' own checks of overflowing loads construct
    blocks beyond them in Python (tests/test_stability.py)."""
    from stitchplan.config import Material, Tissue
    from stitchplan.config.schema import scenario_schema

    slab_raw["needle"] = {"radius": 8.88, "entry": [0.0, 30.0], "turn": "cw", "step": 0.08,
                          "friction": 1e6, "cutting_force": 1e6}
    for thickness in (1e-3, 1e4):
        slab_raw["tissue"]["thickness"] = thickness
        assert parse_scenario(slab_raw).tissue.thickness == thickness
    assert Needle(radius=8.88, entry=(0.0, 30.0), turn="cw", step=0.08, friction=1e200).friction == 1e200
    assert Tissue((100.0, 100.0), 1e-300, Material(), ("right",)).thickness == 1e-300
    definitions = scenario_schema()["$defs"]
    assert definitions["Tissue"]["properties"]["thickness"]["maximum"] == 1e4
    assert definitions["Needle"]["properties"]["friction"]["maximum"] == 1e6
    assert definitions["Needle"]["properties"]["cutting_force"]["maximum"] == 1e6


MODULUS = ("a number between 1e-06 and 1e+06 (MPa; below 1e-06, 1 Pa, softer than any tissue, or beyond 1e+06, "
           "1 TPa, stiffer than diamond, is a unit mistake)")
LAMBDA = "a non-negative number of at most 1e+06 (MPa; beyond it, 1 TPa, stiffer than diamond, is a unit mistake)"


@pytest.mark.parametrize("path, value, line", [
    (("tissue", "material", "lame_lambda"), 1e300, f"tissue.material.lame_lambda: got 1e+300, expected {LAMBDA}"),
    (("tissue", "material", "lame_lambda"), 1e7, f"tissue.material.lame_lambda: got 10000000.0, expected {LAMBDA}"),
    (("tissue", "material", "lame_mu"), 1e300, f"tissue.material.lame_mu: got 1e+300, expected {MODULUS}"),
    (("tissue", "material", "lame_mu"), 1e-300, f"tissue.material.lame_mu: got 1e-300, expected {MODULUS}"),
    (("tissue", "regions", 0, "material", "lame_mu"), 1e300,
     f"tissue.regions[0].material.lame_mu: got 1e+300, expected {MODULUS}"),
])
def test_moduli_beyond_any_tissue_are_unit_mistakes(slab_raw, path, value, line):
    """Before, a modulus of 1e300 MPa (or lame_lambda 1e7) failed Newton's first load step and
    a lame_mu of 1e-300 inverted the slab there, naming no field."""
    slab_raw["tissue"]["regions"] = [{"polygon": [[40, 40], [60, 40], [60, 60], [40, 60]],
                                      "material": {"lame_lambda": 0.2, "lame_mu": 0.1}}]
    set_in(slab_raw, path, value)
    with pytest.raises(ScenarioError) as error:
        parse_scenario(slab_raw)
    assert error.value.lines == [line]


def test_the_moduli_bounds_admit_their_ends_and_any_small_lambda(slab_raw):
    from stitchplan.config import Material

    # a calibration's linear grid from 0 may fit a lame_lambda below 1e-6: its file must load
    for lame_lambda, lame_mu in ((0, 1e-6), (1e-6, 1e6), (1e6, 1e-6), (3e-9, 0.1)):
        slab_raw["tissue"]["material"].update(lame_lambda=lame_lambda, lame_mu=lame_mu)
        assert parse_scenario(slab_raw).tissue.material.lame_mu == lame_mu
    assert Material(lame_mu=1e300).lame_mu == 1e300  # Python callers (an uncertainty's samples) may


def test_a_calibration_files_thickness_has_the_same_bounds():
    from stitchplan.config.calibration import parse_calibration

    raw = {"tissue": {"size": [100.0, 60.0], "thickness": 1e300, "clamped": ["right"]},
           "experiments": [{"loads": [{"segment": [[0.0, 24.0], [0.0, 36.0]], "force": [2.0, 1.0]}],
                            "markers": "markers.csv"}],
           "fit": {"lame_lambda": [0.01, 2.0], "lame_mu": [0.01, 2.0]}}
    with pytest.raises(ScenarioError) as error:
        parse_calibration(raw)
    assert error.value.lines == [f"tissue.thickness: got 1e+300, expected {THICKNESS}"]


def test_loads_apart_are_not_compared_pair_by_pair(monkeypatch, slab_raw):
    """Every pair of loads was compared: a file of 2000 loads took 45 s to read. Only loads whose
    segments' boxes come within the tolerance of each other are, with the same verdicts."""
    from stitchplan.config import load_checks

    compared = []
    shared_length = load_checks.shared_length
    monkeypatch.setattr(load_checks, "shared_length", lambda a, b, tol: compared.append(1) or shared_length(a, b, tol))
    slab_raw["loads"] = [{"segment": [[0.0, 0.5 * i], [0.0, 0.5 * i + 0.25]], "force": [0.01, 0.0]} for i in range(200)]
    assert len(parse_scenario(slab_raw).loads) == 200
    assert len(compared) == 200  # each against the clamped right edge alone (before: 20100)
    slab_raw["loads"].append({"segment": [[0.0, 99.6], [0.0, 99.8]], "force": [0.01, 0.0]})  # over loads[199]
    with pytest.raises(ScenarioError) as error:
        parse_scenario(slab_raw)
    assert error.value.lines == ["loads[200].segment: got [[0.0, 99.6], [0.0, 99.8]], expected a segment sharing at "
                                 "most an end point with loads[199].segment [[0.0, 99.5], [0.0, 99.75]] (they share "
                                 "0.15 mm; one load would overrule the other there)"]
