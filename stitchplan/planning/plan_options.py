"""What a plan is asked for beyond its scenario file (`plan`'s --base-transform, --angular-speed
and --strict), set on the scenario before the plan is guarded and run. Imports no numerics:
`plan` settles its scenario before it imports them (planning/replay_models.py)."""

from __future__ import annotations

from dataclasses import replace

from ..config import Scenario


def with_plan_options(scenario: Scenario, base_transform: tuple[float, tuple[float, float]] | None = None,
                      angular_speed: float | None = None, strict: bool = False) -> Scenario:
    """The scenario with the robot's base frame (ROTATION_DEG, (TX_MM, TY_MM)) and needle speed
    for trajectory.csv replaced where given, and its planner strict if either the file or
    `strict` asks for it."""
    robot = scenario.robot
    if base_transform is not None:
        robot = replace(robot, rotation_deg=base_transform[0], translation=base_transform[1], given=True)
    if angular_speed is not None:
        robot = replace(robot, angular_speed=angular_speed)
    return replace(scenario, robot=robot, planner=replace(scenario.planner, strict=scenario.planner.strict or strict))
