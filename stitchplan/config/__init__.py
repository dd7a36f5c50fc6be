"""Scenario files: YAML in, validated typed configuration out."""

from .scenario import *  # noqa: F401,F403
from .scenario import _point, _required  # noqa: F401
from .scenario import (DEFAULT_NEEDLE_REFINEMENT, EDGES, INTEGRATIONS, LINEAR_SOLVERS,  # noqa: F401
                       MATERIAL_MODELS, TIP_TRACKING, Discretization, Load, Material, Needle, Planner,
                       Robot, Scenario, ScenarioError, Solver, Tissue, _choice, _fail, _integer, _mapping,
                       _number, default_spacing, load_scenario, parse_discretization, parse_scenario,
                       read_yaml, with_discretization)
