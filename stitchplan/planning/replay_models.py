"""The models a plan's and a simulation's replays run on, and what decides which run, from
the scenario alone: this module imports no numerics (scipy, the solvers), so that `plan`
settles them and passes the resource guard before it imports those, and hands its replay
helper the refined model to build while it imports (stitchplan/early_helper.py `hand`,
cli.commands.plan). planning/verification.py runs the replays.
"""

from __future__ import annotations

from ..config import Scenario, with_discretization
from ..needle.geometry import scenario_needle

VERIFICATION_FACTOR = 0.5  # refined spacing / planning spacing
ESTIMATE_FACTOR = 2.0  # the exit error estimate's second run: its spacing / the run's


def rescaled(scenario: Scenario, factor: float) -> Scenario:
    """The scenario with every particle spacing scaled by `factor` (a graded arrangement
    scales as a whole)."""
    discretization = scenario.discretization
    changes = {"spacing": discretization.spacing * factor}
    if discretization.needle_spacing is not None and discretization.needle_refinement is None:
        changes["needle_spacing"] = discretization.needle_spacing * factor
    return with_discretization(scenario, **changes)


def replay_scenario(scenario: Scenario, verify: bool) -> Scenario:
    """The model a plan replays its trajectory on (planning.verification.plan_verified): the
    refined one with `verify`, else the one at 2h (the exit error estimate's, and the
    predicted aim's)."""
    return rescaled(scenario, VERIFICATION_FACTOR if verify else ESTIMATE_FACTOR)


def replay_options(options: dict) -> dict:
    """run_insertion's options for a replay on another model: not the step and ramp
    callbacks, nor the dense condition numbers."""
    return {key: value for key, value in options.items() if key not in ("on_step", "on_ramp", "condition_numbers")}


def aims_at_bites(scenario: Scenario) -> bool:
    """Whether the plan aims at equal bites: planner.target symmetric on a stitch across a
    wound, where the scenario's undeformed needle circle crosses a wound or a hole (elsewhere the
    target means the exit)."""
    return scenario.planner.target == "symmetric" and bool(scenario_needle(scenario).wounds)


def predicts_aim(scenario: Scenario, verify: bool = True) -> bool:
    """Whether a verified plan predicts the refined model's offset from a replay of its
    first pass at 2h (planning/verification.py, predicted aim)."""
    return verify and scenario.planner.predicted_aim and not aims_at_bites(scenario)
