"""Input files: YAML in, validated typed configuration out.

Modules, each importing only those before it (and stitchplan.errors, stitchplan.geometry):

- messages: validation errors as lines, `<field>: got <value>, expected <what>`;
- fields: finite numbers with bounds and units, integers, choices, points;
- yaml_files: reading YAML (duplicate keys, merge keys, alias bombs and non-UTF-8 text refused);
- boundary_points: points a file places on the boundary, moved onto it within the input
  tolerance or refused naming the nearest boundary point;
- tissue_shape: a tissue's outline, holes, regions and clamps made into the shape the model
  uses, or the problems that stop it;
- blocks: tissue, material, discretization, needle, loads, solver;
- plan_blocks: planner, robot;
- load_checks: loads off the clamped edges and apart from each other, a slab held in place;
- study: the optional `study:` block;
- scenario: the scenario file and Scenario, default spacing, load_scenario;
- schema: the JSON Schema of scenario files;
- calibration: the `calibrate material` input file (imported by its command only: a
  scenario's commands need not build its models);
- uncertainty: the `plan --uncertainty` file (and a `calibrate material` output it reads).
"""

from .blocks import (
    Discretization,
    Load,
    Material,
    Needle,
    Solver,
    Tissue,
    parse_discretization,
)
from .fields import EDGES, INTEGRATIONS, LINEAR_SOLVERS, MATERIAL_MODELS, TIP_TRACKING
from .messages import input_error
from .plan_blocks import Planner, Robot
from .scenario import (
    DEFAULT_NEEDLE_REFINEMENT,
    Scenario,
    ScenarioError,
    ScenarioFile,
    default_spacing,
    load_scenario,
    parse_material,
    parse_needle,
    parse_scenario,
    with_discretization,
)
from .schema import scenario_schema
from .study import StudyFamily, StudySpec, parse_study
from .yaml_files import read_yaml

__all__ = [
    "DEFAULT_NEEDLE_REFINEMENT",
    "EDGES",
    "INTEGRATIONS",
    "LINEAR_SOLVERS",
    "MATERIAL_MODELS",
    "TIP_TRACKING",
    "Discretization",
    "Load",
    "Material",
    "Needle",
    "Planner",
    "Robot",
    "Scenario",
    "ScenarioError",
    "ScenarioFile",
    "Solver",
    "StudyFamily",
    "StudySpec",
    "Tissue",
    "default_spacing",
    "input_error",
    "load_scenario",
    "parse_discretization",
    "parse_material",
    "parse_needle",
    "parse_scenario",
    "parse_study",
    "read_yaml",
    "scenario_schema",
    "with_discretization",
]

