"""The JSON Schema of scenario files (`stitchplan schema`): it names every key a file may
have, refuses unknown ones, lists the choices, says each field's unit, and the shipped
scenarios satisfy it (checked by a small validator of the schema subset below, and by
jsonschema when it is installed)."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest
import yaml

from stitchplan.config import (
    EDGES,
    INTEGRATIONS,
    LINEAR_SOLVERS,
    MATERIAL_MODELS,
    TIP_TRACKING,
    ScenarioError,
    load_scenario,
    scenario_schema,
)
from stitchplan.config.scenario import parse_scenario

CONFIGS = sorted((Path(__file__).resolve().parents[1] / "configs").glob("*.yaml"))
TOP_LEVEL = ["name", "tissue", "discretization", "needle", "loads", "load_steps", "probes", "solver",
             "planner", "robot", "study"]


@pytest.fixture(scope="module")
def schema() -> dict:
    return scenario_schema()


def resolve(schema: dict, node: dict) -> dict:
    while "$ref" in node:
        node = schema["$defs"][node["$ref"].rsplit("/", 1)[1]]
    return node


def problems(schema: dict, node: dict, value, path: str = "scenario") -> list[str]:
    """Where `value` breaks `node`: the keywords pydantic's schemas use ($ref, anyOf, type,
    enum, properties, required, additionalProperties, items, prefixItems, min/maxItems,
    minimum, maximum, exclusiveMinimum, minLength) and the blocks add (oneOf of required
    keys that are not null, uniqueItems)."""
    node = resolve(schema, node)
    if "not" in node:
        return [] if problems(schema, node["not"], value, path) else [f"{path}: matches what is forbidden"]
    if "oneOf" in node and isinstance(value, dict):
        matching = [option for option in node["oneOf"] if not problems(schema, option, value, path)]
        if len(matching) != 1:
            return [f"{path}: matches {len(matching)} of oneOf {[option['required'] for option in node['oneOf']]}"]
    if "anyOf" in node:
        options = [problems(schema, option, value, path) for option in node["anyOf"]
                   if value is None or option.get("type") != "null"]
        return [] if any(not found for found in options) else min(options, key=len)
    kinds = {"object": dict, "array": list, "string": str, "boolean": bool, "null": type(None)}
    kind = node.get("type")
    if kind in ("number", "integer"):
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        if not ok or (kind == "integer" and not isinstance(value, int)):
            return [f"{path}: not {kind}"]
    elif kind is not None and not isinstance(value, kinds[kind]):
        return [f"{path}: not {kind}"]
    found = []
    if "enum" in node and value not in node["enum"]:
        found.append(f"{path}: {value!r} not in {node['enum']}")
    for keyword, broken in (("minimum", lambda b: value < b), ("maximum", lambda b: value > b),
                            ("exclusiveMinimum", lambda b: value <= b),
                            ("minLength", lambda b: len(value) < b),
                            ("minItems", lambda b: len(value) < b), ("maxItems", lambda b: len(value) > b)):
        if keyword in node and broken(node[keyword]):
            found.append(f"{path}: breaks {keyword} {node[keyword]}")
    if node.get("uniqueItems") and len({json.dumps(item, sort_keys=True) for item in value}) < len(value):
        found.append(f"{path}: breaks uniqueItems")
    if isinstance(value, dict):
        properties = node.get("properties", {})
        found += [f"{path}.{key}: required" for key in node.get("required", []) if key not in value]
        for key, item in value.items():
            if key in properties:
                found += problems(schema, properties[key], item, f"{path}.{key}")
            elif node.get("additionalProperties") is False:
                found.append(f"{path}.{key}: unknown key")
    if isinstance(value, list):
        prefix = node.get("prefixItems", [])
        for i, item in enumerate(value):
            item_schema = prefix[i] if i < len(prefix) else node.get("items")
            if item_schema is not None:
                found += problems(schema, item_schema, item, f"{path}[{i}]")
    return found


def objects(schema: dict):
    """Every object schema: the root and each definition."""
    yield "scenario", schema
    yield from schema["$defs"].items()


def test_schema_is_json_with_a_title_and_every_top_level_key(schema):
    assert json.loads(json.dumps(schema)) == schema
    assert schema["title"] == "stitchplan scenario" and "2020-12" in schema["$schema"]
    assert list(schema["properties"]) == TOP_LEVEL
    assert schema["required"] == ["tissue"]


def test_every_block_refuses_unknown_keys_and_describes_its_fields(schema):
    for name, node in objects(schema):
        assert node["type"] == "object" and node["additionalProperties"] is False, name
        for key, field in node["properties"].items():
            assert field.get("description"), f"{name}.{key} has no description"


@pytest.mark.parametrize("path, choices", [
    (("tissue", "material", "model"), MATERIAL_MODELS),
    (("tissue", "clamped", "items"), EDGES),
    (("needle", "turn"), ("cw", "ccw")),
    (("needle", "tip_tracking"), TIP_TRACKING),
    (("needle", "linear_solver"), LINEAR_SOLVERS),
    (("discretization", "integration"), INTEGRATIONS),
])
def test_choices_are_enums(schema, path, choices):
    node = schema
    for key in path:
        node = resolve(schema, node)
        node = node["items"] if key == "items" else node["properties"][key]
        if "anyOf" in node:
            node = next(option for option in node["anyOf"] if option.get("type") != "null")
    assert sorted(resolve(schema, node)["enum"]) == sorted(choices)


@pytest.mark.parametrize("path, unit", [
    (("tissue", "size"), "mm"), (("tissue", "thickness"), "mm"), (("tissue", "material", "lame_mu"), "MPa"),
    (("needle", "step"), "rad"), (("needle", "friction"), "N per mm"), (("needle", "cutting_force"), "N"),
    (("discretization", "spacing"), "mm"),
])
def test_descriptions_give_units(schema, path, unit):
    node = schema
    for key in path:
        node = resolve(schema, node)
        if "anyOf" in node:
            node = next(option for option in node["anyOf"] if option.get("type") != "null")
        node = resolve(schema, node)["properties"][key]
    assert unit in node["description"]


def test_file_required_keys_have_no_default(schema):
    material = schema["$defs"]["Material"]
    assert set(material["required"]) == {"lame_lambda", "lame_mu"}
    assert "default" not in material["properties"]["lame_mu"]
    assert {"radius", "entry", "turn", "step"} <= set(schema["$defs"]["Needle"]["required"])


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_shipped_scenarios_satisfy_the_schema_and_the_models(schema, path):
    load_scenario(path)
    assert problems(schema, schema, yaml.safe_load(path.read_text())) == []


def test_the_check_refuses_what_the_schema_forbids(schema, slab_raw):
    """The validator above can fail: unknown keys, choices, bounds, types."""
    raw = copy.deepcopy(slab_raw)
    raw["colour"] = "red"
    raw["tissue"]["material"]["model"] = "mooney-rivlin"
    raw["tissue"]["thickness"] = -1.0
    raw["load_steps"] = "ten"
    raw["needle"] = {"radius": 8.88, "entry": [0.0, 30.0], "turn": "up", "step": 0.8}
    assert sorted(problems(schema, schema, raw)) == [
        "scenario.colour: unknown key",
        "scenario.load_steps: not integer",
        "scenario.needle.step: breaks maximum 0.5",
        "scenario.needle.turn: 'up' not in ['cw', 'ccw']",
        "scenario.tissue.material.model: 'mooney-rivlin' not in ['saint-venant-kirchhoff', 'neo-hookean']",
        "scenario.tissue.thickness: breaks exclusiveMinimum 0",
        "scenario.tissue.thickness: breaks minimum 0.001",
    ]


@pytest.mark.parametrize("change, field", [
    (lambda raw: raw["tissue"].update(thickness=5e-4), "tissue.thickness"),
    (lambda raw: raw["tissue"].update(thickness=2e4), "tissue.thickness"),
    (lambda raw: raw["loads"][0].update(force=None, displacement=[2e4, 0.0]), "loads[0].displacement[0]"),
    (lambda raw: raw["loads"][0].update(force=None, displacement=[0.0, -2e4]), "loads[0].displacement[1]"),
    (lambda raw: raw.update(needle={"radius": 0.01, "entry": [0.0, 30.0], "turn": "cw", "step": 0.1}),
     "needle.radius"),
])
def test_the_schema_states_the_bounds_the_tool_enforces(schema, slab_raw, change, field):
    """A thickness of 0.0005 mm passed the schema (exclusiveMinimum 0) and the tool refused it;
    a displacement had no bound in either, and 1e300 mm failed in the first load step."""
    raw = copy.deepcopy(slab_raw)
    change(raw)
    with pytest.raises(ScenarioError) as error:
        parse_scenario(raw)
    assert [line.split(":")[0] for line in error.value.lines] == [field]
    assert problems(schema, schema, raw), field
    within = copy.deepcopy(slab_raw)
    within["loads"][0].update(force=None, displacement=[1e4, -1e4])
    within["tissue"]["thickness"] = 1e-3
    parse_scenario(within)
    assert problems(schema, schema, within) == []


def test_the_schema_gives_no_default_a_file_does_not_get(schema):
    """A file without a spacing gets one from its tissue and needle (min(W, H)/20, 2r/5 with a
    needle), and a needle scene a needle_refinement of 2: the schema said 5.0 and null."""
    properties = schema["$defs"]["Discretization"]["properties"]
    assert "default" not in properties["spacing"] and "default" not in properties["needle_refinement"]
    assert "min(W, H)/20" in properties["spacing"]["description"]
    assert properties["dilation"]["default"] == 2.0  # the defaults a file does get stay


def test_the_schema_refuses_a_load_of_both_kinds_and_an_edge_clamped_twice(schema, slab_raw):
    """As the tool does: a load gives exactly one of force and displacement, a hole and a
    region one of polygon and circle, and an edge is clamped at most once (the schema let all
    of them through, so an editor's check disagreed with the command)."""
    raw = copy.deepcopy(slab_raw)
    raw["tissue"]["clamped"] = ["right", "right"]
    raw["tissue"]["holes"] = [{"polygon": [[40, 20], [60, 20], [50, 30]], "circle": {"center": [50, 50], "radius": 5}}]
    raw["tissue"]["regions"] = [{"material": raw["tissue"]["material"]}]
    raw["loads"] = [{**raw["loads"][0], "displacement": [1.0, 0.0], "force": [1.0, 0.0]},
                    {"segment": raw["loads"][0]["segment"]}]
    assert sorted(problems(schema, schema, raw)) == [
        "scenario.loads[0]: matches 2 of oneOf [['force'], ['displacement']]",
        "scenario.loads[1]: matches 0 of oneOf [['force'], ['displacement']]",
        "scenario.tissue.clamped: breaks uniqueItems",
        "scenario.tissue.holes[0]: matches 2 of oneOf [['polygon'], ['circle']]",
        "scenario.tissue.regions[0]: matches 0 of oneOf [['polygon'], ['circle']]",
    ]
    jsonschema = pytest.importorskip("jsonschema")
    errors = sorted(jsonschema.Draft202012Validator(schema).iter_errors(raw), key=lambda e: list(e.absolute_path))
    assert [list(error.absolute_path) for error in errors] == [
        ["loads", 0], ["loads", 1], ["tissue", "clamped"], ["tissue", "holes", 0], ["tissue", "regions", 0]]


def test_the_schema_wants_exactly_one_of_size_and_outline(schema, slab_raw):
    """As the tool does (`tissue.size: got both`): the schema let a tissue with both, or with
    neither, through."""
    both = copy.deepcopy(slab_raw)
    both["tissue"]["outline"] = [[0, 0], [100, 0], [100, 60], [0, 60]]
    neither = copy.deepcopy(slab_raw)
    del neither["tissue"]["size"]
    assert problems(schema, schema, both) == ["scenario.tissue: matches 2 of oneOf [['size'], ['outline']]"]
    assert problems(schema, schema, neither) == ["scenario.tissue: matches 0 of oneOf [['size'], ['outline']]"]
    jsonschema = pytest.importorskip("jsonschema")
    for raw in (both, neither):
        assert [list(e.absolute_path) for e in jsonschema.Draft202012Validator(schema).iter_errors(raw)] == [["tissue"]]


def test_jsonschema_agrees_when_installed(schema, slab_raw):
    jsonschema = pytest.importorskip("jsonschema")
    for path in CONFIGS:
        jsonschema.validate(yaml.safe_load(path.read_text()), schema)
    slab_raw["tissue"]["colour"] = "red"
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(slab_raw, schema)


def test_a_study_block_the_tool_accepts_satisfies_the_schema(schema, slab_raw):
    """Families and the reference may go without a name (the tool names them) and give one
    spacing as a number: the schema said `name` was required and `spacing` a list."""
    raw = copy.deepcopy(slab_raw)
    raw["needle"] = {"radius": 8.88, "entry": [0.0, 30.0], "turn": "cw", "step": 0.1}
    raw["study"] = {"spacing": [3.0, 2.0], "families": [{"grading": 2}, {"spacing": 4.0, "dilation": 1.5}],
                    "reference": {"grading": 4, "spacing": 0.5}}
    scenario = parse_scenario(raw)
    assert [f.name for f in scenario.study.families] == ["family 1", "family 2"]
    assert scenario.study.families[1].spacing == (4.0,) and scenario.study.reference.name == "reference"
    assert problems(schema, schema, raw) == []
