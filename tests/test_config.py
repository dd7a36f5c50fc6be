"""Scenario parsing: every user error names the field, the value received and what was
expected; defaults and overrides of the discretization."""

from __future__ import annotations

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
    ("missing tissue", lambda r: drop(r, ("tissue",)), ["scenario.tissue", "missing", "required"]),
    ("unknown top-level key", lambda r: set_in(r, ("load_step",), 5),
     ["scenario", "unknown key 'load_step'", "load_steps"]),
    ("unknown tissue key", lambda r: set_in(r, ("tissue", "colour"), "red"),
     ["tissue", "unknown key 'colour'", "size, thickness, material, clamped"]),
    ("negative lame_mu", lambda r: set_in(r, ("tissue", "material", "lame_mu"), -0.1),
     ["tissue.material.lame_mu", "-0.1", "positive number (MPa)"]),
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
    ("", ["scenario", "None", "a mapping"]),
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
