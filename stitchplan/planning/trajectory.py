"""The needle-centre trajectory a manipulator follows: rows, frames, timestamps, replay.

One row per needle step n = 0 .. N+1: the needle rotation n * step since entry, the
needle centre O(t_n) and the rigid needle's tip, in the tissue frame; row N+1 is the step
during which the tip leaves the tissue (the centre stays at O(t_N)). Optional columns: the
same points in the robot base frame and a timestamp from the needle's angular speed.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from ..config import Robot, ScenarioError
from ..needle.insertion import InsertionResult

COLUMNS = ["step", "angle_rad", "center_x_mm", "center_y_mm", "tip_x_mm", "tip_y_mm"]
BASE_COLUMNS = ["base_center_x_mm", "base_center_y_mm", "base_tip_x_mm", "base_tip_y_mm"]


def trajectory_table(result: InsertionResult, robot: Robot) -> tuple[list[str], np.ndarray]:
    geometry = result.geometry
    centers = [geometry.center] + [s.center for s in result.steps]
    centers.append(centers[-1])  # the exit step keeps the last centre
    centers = np.asarray(centers)  # (N + 2, 2)
    steps = np.arange(len(centers))
    angles = steps * geometry.step
    tips = np.asarray([geometry.tip(a, c) for a, c in zip(angles, centers)])
    columns = list(COLUMNS)
    table = [steps, angles, centers[:, 0], centers[:, 1], tips[:, 0], tips[:, 1]]
    if robot.angular_speed is not None:
        columns.append("time_s")
        table.append(angles / robot.angular_speed)
    if robot.given:
        columns += BASE_COLUMNS
        base_centers = to_base_frame(centers, robot)
        base_tips = to_base_frame(tips, robot)
        table += [base_centers[:, 0], base_centers[:, 1], base_tips[:, 0], base_tips[:, 1]]
    return columns, np.column_stack(table)


def to_base_frame(points: np.ndarray, robot: Robot) -> np.ndarray:
    """p_base = R p + t, R the rotation by robot.rotation_deg about the slab normal."""
    angle = math.radians(robot.rotation_deg)
    rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    return points @ rotation.T + np.asarray(robot.translation)


def read_center_path(path: str | Path) -> np.ndarray:
    """Centres (n, 2) from a trajectory CSV (columns step, center_x_mm, center_y_mm), row n = step n."""
    path = Path(path)
    try:
        with path.open(newline="") as handle:
            reader = csv.DictReader(handle)
            header = reader.fieldnames or []
            needed = ["step", "center_x_mm", "center_y_mm"]
            missing = [c for c in needed if c not in header]
            if missing:
                raise ScenarioError(f"{path}: columns {header} lack {missing}; expected at least "
                                    f"{', '.join(needed)} (a trajectory written by `stitchplan plan`)")
            rows = list(reader)
    except OSError as error:
        raise ScenarioError(f"{path}: cannot be read ({error.strerror or error})") from None
    try:
        steps = [int(float(r["step"])) for r in rows]
        centers = np.array([[float(r["center_x_mm"]), float(r["center_y_mm"])] for r in rows])
    except (TypeError, ValueError):
        raise ScenarioError(f"{path}: a step or centre value is not a number; expected numbers") from None
    if not rows or steps != list(range(len(rows))):
        raise ScenarioError(f"{path}: steps {steps[:5]}... expected 0, 1, 2, ... one row per step")
    return centers
