"""The needle-centre trajectory a manipulator follows: rows, frames, timestamps, replay.

One row per needle step n = 0 .. N+1: the needle rotation n * step since entry, the
needle centre O(t_n) and the rigid needle's tip, in the tissue frame; row N+1 is the step
during which the tip leaves the tissue (the centre stays at O(t_N)). Optional columns: the
same points in the robot base frame and a timestamp from the needle's angular speed.
"""

from __future__ import annotations

import math

import numpy as np

from ..config import Robot
# the bounds of the robot's frame and speed (the robot block checks a file's, cli.options the options')
from ..config.plan_blocks import MAX_BASE_OFFSET_MM, MIN_ANGULAR_SPEED
from ..errors import InputError, NumericalFailure
from ..needle.results import InsertionResult

COLUMNS = ["step", "angle_rad", "center_x_mm", "center_y_mm", "tip_x_mm", "tip_y_mm"]
BASE_COLUMNS = ["base_center_x_mm", "base_center_y_mm", "base_tip_x_mm", "base_tip_y_mm"]
DECIMALS_MM = 9  # coordinates are rounded to 1e-9 mm: no round-off noise (5e-16) for a robot
DECIMALS_ANGLE = 12  # angles (rad) and times (s) to 1e-12: 2.8, not n x 0.08 = 2.8000000000000003


def _clean(values: np.ndarray, decimals: int = DECIMALS_MM) -> np.ndarray:
    """Rounded to `decimals` decimals (numpy divides by 10**decimals: the nearest double to
    the decimal), with -0.0 made 0.0."""
    return np.round(np.asarray(values, dtype=float), decimals) + 0.0


def exported_center(center: np.ndarray) -> np.ndarray:
    """A centre as trajectory.csv writes it."""
    return _clean(center)


def _centers(result: InsertionResult) -> np.ndarray:
    """O(t_0) .. O(t_N) and the exit step's row, which keeps O(t_N), (N + 2, 2)."""
    centers = [result.geometry.center] + [s.center for s in result.steps]
    return np.asarray(centers + centers[-1:])


def exported_centers(result: InsertionResult) -> np.ndarray:
    """The centre columns of trajectory.csv, as written (N + 2, 2)."""
    return _clean(_centers(result))


def trajectory_table(result: InsertionResult, robot: Robot) -> tuple[list[str], np.ndarray]:
    """The columns and rows (N + 2, columns) of trajectory.csv; a table holding inf or nan
    is refused (_refuse_non_finite), so a robot never reads one."""
    geometry = result.geometry
    centers = _centers(result)
    steps = np.arange(len(centers))
    angles = steps * geometry.step
    tips = geometry.tips_along(centers)
    with np.errstate(over="ignore", invalid="ignore"):  # an overflow is inf, refused below by its column
        if robot.given:
            base_centers, base_tips = _clean(to_base_frame(centers, robot)), _clean(to_base_frame(tips, robot))
        centers, tips = _clean(centers), _clean(tips)
        columns = list(COLUMNS)
        table = [steps, _clean(angles, DECIMALS_ANGLE), centers[:, 0], centers[:, 1], tips[:, 0], tips[:, 1]]
        if robot.angular_speed is not None:
            columns.append("time_s")
            table.append(_clean(angles / robot.angular_speed, DECIMALS_ANGLE))
    if robot.given:
        columns += BASE_COLUMNS
        table += [base_centers[:, 0], base_centers[:, 1], base_tips[:, 0], base_tips[:, 1]]
    table = np.column_stack(table)
    _refuse_non_finite(columns, table, robot)
    return columns, table


def _refuse_non_finite(columns: list[str], table: np.ndarray, robot: Robot) -> None:
    """The first column holding inf or nan, named with its first such step and what made it:
    the robot's speed or base transform beyond their bounds (an input), else the planned
    path itself (a numerical failure)."""
    bad = ~np.isfinite(table)
    if not bad.any():
        return
    column = int(np.flatnonzero(bad.any(axis=0))[0])
    step = int(np.flatnonzero(bad[:, column])[0])
    name = columns[column]
    found = f"trajectory: step {step}, {name}: got {table[step, column]:g}, expected a finite number"
    if name == "time_s":
        raise InputError(f"{found}; angle_rad {table[step, 1]:g} rad / angular speed {robot.angular_speed:g} "
                         f"rad/s overflows (expected a speed of at least {MIN_ANGULAR_SPEED:g} rad/s)")
    if name in BASE_COLUMNS:
        offset = ", ".join(f"{value:g}" for value in robot.translation)
        raise InputError(f"{found}; the base transform's offset [{offset}] mm overflows (expected offsets "
                         f"within +-{MAX_BASE_OFFSET_MM:g} mm)")
    raise NumericalFailure(f"{found}: the planned needle path is not finite")


def to_base_frame(points: np.ndarray, robot: Robot) -> np.ndarray:
    """p_base = R p + t, R the rotation by robot.rotation_deg about the slab normal."""
    angle = math.radians(robot.rotation_deg)
    rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    return points @ rotation.T + np.asarray(robot.translation)

