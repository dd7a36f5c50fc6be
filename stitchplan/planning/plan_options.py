"""What a plan is asked for beyond its scenario file (`plan`'s --base-transform, --angular-speed
and --strict), set on the scenario before the plan is guarded and run. Imports no numerics:
`plan` settles its scenario before it imports them (planning/replay_models.py)."""

from __future__ import annotations

from dataclasses import replace

from ..config import Scenario
from ..config.plan_blocks import speed_problem
from ..errors import InputError


def with_plan_options(scenario: Scenario, base_transform: tuple[float, tuple[float, float]] | None = None,
                      angular_speed: float | None = None, strict: bool = False) -> Scenario:
    """The scenario with the robot's base frame (ROTATION_DEG, (TX_MM, TY_MM)) and needle speed
    for trajectory.csv replaced where given, and its planner strict if either the file or
    `strict` asks for it."""
    robot = scenario.robot
    if base_transform is not None:
        robot = replace(robot, rotation_deg=base_transform[0], translation=base_transform[1], given=True)
    if angular_speed is not None:
        expected = speed_problem(angular_speed, scenario.needle.step) if scenario.needle is not None else None
        if expected is not None:
            raise InputError(f"--angular-speed: got {angular_speed!r}, expected {expected}")
        robot = replace(robot, angular_speed=angular_speed)
    return replace(scenario, robot=robot, planner=replace(scenario.planner, strict=scenario.planner.strict or strict))
